"""Training, model artifact, Optuna resume, the train/predict commands.

Data: ``surrogate.features.synthetic_collisions`` — a TEST FIXTURE of analytic frictionless
impacts with restitution 0.9 (docs/physics/references.md "Binary collision outcome"), not DEM.
References: the trivial baseline (train-mean velocity), momentum conservation, XGBoost's
own predict, the analytic outcome.
"""

import io
import json
import os
import shutil

import numpy as np
import pytest

pytest.importorskip("xgboost")
pytest.importorskip("optuna")

from hel_warp.errors import ConfigError, HelWarpError
from surrogate.artifact import load_artifact
from surrogate.features import CollisionData, standardize, synthetic_collisions, validate_data, write_synthetic_zarr
from surrogate.train import TrainConfig, run_study, train

QUICK = {"n_estimators": (20, 150), "max_depth": (3, 7)}  # a cheap search space for the tests


@pytest.fixture(scope="module")
def contact_model(tmp_path_factory):
    root = tmp_path_factory.mktemp("contact")
    data = synthetic_collisions(1500, seed=21)
    meta = train(data, str(root / "model"), TrainConfig(form="contact", trials=3, progress=False, jobs=1,
                                                                      search_space=QUICK),
                 log=lambda *_: None)
    return str(root / "model"), data, meta


def test_quick_training_beats_the_mean_by_far_and_conserves_momentum(contact_model):
    model_dir, _, meta = contact_model
    metrics = json.load(open(os.path.join(model_dir, "metrics.json")))
    assert metrics == meta["metrics"]
    assert metrics["form"] == "contact" and metrics["n_test"] == 75
    for k in "uvw":
        assert metrics["mae"][k] < 0.05 * metrics["baseline_mae"][k]
    # equal and opposite impulses: momentum exact to float64 round-off
    assert metrics["momentum_rel_error_max"] < 1e-6
    assert metrics["forest_vs_xgboost_max_abs_diff"] <= 1e-5
    for name in ("parity.png", "relative_error.png", "metrics.json"):
        assert os.path.getsize(os.path.join(model_dir, "report", name)) > 1000 or name == "metrics.json"


def test_the_artifact_states_its_training_domain(contact_model):
    """metadata.json and forest.json carry the ranges of the train rows' features (recomputed here from
    the data and the split), the material friction and the Coulomb bound; the guard's counts are in metrics."""
    from hel_warp.collisions.forest import load_forest
    from surrogate.features import CANONICAL_FEATURES, form_rows
    from surrogate.train import split_groups

    model_dir, data, meta = contact_model
    rows = form_rows("contact", data)
    _, train_g, _ = split_groups(len(data), 0)
    x = rows.features[train_g]
    flat = load_forest(model_dir)
    assert meta["domain"]["features"] == list(CANONICAL_FEATURES["contact"]) == flat.domain["features"]
    np.testing.assert_array_equal(flat.feature_lo, x.min(axis=0))
    np.testing.assert_array_equal(flat.feature_hi, x.max(axis=0))
    assert meta["domain"]["lo"] == flat.domain["lo"] and meta["domain"]["hi"] == flat.domain["hi"]
    # the fixture is frictionless (b = 0 up to float64 round-off): the bound is max(mu = 0, largest b/a),
    # never below any row's b/a (a bound that clipped the data would be wrong)
    a, b = rows.targets[:, 0], rows.targets[:, 1]
    ratio = np.max(b[a >= 1e-4] / a[a >= 1e-4])
    assert flat.domain["friction"] == 0.0 and ratio <= flat.friction_bound <= max(0.0, ratio) * (1 + 1e-6) + 1e-30
    assert flat.friction_bound < 1e-12
    guard = meta["metrics"]["guard"]
    assert guard["calls"] == meta["metrics"]["n_test"]
    for key in ("fraction_clamped", "fraction_separation", "fraction_coulomb", "fraction_energy", "material_fraction"):
        assert 0.0 <= guard[key] <= 1.0
    # flagged when the guard contradicts the DEM (analytic rows here: never), not for bringing the raw model back
    assert guard["flagged"] == (max(guard["farther_fraction"], guard["dem_needs_fraction"]) > guard["flag_fraction"])


def test_paper_form_beats_the_mean(tmp_path):
    data = synthetic_collisions(1000, seed=5, central_fraction=1.0)
    meta = train(data, str(tmp_path / "paper"), TrainConfig(form="paper", trials=2, progress=False, jobs=1,
                                                             report=False, search_space=QUICK), log=lambda *_: None)
    m = meta["metrics"]
    assert meta["features"] == ["v1x", "v1y", "v1z", "v2x", "v2y", "v2z"]  # d, rho constant: dropped
    assert m["n_test_rows"] == 2 * m["n_test"]  # swapped twins stay in the test set
    for k in "uvw":
        assert m["mae"][k] < 0.3 * m["baseline_mae"][k]


def test_one_job_at_a_time_reproduces_the_model_for_a_seed(contact_model, tmp_path):
    """With jobs=1 the search and the fits follow the seed alone: the same command gives the same forest (with
    trials side by side the order in which they finish steers the sampler, so runs may differ)."""
    model_dir, data, _ = contact_model
    train(data, str(tmp_path / "again"), TrainConfig(form="contact", trials=3, progress=False, jobs=1,
                                                     search_space=QUICK), log=lambda *_: None)
    first = open(os.path.join(model_dir, "forest.json"), "rb").read()
    assert open(tmp_path / "again" / "forest.json", "rb").read() == first


def test_artifact_round_trip_equals_xgboost(contact_model):
    model_dir, data, meta = contact_model
    art = load_artifact(model_dir, boosters=True)
    assert art.form == "contact" and art.features == meta["features"] and art.targets == ["impulse_n", "impulse_t"]
    assert art.metadata["dataset_hash"] == data.dataset_hash
    from hel_warp.collisions.forest import ForestPredictor, load_forest
    from surrogate.features import form_rows

    rows = form_rows("contact", data)
    out = ForestPredictor(load_forest(model_dir)).predict_features(rows.features)
    np.testing.assert_allclose(out, art.predict(rows.features), rtol=1e-5, atol=1e-5)


def test_corrupted_truncated_and_mismatched_artifacts(contact_model, tmp_path):
    model_dir, _, meta = contact_model
    bad = tmp_path / "bad"
    shutil.copytree(model_dir, bad)
    with pytest.raises(ConfigError, match="feature mismatch"):
        load_artifact(str(bad), expect_features=["g_n", "g_t"])
    with pytest.raises(ConfigError, match="different data set"):
        load_artifact(str(bad), expect_dataset_hash="0" * 64)
    model_file = bad / "impulse_n.json"
    text = model_file.read_text()
    model_file.write_text(text[: len(text) // 3])  # truncated
    with pytest.raises(ConfigError, match="sha256"):
        load_artifact(str(bad))
    # truncated, with a forged matching hash: XGBoost's own parser refuses it
    from surrogate.artifact import sha256_file

    meta_path = bad / "metadata.json"
    forged = json.loads(meta_path.read_text())
    forged["files"]["impulse_n.json"] = sha256_file(str(model_file))
    meta_path.write_text(json.dumps(forged))
    with pytest.raises(ConfigError, match="XGBoost cannot load"):
        load_artifact(str(bad), boosters=True)
    meta_path.write_text(json.dumps(forged)[:100])
    with pytest.raises(ConfigError, match="not valid JSON"):
        load_artifact(str(bad))
    forged["features"] = ["g_n", "v1x"]
    meta_path.write_text(json.dumps(forged))
    with pytest.raises(ConfigError, match="not features"):
        load_artifact(str(bad))


def test_nan_inf_and_empty_data_are_refused(tmp_path):
    data = synthetic_collisions(200, seed=1)
    for value in (np.nan, np.inf):
        broken = CollisionData(data.inputs.copy(), data.outputs.copy())
        broken.inputs[7, 2] = value
        with pytest.raises(ConfigError, match="NaN or infinite.*row 7"):
            train(broken, str(tmp_path / "m"), TrainConfig(trials=1, progress=False))
    with pytest.raises(ConfigError, match="empty"):
        validate_data(CollisionData(np.zeros((0, 14)), np.zeros((0, 15))))
    with pytest.raises(ConfigError, match="need at least"):
        train(synthetic_collisions(10, seed=1), str(tmp_path / "m"), TrainConfig(trials=1, progress=False))


def test_interrupted_study_resumes_to_the_total(tmp_path):
    import optuna

    rng = np.random.default_rng(0)
    x = rng.normal(size=(300, 3)).astype(np.float32)
    y = x[:, 0] + 0.5 * x[:, 1] ** 2
    storage = f"sqlite:///{tmp_path / 'study.db'}"
    kw = dict(study_name="contact-impulse_n", storage=storage, progress=False, dataset_hash="abc",
              search_space={"n_estimators": (20, 60), "max_depth": (2, 4)})
    run_study(x[:200], y[:200], x[200:], y[200:], trials=2, **kw)  # "interrupted" after 2
    study = run_study(x[:200], y[:200], x[200:], y[200:], trials=4, **kw)  # the rerun continues
    finished = [t for t in study.trials if t.state.is_finished()]
    assert len(finished) == 4
    assert len(optuna.load_study(study_name="contact-impulse_n", storage=storage).trials) == 4
    again = run_study(x[:200], y[:200], x[200:], y[200:], trials=4, **kw)  # nothing left to do
    assert len(again.trials) == 4
    with pytest.raises(ConfigError, match="another data set"):
        run_study(x[:200], y[:200], x[200:], y[200:], trials=5, **dict(kw, dataset_hash="xyz"))


def test_train_and_predict_commands(tmp_path, monkeypatch, capsys):
    from hel_warp.cli import main

    write_synthetic_zarr(str(tmp_path / "ds"), 800, seed=3)
    model = str(tmp_path / "model")
    assert main(["train", "--data", str(tmp_path / "ds"), "--out", model, "--trials", "2", "--jobs", "1",
                 "--no-progress", "--no-report", "--json"]) == 0
    metrics = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(metrics["mae"]) == {"u", "v", "w"} and metrics["n_test"] == 40
    # head-on central impact of equal spheres, e = 0.9: v1' = -0.9, v2' = +0.9 (analytic)
    lines = ['{"v1": [1, 0, 0], "v2": [-1, 0, 0], "normal": [1, 0, 0]}',
             '{"v1": [0, 3, 0], "v2": [0, 0, 0], "normal": [0, 1, 0], "d1": 3.15e-4, "d2": 3.15e-4}']
    monkeypatch.setattr("sys.stdin", io.StringIO("\n".join(lines) + "\n"))
    assert main(["predict", "--model", model, "--json"]) == 0
    captured = capsys.readouterr()
    out = [json.loads(line) for line in captured.out.strip().splitlines()]
    assert len(out) == 2
    v1, v2 = np.array(out[0]["velocity1_after"]), np.array(out[0]["velocity2_after"])
    np.testing.assert_allclose(v1 + v2, 0.0, atol=1e-6)  # momentum of equal masses
    # the synthetic data hold e = 0.9 at every impact, so the forest learns a constant: float32 round-off of the
    # targets and the contact frame bounds the error (1e-5 of |g| = 2 m/s)
    assert abs(v1[0] + 0.9) < 2e-5
    assert "2 pairs" in captured.err and "guard corrections" in captured.err  # the engine's guarded path, with its counts
    monkeypatch.setattr("sys.stdin", io.StringIO('{"v1": [1, 0, 0], "v2": [0, 0, 0]}\n'))
    assert main(["predict", "--model", model, "--json"]) == 2
    assert "normal" in capsys.readouterr().err
    assert main(["predict", "--model", str(tmp_path / "nowhere")]) == 2
    assert main(["train", "--data", str(tmp_path / "nowhere"), "--out", model]) == 2
    assert main(["train", "--data", str(tmp_path / "ds"), "--out", model, "--search-space", "{bad"]) == 2
    assert "--search-space" in capsys.readouterr().err
    assert issubclass(ConfigError, HelWarpError)


def test_targets_fitted_per_incidence_need_fewer_trees_for_the_same_error(tmp_path):
    """The same small forest (20 trees of depth 4) fits impulse_n (about (1 + e) cos_angle) better per cos_angle than
    as it is: XGBoost's own test MAE of the target, scaled fit against unscaled, on the same split; both files state
    what their forest multiplies by."""
    from hel_warp.collisions.forest import load_forest

    data = synthetic_collisions(3000, seed=5, central_fraction=0.2)
    fixed = {"n_estimators": (20, 20), "max_depth": (4, 4), "learning_rate": (0.3, 0.3)}
    mae = {}
    for scaled in (True, False):
        out = str(tmp_path / f"scaled_{scaled}")
        meta = train(data, out, TrainConfig(form="contact", trials=1, progress=False, jobs=1, report=False,
                                            search_space=fixed, target_scale=scaled), log=lambda *_: None)
        mae[scaled] = meta["metrics"]["targets"]["impulse_n"]["mae"]
        assert meta["target_scale"] == (["cos_angle", "sin_angle"] if scaled else None)
        assert load_forest(out).target_scale == meta["target_scale"]
        assert meta["metrics"]["forest_vs_xgboost_max_abs_diff"] <= 1e-5
    print(f"impulse_n test MAE, 20 trees of depth 4: per cos_angle {mae[True]:.2e}, as it is {mae[False]:.2e}")
    assert mae[True] < 0.5 * mae[False], mae


def test_a_forest_file_with_a_bad_target_scale_is_refused(contact_model):
    from hel_warp.collisions.forest import parse_forest

    model_dir, _, _ = contact_model
    doc = json.load(open(os.path.join(model_dir, "forest.json")))
    for bad in (["cos_angle"], ["cos_angle", "tan_angle"], "cos_angle"):
        doc["target_scale"] = bad
        with pytest.raises(ConfigError, match="target_scale"):
            parse_forest(doc)

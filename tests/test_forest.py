"""The flattened forest in Warp against XGBoost's own predict (the independent reference).

Reference: ``Booster.predict`` on the standardised float32 features (eq. 17) — the
flattened forest must give the same value up to float32 summation order (1e-5), because
the folded thresholds take exactly the branch XGBoost takes (surrogate/flatten.py).
Data: the analytic frictionless impacts of ``surrogate.features.synthetic_collisions``
(a TEST FIXTURE, not DEM).
"""

import json

import numpy as np
import pytest

xgb = pytest.importorskip("xgboost")

from hel_warp.errors import ConfigError
from hel_warp.collisions.forest import ForestPredictor, load_forest, parse_forest
from kernels.forest import Forest as kf_Forest
from surrogate.features import (CANONICAL_FEATURES, apply_contact_model, form_rows, sphere_mass, standardize,
                                synthetic_collisions, used_features)
from surrogate.admissibility import training_domain
from surrogate.flatten import fold_thresholds, flatten_models, parse_base_score


def _fit_forest(form, data, depths, *, nan_fraction=0.0, seed=0, n_estimators=30):
    """XGBoost models (one per target, depth from ``depths``) on ``form`` rows; optional NaNs."""
    rows = form_rows(form, data)
    names = used_features(form, rows.features)
    cols = [CANONICAL_FEATURES[form].index(f) for f in names]
    raw = rows.features[:, cols].copy()
    rng = np.random.default_rng(seed)
    if nan_fraction:
        raw[rng.random(raw.shape) < nan_fraction] = np.nan
    mean = np.nanmean(raw.astype(np.float64), axis=0)
    std = np.nanstd(raw.astype(np.float64), axis=0)
    std = np.where(std > 0, std, 1.0)
    xs = standardize(raw, mean, std)
    targets = [f"t{k}" for k in range(rows.targets.shape[1])]
    boosters, models = {}, {}
    for k, target in enumerate(targets):
        model = xgb.XGBRegressor(n_estimators=n_estimators, max_depth=depths[k % len(depths)], learning_rate=0.3,
                                 tree_method="hist", n_jobs=1, random_state=seed)
        model.fit(xs, rows.targets[:, k])
        boosters[target] = model.get_booster()
        models[target] = json.loads(boosters[target].save_raw("json"))
    domain = training_domain(form, rows.features, friction=0.0, friction_bound=0.0, rule="test: frictionless fixture")
    doc = flatten_models(form, list(CANONICAL_FEATURES[form]), names, targets, models, mean, std, domain=domain)
    return rows, cols, raw, mean, std, boosters, doc


def _full_features(rows, cols, raw):
    """Canonical-width raw features with the used columns from ``raw`` (NaNs kept)."""
    full = rows.features.copy()
    full[:, cols] = raw
    return full


def _flat(doc, form):
    # the engine's targets are named by the form; the test models use t0.. names
    doc = dict(doc, targets={"paper": ["u", "v", "w"], "contact": ["impulse_n", "impulse_t"]}[form])
    return parse_forest(json.loads(json.dumps(doc)))


@pytest.mark.parametrize("layout", ["perfect", "explicit"])
# depths 1..4 and 12: the kernel reads levels 0, 1 and 2 of a padded tree without a gather and
# gathers from level 3 on, so every path of kernels/forest.py's perfect walk is taken
@pytest.mark.parametrize("form,depths", [("contact", (12, 2)), ("paper", (3, 6, 9)), ("paper", (1, 4, 2))])
def test_forest_equals_xgboost_predict(form, depths, layout):
    data = synthetic_collisions(1500, seed=11, polydisperse=True)
    rows, cols, raw, mean, std, boosters, doc = _fit_forest(form, data, depths)
    assert doc["max_depth"] == max(depths)
    n = 1001  # not a multiple of the rows walked per thread
    out = ForestPredictor(_flat(doc, form), layout=layout, rows_per_thread=7).predict_features(
        _full_features(rows, cols, raw)[:n])
    for k, booster in enumerate(boosters.values()):
        reference = booster.predict(xgb.DMatrix(standardize(raw[:n], mean, std)))
        np.testing.assert_allclose(out[:, k], reference, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("layout", ["perfect", "explicit"])
def test_missing_values_take_the_default_direction(layout):
    """NaN features go to XGBoost's learned default side; both sides must occur."""
    data = synthetic_collisions(2000, seed=4)
    rows, cols, raw, mean, std, boosters, doc = _fit_forest("contact", data, (4, 8), nan_fraction=0.15)
    flat = _flat(doc, "contact")
    split = flat.node_info >= 0
    assert set(np.unique(flat.node_info[split] & 1)) == {0, 1}  # default_left both ways
    assert np.isnan(raw).any(axis=1).mean() > 0.3
    out = ForestPredictor(flat, layout=layout).predict_features(_full_features(rows, cols, raw))
    for k, booster in enumerate(boosters.values()):
        reference = booster.predict(xgb.DMatrix(standardize(raw, mean, std)))
        np.testing.assert_allclose(out[:, k], reference, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("depths", [(12, 2), (1, 3)], ids=["deep", "shallow"])
def test_thread_per_row_forest_gives_the_block_kernels_bits_and_xgboosts_values(depths):
    """The GPU's form of the perfect-layout walk (``eval_forest_perfect_rows_kernel``: one thread per row and target,
    TREE_GROUP trees side by side, the leaves added in tree order) gives the CPU's block kernel's float32 sums bit
    for bit, with trees of mixed depths (padded to their own depths; 31 per target, not a multiple of
    TREE_GROUP), NaN features and a device row count that stops short of the batch; both equal XGBoost's predict
    to 1e-5."""
    import warp as wp

    from kernels.forest import eval_forest

    data = synthetic_collisions(1500, seed=12, polydisperse=True)
    rows, cols, raw, mean, std, boosters, doc = _fit_forest("contact", data, depths, nan_fraction=0.05,
                                                            n_estimators=31)
    flat = _flat(doc, "contact")
    forest = flat.to_device(None, layout="perfect")
    x = wp.array(_full_features(rows, cols, raw)[:777], dtype=wp.float32)
    n_targets = forest.tree_start.shape[0] - 1
    count = wp.array([700], dtype=wp.int32)
    outs = {}
    for per_row in (False, True):
        out = wp.array(np.full((x.shape[0], n_targets), np.nan, np.float32), dtype=wp.float32)
        eval_forest(forest, x, out, row_count=count, thread_per_row=per_row)
        outs[per_row] = out.numpy()
    assert np.array_equal(outs[True][:700], outs[False][:700])
    assert np.isnan(outs[True][700:]).all() and np.isnan(outs[False][700:]).all()  # past the count: not written
    for k, booster in enumerate(boosters.values()):
        reference = booster.predict(xgb.DMatrix(standardize(raw[:700], mean, std)))
        np.testing.assert_allclose(outs[True][:700, k], reference, rtol=1e-5, atol=1e-5)


def test_folded_thresholds_take_xgboosts_branch_for_every_float32():
    """x < T  <=>  float32((x - mean)/std) < t, checked on the float32 neighbours of T."""
    rng = np.random.default_rng(3)
    t = rng.normal(size=2000).astype(np.float32)
    mean = rng.normal(size=2000) * rng.choice([1e-4, 1.0, 1e3], size=2000)
    std = np.exp(rng.normal(size=2000) * 3)
    big_t = fold_thresholds(t, mean, std)
    for steps in (-2, -1, 0, 1, 2):
        x = big_t.copy()
        for _ in range(abs(steps)):
            x = np.nextafter(x, np.float32(np.sign(steps) * np.inf), dtype=np.float32)
        xs = ((x.astype(np.float64) - mean) / std).astype(np.float32)
        np.testing.assert_array_equal(x < big_t, xs < t)
    naive = (t.astype(np.float64) * std + mean).astype(np.float32)
    assert np.any(naive != big_t)  # the naive fold would disagree somewhere


def test_tree_value_walks_both_layouts():
    """The single-row tree walk used by other kernels gives the same sums in both layouts."""
    import warp as wp

    from kernels.forest import tree_value

    @wp.kernel
    def sum_trees(forest: kf_Forest, features: wp.array2d(dtype=wp.float32), out: wp.array(dtype=wp.float32)):
        row = wp.tid()
        acc = forest.base_score[0]
        for k in range(forest.tree_start[0], forest.tree_start[1]):
            acc = acc + tree_value(forest, k, features, row)
        out[row] = acc

    data = synthetic_collisions(600, seed=6)
    rows, cols, raw, mean, std, boosters, doc = _fit_forest("contact", data, (7,), nan_fraction=0.05)
    x = wp.array(_full_features(rows, cols, raw), dtype=wp.float32)
    reference = next(iter(boosters.values())).predict(xgb.DMatrix(standardize(raw, mean, std)))
    for layout in ("explicit", "perfect"):
        out = wp.zeros(x.shape[0], dtype=wp.float32)
        wp.launch(sum_trees, dim=x.shape[0], inputs=[_flat(doc, "contact").to_device(None, layout=layout), x],
                  outputs=[out])
        np.testing.assert_allclose(out.numpy(), reference, rtol=1e-5, atol=1e-5)


def test_base_score_forms():
    assert parse_base_score("[5E-1]") == 0.5
    assert parse_base_score("0.25") == 0.25
    with pytest.raises(ConfigError):
        parse_base_score("[1E0,2E0]")


def test_contact_pairs_conserve_momentum_and_match_numpy():
    """Warp pair kernels: momentum exact to float32 round-off; same as the numpy twin."""
    data = synthetic_collisions(3000, seed=8, polydisperse=True)
    rows, cols, raw, mean, std, boosters, doc = _fit_forest("contact", data, (6,))
    c = data.col
    v1 = np.column_stack([c("v1x"), c("v1y"), c("v1z")]).astype(np.float32)
    v2 = np.column_stack([c("v2x"), c("v2y"), c("v2z")]).astype(np.float32)
    n = np.column_stack([c("nx"), c("ny"), c("nz")]).astype(np.float32)
    d1, d2, rho1, rho2 = (c(k).astype(np.float32) for k in ("d1", "d2", "rho1", "rho2"))
    u1, u2 = ForestPredictor(_flat(doc, "contact")).predict_pairs(v1, v2, d1, d2, rho1, rho2, normal=n, guard=False)
    m1, m2 = sphere_mass(d1, rho1), sphere_mass(d2, rho2)
    before = m1[:, None] * v1 + m2[:, None] * v2
    after = m1[:, None] * u1.astype(np.float64) + m2[:, None] * u2
    scale = m1 * np.linalg.norm(v1, axis=1) + m2 * np.linalg.norm(v2, axis=1)
    assert np.max(np.linalg.norm(after - before, axis=1) / scale) < 1e-6
    # step by step against the numpy twins: features, forest = XGBoost on those features, impulse
    import warp as wp

    from kernels import forest as kf
    from surrogate.features import raw_features

    vec = lambda a: wp.array(a, dtype=wp.vec3)
    sca = lambda a: wp.array(a, dtype=wp.float32)
    args = (vec(v1), vec(v2), vec(n), sca(d1), sca(d2), sca(rho1), sca(rho2))
    feats = wp.zeros((len(v1), 6), dtype=wp.float32)
    kf.contact_features(*args, feats)
    reference = raw_features("contact", v1, v2, n, d1, d2, rho1, rho2)
    scale_g = np.linalg.norm(v1 - v2, axis=1)[:, None] * np.array([1, 1, 0, 0, 0, 0])
    assert_close_rows(feats.numpy(), reference, 2e-6 * (scale_g + np.abs(reference)) + 1e-7)
    feats_np = feats.numpy()
    targets = wp.zeros((len(v1), 2), dtype=wp.float32)
    forest = _flat(doc, "contact").to_device(None)  # the test run's device (conftest)
    kf.eval_forest(forest, feats, targets, rows_per_thread=16)
    xgb_targets = np.column_stack([b.predict(xgb.DMatrix(standardize(feats_np[:, cols], mean, std)))
                                   for b in boosters.values()])
    np.testing.assert_allclose(targets.numpy(), xgb_targets, rtol=1e-5, atol=1e-5)
    a1, a2 = wp.zeros(len(v1), dtype=wp.vec3), wp.zeros(len(v1), dtype=wp.vec3)
    kf.apply_contact(*args, targets, a1, a2)
    r1, r2 = apply_contact_model(v1, v2, n, d1, d2, rho1, rho2, xgb_targets)
    speed = np.maximum(np.linalg.norm(v1, axis=1), np.linalg.norm(v2, axis=1))[:, None]
    assert_close_rows(a1.numpy(), r1, 2e-6 * speed + 1e-6)
    assert_close_rows(a2.numpy(), r2, 2e-6 * speed + 1e-6)


def assert_close_rows(actual, expected, tolerance):
    bad = np.abs(actual - expected) > tolerance
    assert not bad.any(), f"{bad.any(axis=1).sum()} rows differ, worst {np.max(np.abs(actual - expected)):.3g}"


def test_paper_pairs_use_the_swapped_pair_for_particle_2():
    data = synthetic_collisions(1500, seed=9)
    rows, cols, raw, mean, std, boosters, doc = _fit_forest("paper", data, (5,))
    sub = rows.data
    c = sub.col
    v1 = np.column_stack([c("v1x"), c("v1y"), c("v1z")]).astype(np.float32)
    v2 = np.column_stack([c("v2x"), c("v2y"), c("v2z")]).astype(np.float32)
    u1, u2 = ForestPredictor(_flat(doc, "paper")).predict_pairs(v1, v2, c("d1"), c("d2"), c("rho1"), c("rho2"))
    x12 = standardize(np.column_stack([v1, v2]), mean, std)
    x21 = standardize(np.column_stack([v2, v1]), mean, std)
    for k, booster in enumerate(boosters.values()):
        np.testing.assert_allclose(u1[:, k], booster.predict(xgb.DMatrix(x12)), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(u2[:, k], booster.predict(xgb.DMatrix(x21)), rtol=1e-5, atol=1e-5)


def test_forest_file_errors(tmp_path):
    data = synthetic_collisions(400, seed=2)
    *_, doc = _fit_forest("contact", data, (3,), n_estimators=5)
    doc = dict(doc, targets=["impulse_n", "impulse_t"])
    path = tmp_path / "forest.json"
    text = json.dumps(doc)
    path.write_text(text[: len(text) // 2])
    with pytest.raises(ConfigError, match="truncated or corrupted"):
        load_forest(str(path))
    bad = json.loads(text)
    bad["features"] = ["g_n", "g_t"]
    path.write_text(json.dumps(bad))
    with pytest.raises(ConfigError, match="features"):
        load_forest(str(path))
    bad = json.loads(text)
    bad["arrays"]["node_left"]["base64"] = bad["arrays"]["node_left"]["base64"][:-8]
    path.write_text(json.dumps(bad))
    with pytest.raises(ConfigError):
        load_forest(str(path))
    path.write_text(text)
    (tmp_path / "metadata.json").write_text(json.dumps({"files": {"forest.json": "0" * 64}}))
    with pytest.raises(ConfigError, match="sha256"):
        load_forest(str(tmp_path))
    with pytest.raises(ConfigError, match="shape"):
        ForestPredictor(parse_forest(json.loads(text))).predict_features(np.zeros((3, 2), np.float32))
    # a forest without a training domain (format version 1) is refused: retrain
    (tmp_path / "metadata.json").unlink()
    for old in (dict(json.loads(text), version=1), {k: v for k, v in json.loads(text).items() if k != "domain"}):
        old.pop("domain", None)
        path.write_text(json.dumps(old))
        with pytest.raises(ConfigError, match="retrain") as info:
            load_forest(str(path))
        assert "\n" not in str(info.value)
    bad = json.loads(text)
    bad["domain"]["lo"] = bad["domain"]["lo"][:3]
    path.write_text(json.dumps(bad))
    with pytest.raises(ConfigError, match="domain"):
        load_forest(str(path))


@pytest.mark.parametrize("n_trees", [5, 8, 21])
def test_tree_sum_walks_groups_of_trees_as_one_by_one(n_trees):
    """``tree_sum`` (the engine's single-row forest: groups of TREE_GROUP trees walked side by side, the rest one by
    one) gives XGBoost's prediction, and the float32 sum of ``walk_tree`` tree by tree bit for bit; tree counts
    below, at and above a group, rows with NaN features (the default side)."""
    import warp as wp

    from kernels.forest import tree_sum, walk_tree

    @wp.kernel
    def both(forest: kf_Forest, features: wp.array2d(dtype=wp.float32), grouped: wp.array2d(dtype=wp.float32),
             single: wp.array2d(dtype=wp.float32)):
        row = wp.tid()
        for t in range(forest.tree_start.shape[0] - 1):
            first = forest.tree_start[t]
            last = forest.tree_start[t + 1]
            grouped[row, t] = tree_sum(forest, first, last, features, row, forest.base_score[t])
            acc = forest.base_score[t]
            for k in range(first, last):
                acc = acc + walk_tree(forest, forest.tree_root[k], features, row)
            single[row, t] = acc

    data = synthetic_collisions(800, seed=4)
    rows, cols, raw, mean, std, boosters, doc = _fit_forest("contact", data, (6, 3), nan_fraction=0.05,
                                                            n_estimators=n_trees)
    x = wp.array(_full_features(rows, cols, raw), dtype=wp.float32)
    grouped, single = (wp.zeros((x.shape[0], 2), dtype=wp.float32) for _ in range(2))
    wp.launch(both, dim=x.shape[0], inputs=[_flat(doc, "contact").to_device(None), x], outputs=[grouped, single])
    np.testing.assert_array_equal(grouped.numpy(), single.numpy())
    for k, booster in enumerate(boosters.values()):
        reference = booster.predict(xgb.DMatrix(standardize(raw, mean, std)))
        np.testing.assert_allclose(grouped.numpy()[:, k], reference, rtol=1e-5, atol=1e-5)

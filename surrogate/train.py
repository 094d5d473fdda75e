"""Training of the surrogate collision model (reference paper, sec. 4.2).

One XGBoost regressor per target (surrogate/features.py: ``paper`` form u, v, w of
particle 1; ``contact`` form the normalised normal and tangential impulse). The data-set
rows are split 5 % test first, then the rest 75 % train / 25 % validation (by data-set
row, so a row and its swapped twin of the paper form always fall in the same subset).
Features are standardised with the TRAIN mean and std (eq. 17). Hyperparameters
(n_estimators, max_depth, learning_rate, colsample_bytree, reg_alpha) are tuned by
Optuna's TPE sampler on the validation MAE, with trials pruned by
``optuna_integration.XGBoostPruningCallback`` (median pruner) and early stopping on the
validation set; the final model is refit with the best parameters and cut at its best
iteration. Studies live in an Optuna storage (default ``sqlite:///MODEL_DIR/study.db``), one
study per target named ``<form>-<target>``: rerunning the same command continues an
interrupted study up to N finished trials in all, and any database URL lets several
workers share the studies.

Test-set metrics (``metrics.json``): ``mae`` = MAE of particle 1's post-collision u, v, w
in m/s, lab frame (contact form: after the impulse is applied and rotated back), the same
for particle 2, a trivial baseline (the train-set mean velocity), target-level MAE/R²,
the share of rows with a relative velocity error below 5 % (Fig. 8), the relative momentum
error, and the largest difference between the flattened Warp forest and XGBoost.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import dataclass

import numpy as np

from hel_warp.errors import ConfigError
from surrogate.features import (CANONICAL_FEATURES, TARGET_SCALE, TARGETS, CollisionData, FormRows, form_rows,
                                predictions_to_lab, rows_of_groups, sphere_mass, standardize, target_scale_values,
                                used_features)

TEST_FRACTION = 0.05
VALIDATION_FRACTION = 0.25
EARLY_STOPPING_ROUNDS = 25
HEARTBEAT_S = 30
"""Optuna trial heartbeat, s (stale-trial detection for killed workers)."""
PRUNING_REPORT_EVERY = 10
"""Boosting rounds between two reports to the pruner: each report is a storage write (sqlite
commit) and each pruning check reads the study, so reporting every round costs more than
the training itself on a busy disk."""
SEARCH_SPACE = {
    "n_estimators": (40, 200),
    "max_depth": (3, 9),
    "learning_rate": (0.02, 0.3),
    "colsample_bytree": (0.5, 1.0),
    "reg_alpha": (1e-8, 1.0),
}
"""Ranges of the tuned hyperparameters (learning_rate and reg_alpha sampled log-uniform). The forest's cost per
collision is about trees x depth node visits: with the contact targets fitted per cos_angle / sin_angle (the
default) 50 + 40 trees of depth <= 8 meet the engine sweep against the DEM with 0.75 % of |g| at worst (the rig's
data set), where the unscaled fit needed 400 + 95 trees of depth 9 for 1.64 % (``python scripts/check_surrogate.py --model DIR``)."""


@dataclass(frozen=True, kw_only=True)
class TrainConfig:
    """Options of one training run."""

    form: str = "contact"
    """``contact`` (default) or ``paper``."""
    trials: int = 50
    """Finished Optuna trials per target (in all, counting earlier runs of the same study)."""
    storage: str | None = None
    """Optuna storage URL; None -> ``sqlite:///MODEL_DIR/study.db``."""
    timeout: float | None = None
    """Wall-clock budget of the whole search, s (split over the targets); None = no limit."""
    seed: int = 0
    """Seed of the split, the sampler and XGBoost."""
    nthread: int = 1
    """XGBoost threads per trial. One thread per trial, trials run side by side (``jobs``): on a
    shared 2-core machine OpenMP barriers made nthread=2 fits 4x slower than nthread=1."""
    jobs: int = 2
    """Trials evaluated at the same time in this process (Optuna threads; XGBoost frees the GIL)."""
    progress: bool = True
    """Show Optuna's progress bar."""
    report: bool = True
    """Write the parity plots and error histograms to MODEL_DIR/report/."""
    min_rows: int = 40
    """Fewest data-set rows accepted."""
    search_space: dict | None = None
    """Overrides of SEARCH_SPACE ranges, e.g. ``{"n_estimators": (20, 100)}`` (quick runs, tests)."""
    target_scale: bool = True
    """Contact form: the trees learn impulse_n / cos_angle and impulse_t / sin_angle (surrogate/features.py
    TARGET_SCALE; ``fit_weights``), tuned on the validation MAE of the targets themselves; the forest multiplies
    the scale back. False: the targets as they are (models before this option)."""
    sweep: bool = True
    """Contact form on a DEM data set: run the angle/speed sweep against the DEM into metrics.json
    (surrogate/sweep.py; a few seconds)."""

    def __post_init__(self):
        if self.form not in TARGETS:
            raise ConfigError(f"--form must be one of {', '.join(TARGETS)}, got {self.form!r}")
        if self.trials < 1:
            raise ConfigError(f"--trials must be >= 1, got {self.trials}")
        if self.timeout is not None and not self.timeout > 0:
            raise ConfigError(f"--timeout must be > 0 s, got {self.timeout}")
        if self.nthread < 1:
            raise ConfigError(f"--nthread must be >= 1, got {self.nthread}")
        if self.jobs < 1:
            raise ConfigError(f"--jobs must be >= 1, got {self.jobs}")
        unknown = set(self.search_space or {}) - set(SEARCH_SPACE)
        if unknown:
            raise ConfigError(f"unknown hyperparameter(s) {sorted(unknown)}; tunable: {sorted(SEARCH_SPACE)}")


def split_groups(n_groups: int, seed: int):
    """5 % test first, then 75/25 train/validation of the rest; returns three sorted index arrays."""
    rng = np.random.default_rng(seed)
    perm = rng.permutation(n_groups)
    n_test = max(1, int(round(TEST_FRACTION * n_groups)))
    rest = perm[n_test:]
    n_val = max(1, int(round(VALIDATION_FRACTION * rest.size)))
    return np.sort(perm[:n_test]), np.sort(rest[n_val:]), np.sort(rest[:n_val])


def default_storage(model_dir: str) -> str:
    return f"sqlite:///{os.path.abspath(os.path.join(model_dir, 'study.db'))}"


def _xgb_params(params: dict, nthread: int, seed: int) -> dict:
    return dict(params, tree_method="hist", n_jobs=nthread, random_state=seed, objective="reg:squarederror",
                eval_metric="mae", early_stopping_rounds=EARLY_STOPPING_ROUNDS)


def run_study(x_train, y_train, x_val, y_val, *, study_name: str, storage: str, trials: int, seed: int = 0,
              nthread: int = 1, jobs: int = 1, timeout: float | None = None, progress: bool = False,
              dataset_hash: str = "", search_space: dict | None = None, scale_train=None, scale_val=None):
    """Tune one target; continues the study ``study_name`` until it holds ``trials`` finished trials.

    ``scale_train`` / ``scale_val`` (a scaled target: ``y`` is target / scale): weights of ``fit_weights``; the
    objective is the validation MAE of the target itself."""
    space = dict(SEARCH_SPACE, **(search_space or {}))
    import optuna
    import xgboost as xgb
    from optuna.study import MaxTrialsCallback
    from optuna.trial import TrialState
    from optuna_integration import XGBoostPruningCallback

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    finished = (TrialState.COMPLETE, TrialState.PRUNED)
    if isinstance(storage, str):
        # heartbeats: a trial left RUNNING by a killed worker is marked FAIL after the grace period
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            storage = optuna.storages.RDBStorage(storage, heartbeat_interval=HEARTBEAT_S,
                                                 grace_period=3 * HEARTBEAT_S)
    try:
        probe = optuna.load_study(study_name=study_name, storage=storage)
        n_done = len(probe.get_trials(deepcopy=False, states=finished))
    except KeyError:
        n_done = 0
    study = optuna.create_study(study_name=study_name, storage=storage, direction="minimize", load_if_exists=True,
                                sampler=optuna.samplers.TPESampler(seed=seed + n_done),
                                pruner=optuna.pruners.MedianPruner(n_startup_trials=5, n_warmup_steps=30))
    known = study.user_attrs.get("dataset_hash")
    if known is not None and dataset_hash and known != dataset_hash:
        raise ConfigError(f"study {study_name!r} in {storage} was run on another data set; "
                          "give a new --out or --storage to start afresh")
    if known is None and dataset_hash:
        study.set_user_attr("dataset_hash", dataset_hash)

    class SparsePruningCallback(XGBoostPruningCallback):
        """XGBoostPruningCallback that reports every PRUNING_REPORT_EVERY rounds only."""

        def after_iteration(self, model, epoch, evals_log):
            if (epoch + 1) % PRUNING_REPORT_EVERY:
                return False
            return super().after_iteration(model, epoch, evals_log)

    def objective(trial):
        params = {
            "n_estimators": trial.suggest_int("n_estimators", *space["n_estimators"], step=10),
            "max_depth": trial.suggest_int("max_depth", *space["max_depth"]),
            "learning_rate": trial.suggest_float("learning_rate", *space["learning_rate"], log=True),
            "colsample_bytree": trial.suggest_float("colsample_bytree", *space["colsample_bytree"]),
            "reg_alpha": trial.suggest_float("reg_alpha", *space["reg_alpha"], log=True),
        }
        model = xgb.XGBRegressor(**_xgb_params(params, nthread, seed),
                                 callbacks=[SparsePruningCallback(trial, "validation_0-mae")])
        model.fit(x_train, y_train, eval_set=[(x_val, y_val)], verbose=False, **weights)
        trial.set_user_attr("best_iteration", int(model.best_iteration))
        return float(model.best_score) * val_factor

    weights, val_factor = fit_weights(scale_train, scale_val)
    remaining = max(0, trials - n_done)
    if remaining:
        study.optimize(objective, n_trials=remaining, timeout=timeout, show_progress_bar=progress, n_jobs=jobs,
                       callbacks=[MaxTrialsCallback(trials, states=finished)], gc_after_trial=False)
    if not study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
        raise ConfigError(f"study {study_name!r} has no completed trial; raise --trials or --timeout")
    return study


def fit_weights(scale_train, scale_val) -> tuple[dict, float]:
    """``fit`` keyword arguments of a scaled target and the factor mean(scale_val) that turns the weighted
    validation MAE into the MAE of the target itself; ({}, 1) if unscaled.

    The fit weighs every row alike except those of scale 0 (their label target / scale is undefined: weight 0);
    the validation MAE weighs each row by its scale, |scale (pred - label)| being the row's error in the target.
    (Weights scale^2 in the fit, the target's own squared error, gave a larger target MAE: on the rig's data set
    0.00114 against 0.00092 for impulse_n with 60 trees of depth 6.)"""
    if scale_train is None:
        return {}, 1.0
    s_train = np.asarray(scale_train, dtype=np.float64)
    s_val = np.asarray(scale_val, dtype=np.float64)
    if not (s_val > 0).any():
        raise ConfigError("every validation row has a zero target scale; train with --no-target-scale")
    return ({"sample_weight": (s_train > 0).astype(np.float64), "sample_weight_eval_set": [s_val]},
            float(s_val.mean()))


def scaled_label(y: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """target / scale where the scale is positive, 0 where it is 0 (those rows carry weight 0)."""
    s = np.asarray(scale, dtype=np.float64)
    return np.where(s > 0, np.asarray(y, dtype=np.float64) / np.where(s > 0, s, 1.0), 0.0)


def fit_final(params: dict, x_train, y_train, x_val, y_val, *, nthread: int, seed: int, scale_train=None,
              scale_val=None):
    """Refit with the best parameters; return the booster cut at its best iteration."""
    import xgboost as xgb

    model = xgb.XGBRegressor(**_xgb_params(params, nthread, seed))
    model.fit(x_train, y_train, eval_set=[(x_val, y_val)], verbose=False, **fit_weights(scale_train, scale_val)[0])
    return model.get_booster()[: int(model.best_iteration) + 1]


def _mae_dict(pred, true, keys=("u", "v", "w")):
    return {k: float(np.mean(np.abs(pred[:, i] - true[:, i]))) for i, k in enumerate(keys)}


def lab_metrics(form: str, rows: FormRows, test_rows: np.ndarray, predicted: np.ndarray,
                train_rows: np.ndarray) -> tuple[dict, dict]:
    """Test-set lab-frame metrics and the arrays behind the report figures."""
    data_rows, u1_pred, u2_pred = predictions_to_lab(form, rows.data, rows.group[test_rows], predicted)
    sel = rows.data.take(data_rows)
    c = sel.col
    v1, v2, u1, u2 = sel.vec3("v1"), sel.vec3("v2"), sel.vec3("u1"), sel.vec3("u2")
    m1, m2 = sphere_mass(c("d1"), c("rho1")), sphere_mass(c("d2"), c("rho2"))
    p_before = m1[:, None] * v1 + m2[:, None] * v2
    p_after = m1[:, None] * u1_pred + m2[:, None] * u2_pred
    p_scale = m1 * np.linalg.norm(v1, axis=1) + m2 * np.linalg.norm(v2, axis=1)
    momentum_rel = np.linalg.norm(p_after - p_before, axis=1) / np.maximum(p_scale, 1e-300)
    rel_err = np.linalg.norm(u1_pred - u1, axis=1) / np.maximum(np.linalg.norm(u1, axis=1), 1e-12)
    train_data = rows.data.take(np.unique(rows.group[train_rows])).col
    u1_train_mean = np.array([train_data("u1x").mean(), train_data("u1y").mean(), train_data("u1z").mean()])
    metrics = {
        "mae": _mae_dict(u1_pred, u1),
        "mae_particle2": _mae_dict(u2_pred, u2),
        "baseline_mae": _mae_dict(np.broadcast_to(u1_train_mean, u1.shape), u1),
        "rel_error_median": float(np.median(rel_err)),
        "frac_rel_error_below_5pct": float(np.mean(rel_err < 0.05)),
        "momentum_rel_error_max": float(momentum_rel.max()),
        "momentum_rel_error_mean": float(momentum_rel.mean()),
    }
    return metrics, {"u1_true": u1, "u1_pred": u1_pred, "rel_err": rel_err, "u2_true": u2, "u2_pred": u2_pred,
                     "v1": v1, "v2": v2, "d1": c("d1"), "d2": c("d2")}


def mixture_species(attrs: dict) -> tuple[list, list] | None:
    """(means, stds) of the data set's size mixture (``configuration.mixture_diameters``), or None."""
    cfg = attrs.get("configuration") or {}
    means = cfg.get("mixture_diameters")
    if not means:
        return None
    return [float(d) for d in means], [float(s) for s in cfg.get("mixture_diameter_stds") or [0.0] * len(means)]


def pair_type_metrics(arrays: dict, means, stds) -> dict:
    """Test-set metrics per pair type of a size mixture (``hel_warp.collisions.mixture.pair_type_names``: small-small,
    small-large, large-large), each row's particles put in the species of the nearest mean
    (``hel_warp.collisions.mixture.species_of``): rows, share of the test rows, MAE of u1 per component, median relative
    error of u1, and the error of the post-collision relative velocity g' in % of |g| (median, p99, max)."""
    from hel_warp.collisions.mixture import pair_type_names, pair_type_of, species_of

    kind = pair_type_of(species_of(arrays["d1"], means, stds), species_of(arrays["d2"], means, stds))
    g = arrays["v1"] - arrays["v2"]
    g_err = 100.0 * np.linalg.norm((arrays["u1_pred"] - arrays["u2_pred"]) - (arrays["u1_true"] - arrays["u2_true"]),
                                   axis=1) / np.maximum(np.linalg.norm(g, axis=1), 1e-300)
    out = {}
    for i, j, name in pair_type_names(len(means)):
        m = (kind[:, 0] == i) & (kind[:, 1] == j)
        if not m.any():
            out[name] = {"rows": 0, "share": 0.0}
            continue
        out[name] = {"rows": int(m.sum()), "share": float(m.mean()),
                     "diameters_um": [round(means[i] * 1e6, 3), round(means[j] * 1e6, 3)],
                     "mae": _mae_dict(arrays["u1_pred"][m], arrays["u1_true"][m]),
                     "rel_error_median": float(np.median(arrays["rel_err"][m])),
                     "g_error_pct_median": float(np.median(g_err[m])),
                     "g_error_pct_p99": float(np.percentile(g_err[m], 99)),
                     "g_error_pct_max": float(np.max(g_err[m]))}
    return out


def train(data: CollisionData, model_dir: str, config: TrainConfig, *, log=print) -> dict:
    """Tune, fit, evaluate and save one model per target; return the metadata written."""
    import xgboost as xgb

    t_start = time.perf_counter()
    rows = form_rows(config.form, data)
    n_groups = len(rows.data)
    if n_groups < config.min_rows:
        raise ConfigError(f"only {n_groups} usable data-set rows for the {config.form!r} form; "
                          f"need at least {config.min_rows}")
    test_g, train_g, val_g = split_groups(n_groups, config.seed)
    test_r, train_r, val_r = (rows_of_groups(rows, g) for g in (test_g, train_g, val_g))
    features = used_features(config.form, rows.features[train_r])
    cols = [CANONICAL_FEATURES[config.form].index(f) for f in features]
    raw = rows.features[:, cols]
    mean = raw[train_r].astype(np.float64).mean(axis=0)
    std = raw[train_r].astype(np.float64).std(axis=0)
    std = np.where(std > 0, std, 1.0)
    x_all = standardize(raw, mean, std)
    storage = config.storage or default_storage(model_dir)
    os.makedirs(model_dir, exist_ok=True)
    targets = list(TARGETS[config.form])
    boosters, hyper, target_metrics = {}, {}, {}
    predicted = np.zeros((test_r.size, len(targets)))
    deadline = None if config.timeout is None else time.monotonic() + config.timeout
    log(f"{config.form} form: {n_groups} data-set rows -> {train_r.size} train / {val_r.size} validation / "
        f"{test_r.size} test rows, features {features}")
    target_scale = list(TARGET_SCALE[config.form]) if config.target_scale and config.form in TARGET_SCALE else None
    for k, target in enumerate(targets):
        y = rows.targets[:, k]
        scale = None if target_scale is None else target_scale_values(target_scale[k], rows.features)
        label = y if scale is None else scaled_label(y, scale)
        split_scale = {} if scale is None else {"scale_train": scale[train_r], "scale_val": scale[val_r]}
        budget = None if deadline is None else max(1.0, (deadline - time.monotonic()) / (len(targets) - k))
        t0 = time.perf_counter()
        # a scaled target has its own study (its trials' objective is the same MAE, its trees another function)
        study_name = f"{config.form}-{target}" + ("" if scale is None else f"-per-{target_scale[k]}")
        study = run_study(x_all[train_r], label[train_r], x_all[val_r], label[val_r],
                          study_name=study_name, storage=storage, trials=config.trials,
                          seed=config.seed, nthread=config.nthread, jobs=config.jobs, timeout=budget,
                          progress=config.progress, search_space=config.search_space,
                          dataset_hash=data.dataset_hash, **split_scale)
        best = study.best_trial
        booster = fit_final(best.params, x_all[train_r], label[train_r], x_all[val_r], label[val_r],
                            nthread=config.nthread, seed=config.seed, **split_scale)
        boosters[target] = booster
        pred = booster.inplace_predict(x_all[test_r])
        if scale is not None:
            pred = np.float32(pred) * scale[test_r]  # the forest's float32 product (kernels/forest.py)
        predicted[:, k] = pred
        y_test = y[test_r]
        ss_tot = float(np.sum((y_test - y_test.mean()) ** 2))
        target_metrics[target] = {
            "mae": float(np.mean(np.abs(pred - y_test))),
            "baseline_mae": float(np.mean(np.abs(y[train_r].mean() - y_test))),
            "r2": float(1.0 - np.sum((pred - y_test) ** 2) / ss_tot) if ss_tot > 0 else None,
        }
        n_finished = sum(t.state.is_finished() and t.state.name != "FAIL" for t in study.trials)
        hyper[target] = dict(best.params, best_iteration=int(booster.num_boosted_rounds()) - 1,
                             validation_mae=float(best.value), trials=n_finished)
        log(f"  {target}: best validation MAE {best.value:.4g} after {n_finished} finished trials "
            f"({time.perf_counter() - t0:.1f} s), test MAE {target_metrics[target]['mae']:.4g}")
    lab, arrays = lab_metrics(config.form, rows, test_r, predicted, train_r)
    metrics = {"form": config.form, **lab, "n_test": int(test_g.size), "n_test_rows": int(test_r.size),
               "n_train_rows": int(train_r.size), "n_validation_rows": int(val_r.size),
               "targets": target_metrics, "dataset_samples": int(len(data)),
               "wall_time_s": None}
    species = mixture_species(data.attrs)
    if species is not None:
        metrics["pair_types"] = pair_type_metrics(arrays, *species)
        for name, row in metrics["pair_types"].items():
            if row["rows"]:
                log(f"  {name}: {row['rows']} test rows ({100 * row['share']:.1f} %), g' error median "
                    f"{row['g_error_pct_median']:.3f} / p99 {row['g_error_pct_p99']:.3f} / max "
                    f"{row['g_error_pct_max']:.3f} % of |g|")
    material = data.attrs.get("material")
    domain = _domain(config.form, rows, train_r, material)
    doc = _flat_document(config.form, features, targets, boosters, mean, std, domain, target_scale)
    metrics["forest_vs_xgboost_max_abs_diff"] = _forest_check(doc, rows.features[test_r], predicted)
    metrics["fit_wall_time_s"] = round(time.perf_counter() - t_start, 2)
    if config.form == "contact_spin" and material is not None and config.sweep:
        from hel_warp.collisions.forest import parse_forest
        from surrogate.sweep import format_spin_table, format_table, spin_sweep_against_dem, sweep_against_dem

        defaults = {k: float(np.mean(data.col(k))) for k in ("d1", "rho1")}
        contact_model = str(data.attrs.get("contact_model", "hertz"))
        metrics["sweep"] = sweep_against_dem(parse_forest(doc), material, contact_model=contact_model,
                                             diameter=defaults["d1"], density=defaults["rho1"])
        log(format_table(metrics["sweep"]))
        metrics["spin_sweep"] = spin_sweep_against_dem(parse_forest(doc), material, contact_model=contact_model,
                                                       diameter=defaults["d1"], density=defaults["rho1"],
                                                       size_ratios=metrics["sweep"]["size_ratios"])
        log(format_spin_table(metrics["spin_sweep"]))
    if config.form == "contact":
        metrics["guard"] = guard_metrics(doc, rows, test_r, predicted)
        log(f"WARNING: {metrics['guard']['warning']}" if metrics["guard"]["flagged"] else metrics["guard"]["note"])
        if material is not None and config.sweep:
            from hel_warp.collisions.forest import parse_forest
            from surrogate.sweep import format_table, sweep_against_dem

            defaults = {k: float(np.mean(data.col(k))) for k in ("d1", "rho1")}
            metrics["sweep"] = sweep_against_dem(parse_forest(doc), material,
                                                 contact_model=str(data.attrs.get("contact_model", "hertz")),
                                                 diameter=defaults["d1"], density=defaults["rho1"])
            log(format_table(metrics["sweep"]))
            if species is not None:  # one sweep per pair type, at the species' mean sizes
                from hel_warp.collisions.mixture import pair_type_names

                means = species[0]
                metrics["sweep_pair_types"] = {}
                for i, j, name in pair_type_names(len(means)):
                    sweep = sweep_against_dem(parse_forest(doc), material,
                                              contact_model=str(data.attrs.get("contact_model", "hertz")),
                                              diameter=means[i], density=defaults["rho1"],
                                              size_ratios=(means[j] / means[i],))
                    metrics["sweep_pair_types"][name] = sweep
                    log(f"{name}:\n{format_table(sweep)}")
    metrics["wall_time_s"] = round(time.perf_counter() - t_start, 2)
    from surrogate.artifact import save_artifact

    metadata = save_artifact(model_dir, form=config.form, features=features, targets=targets, scaler_mean=mean,
                             scaler_std=std, boosters=boosters, metrics=metrics, dataset_hash=data.dataset_hash,
                             hyperparameters=hyper, domain=domain, target_scale=target_scale,
                             extra={"material": material, "contact_model": data.attrs.get("contact_model"),
                                    "split": {"seed": config.seed, "test_fraction": TEST_FRACTION,
                                              "validation_fraction": VALIDATION_FRACTION},
                                    "optuna_storage": storage if config.storage else "study.db",
                                    "defaults": {k: float(np.mean(data.col(k))) for k in ("d1", "d2", "rho1", "rho2")},
                                    "search_space": {k: list(v) for k, v in
                                                     dict(SEARCH_SPACE, **(config.search_space or {})).items()}})
    if config.report:
        from surrogate.report import write_report

        write_report(model_dir, arrays["u1_true"], arrays["u1_pred"], arrays["rel_err"], metrics)
    log(f"test MAE u, v, w = {metrics['mae']['u']:.4g}, {metrics['mae']['v']:.4g}, {metrics['mae']['w']:.4g} m/s "
        f"(baseline {metrics['baseline_mae']['u']:.3g}, {metrics['baseline_mae']['v']:.3g}, "
        f"{metrics['baseline_mae']['w']:.3g}); wrote {model_dir}")
    return metadata


def _domain(form: str, rows: FormRows, train_rows: np.ndarray, material: dict | None) -> dict:
    """The training domain written into the artifact: feature ranges of the train rows, friction, Coulomb bound."""
    from surrogate.admissibility import choose_friction_bound, dem_admissibility, training_domain

    friction = float((material or {}).get("friction", 0.0))
    if form not in ("contact", "contact_spin"):
        return training_domain(form, rows.features[train_rows], friction=friction, friction_bound=friction,
                               rule="paper form: no impulse guard (the bound is mu)")
    targets = rows.targets
    if form == "contact_spin":  # the guard bounds the tangential impulse |(b, c)| (kernels/forest.py)
        targets = np.column_stack([targets[:, 0], np.hypot(targets[:, 1], targets[:, 2])])
    bound, rule, ratio_max = choose_friction_bound(rows.features, targets, friction)
    return training_domain(form, rows.features[train_rows], friction=friction, friction_bound=bound, rule=rule,
                           dem_max_b_over_a=ratio_max,
                           dem_admissibility=dem_admissibility(rows.features, targets, friction, bound))


def _flat_document(form, features, targets, boosters, mean, std, domain, target_scale=None) -> dict:
    from surrogate.flatten import flatten_models

    models = {t: json.loads(boosters[t].save_raw("json")) for t in targets}
    return flatten_models(form, list(CANONICAL_FEATURES[form]), features, targets, models, mean, std, domain=domain,
                          target_scale=target_scale)


def _forest_check(doc: dict, raw_test, predicted) -> float:
    """Largest |Warp flattened forest - XGBoost| over the test rows and targets (should be ~0)."""
    from hel_warp.collisions.forest import ForestPredictor, parse_forest

    out = ForestPredictor(parse_forest(doc)).predict_features(raw_test)
    return float(np.max(np.abs(out - predicted))) if predicted.size else 0.0


def guard_metrics(doc: dict, rows: FormRows, test_rows: np.ndarray, predicted: np.ndarray) -> dict:
    """How often the engine's domain clamp and admissibility guard act on the test set (contact form).

    ``fraction_*``: calls of the engine path (``ForestPredictor.predict_pairs``, clamp + guard) with
    that correction, any size. The rest measure the guard the engine applies (the artifact's Coulomb bound and
    separation slack, the training DEM's own largest b/a and separation shortfall), target by target:
    ``material_fraction``: calls whose guard correction moves g' by more than MATERIAL_CORRECTION |g|
    (``max_correction``: the largest, in units of |g|); ``dem_needs_fraction``: test rows whose DEM outcome the
    guard would move that much; ``beyond_dem_fraction``: corrected rows whose DEM outcome needs none (the
    model's raw outcome outside the admissible set); ``farther_fraction``: rows the guard moves farther from the
    DEM outcome by more than MATERIAL_CORRECTION |g|.

    The admissible set is convex and holds every DEM outcome of the data, so a correction brings the raw outcome
    towards the DEM, not away (a model of ``hel-warp demo``'s size, 20,000 default rows and 4 trials: 6.3 % of the
    test rows corrected by up to 2.2 % of |g|, median error against the DEM 0.72 -> 0.16 % of |g|, none farther).
    A correction is then the guard doing its work, reported in ``note``; ``flagged`` (with ``warning``) when the
    guard contradicts the DEM: ``farther_fraction`` or ``dem_needs_fraction`` above FLAG_FRACTION (0.1 %). Measured
    with the strict separation rule (no slack) instead, the DEM's own grazing outcomes would count as corrected
    (4-5 % of the rows), which the engine never does.
    """
    from hel_warp.collisions.forest import ForestPredictor, parse_forest
    from surrogate.admissibility import FLAG_FRACTION, MATERIAL_CORRECTION, guarded_targets

    flat = parse_forest(doc)
    sel = rows.data.take(rows.group[test_rows])
    c = sel.col
    predictor = ForestPredictor(flat)
    predictor.predict_pairs(sel.vec3("v1"), sel.vec3("v2"), c("d1"), c("d2"), c("rho1"), c("rho2"),
                            normal=sel.vec3("n"), guard=True)
    counts = predictor.last_counts
    n_calls = max(1, counts["pairs"])
    cos = rows.features[test_rows, 2]
    slack = flat.separation_slack
    dem = rows.targets[test_rows]
    fixed, flags = guarded_targets(cos, predicted, flat.friction_bound, slack)
    correction = np.hypot(*(fixed - predicted).T)
    moved = correction > MATERIAL_CORRECTION
    dem_fixed, _ = guarded_targets(cos, dem, flat.friction_bound, slack)
    dem_needs = np.hypot(*(dem_fixed - dem).T) > MATERIAL_CORRECTION
    farther = np.hypot(*(fixed - dem).T) - np.hypot(*(predicted - dem).T) > MATERIAL_CORRECTION
    out = {"calls": int(counts["pairs"]),
           "fraction_clamped": counts["clamped"] / n_calls,
           "fraction_separation": counts["guard_separation"] / n_calls,
           "fraction_coulomb": counts["guard_coulomb"] / n_calls,
           "fraction_energy": counts["guard_energy"] / n_calls,
           "fraction_any": counts["guard_any"] / n_calls,
           "separation_slack": float(slack),
           "material_correction": MATERIAL_CORRECTION,
           "material_fraction": float(np.mean(moved)),
           "material_fraction_by_flag": {name: float(np.mean(moved & ((flags & bit) != 0)))
                                         for name, bit in (("separation", 1), ("coulomb", 2), ("energy", 4))},
           "max_correction": float(np.max(correction)) if correction.size else 0.0,
           "dem_needs_fraction": float(np.mean(dem_needs)),
           "beyond_dem_fraction": float(np.mean(moved & ~dem_needs)),
           "farther_fraction": float(np.mean(farther)),
           "flag_fraction": FLAG_FRACTION}
    pct = {k: 100 * v for k, v in out["material_fraction_by_flag"].items()}
    out["note"] = (f"the admissibility guard brings {100 * out['material_fraction']:.2f} % of the test-set outcomes "
                   f"back into the physical set (separation {pct['separation']:.2f} %, Coulomb "
                   f"{pct['coulomb']:.2f} %, energy {pct['energy']:.2f} %) by more than "
                   f"{100 * MATERIAL_CORRECTION:g} % of |g|, at most {100 * out['max_correction']:.2f} %; "
                   f"{100 * out['farther_fraction']:.2f} % end farther from the DEM")
    out["flagged"] = bool(out["farther_fraction"] > FLAG_FRACTION or out["dem_needs_fraction"] > FLAG_FRACTION)
    out["warning"] = (f"the admissibility guard contradicts the DEM: it moves {100 * out['farther_fraction']:.2f} % "
                      f"of the test-set outcomes farther from the DEM and would change "
                      f"{100 * out['dem_needs_fraction']:.2f} % of the DEM outcomes themselves by more than "
                      f"{100 * MATERIAL_CORRECTION:g} % of |g| (limit {100 * FLAG_FRACTION:g} %); its bound "
                      f"{flat.friction_bound:.6g} and separation slack {slack:.6g} do not hold the training DEM"
                      ) if out["flagged"] else ""
    return out

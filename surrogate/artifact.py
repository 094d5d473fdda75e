"""The model directory: XGBoost native JSON models + ``metadata.json`` (+ the flattened forest).

Layout of ``MODEL_DIR``::

    <target>.json     one XGBoost model per target (``Booster.save_model``, native JSON)
    forest.json       the flattened forest the engine loads (surrogate/flatten.py)
    metadata.json     {"format": "hel_warp.surrogate", "version": 1, "form", "features" (the
                       model's inputs, in order), "canonical_features", "targets",
                       "scaler": {"mean", "std"} (train statistics, eq. 17),
                       "metrics", "dataset_hash", "hyperparameters" {target: {...}},
                       "domain" (training feature ranges, friction, Coulomb bound: as in forest.json),
                       "material", "contact_model" (of the data set's DEM),
                       "xgboost_version", "files": {file name: sha256}}
    metrics.json      the test-set metrics (also inside metadata.json)
    study.db          the Optuna study (default storage), report/ the figures

Never pickle. :func:`load_artifact` validates everything and raises ``ConfigError`` with a
message that says what is wrong: unreadable or truncated JSON, a file whose sha256 differs
from the metadata, features that differ from the form's or from the data's.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field

import numpy as np

from hel_warp.errors import ConfigError
from hel_warp.collisions.forest import sha256_file  # noqa: F401 (one implementation; tests import it from here)
from surrogate.features import CANONICAL_FEATURES, TARGETS

FORMAT = "hel_warp.surrogate"
VERSION = 1
METADATA = "metadata.json"


@dataclass
class ModelArtifact:
    """A validated model directory."""

    model_dir: str
    form: str
    features: list
    targets: list
    scaler_mean: np.ndarray
    scaler_std: np.ndarray
    metadata: dict
    boosters: dict = field(default_factory=dict)
    """target -> xgboost.Booster (loaded lazily by :func:`load_artifact` with ``boosters=True``)."""

    @property
    def target_scale(self) -> list | None:
        """Per target the scale its trees were fitted per (None: unscaled; surrogate/features.py TARGET_SCALE)."""
        return self.metadata.get("target_scale")

    def predict(self, raw_features: np.ndarray) -> np.ndarray:
        """XGBoost's own prediction of the model's targets (N, T) from raw canonical features (N, F): the boosters
        (``boosters=True``) on the standardised used features, times each target's scale (float32, as the
        engine). The reference the engine's forest is tested against."""
        from surrogate.features import CANONICAL_FEATURES, scale_predictions, standardize

        if not self.boosters:
            raise ConfigError("load the artifact with boosters=True to predict with XGBoost")
        raw = np.ascontiguousarray(raw_features, dtype=np.float32)
        cols = [CANONICAL_FEATURES[self.form].index(f) for f in self.features]
        x = standardize(raw[:, cols], self.scaler_mean, self.scaler_std)
        sums = np.column_stack([self.boosters[t].inplace_predict(x) for t in self.targets])
        return scale_predictions(sums, self.target_scale, raw)

    def model_json(self, target: str) -> dict:
        with open(os.path.join(self.model_dir, f"{target}.json")) as fh:
            return json.load(fh)


def save_artifact(model_dir: str, *, form: str, features: list, targets: list, scaler_mean, scaler_std,
                  boosters: dict, metrics: dict, dataset_hash: str, hyperparameters: dict, domain: dict,
                  extra: dict | None = None, target_scale: list | None = None) -> dict:
    """Write the models, the flattened forest and metadata.json; returns the metadata.

    ``domain``: the training domain (``surrogate.admissibility.training_domain``), in both the forest
    file (what the engine clamps to) and metadata.json. ``target_scale``: per target the scale its trees were
    fitted per (surrogate/features.py TARGET_SCALE; None: unscaled), in both files too: the model's target is
    the booster's prediction times the scale (``ModelArtifact.predict``)."""
    import xgboost

    from surrogate.flatten import flatten_models, write_forest

    os.makedirs(model_dir, exist_ok=True)
    files = {}
    models = {}
    for target in targets:
        name = f"{target}.json"
        path = os.path.join(model_dir, name)
        boosters[target].save_model(path)
        files[name] = sha256_file(path)
        with open(path) as fh:
            models[target] = json.load(fh)
    forest = flatten_models(form, list(CANONICAL_FEATURES[form]), list(features), list(targets), models,
                            np.asarray(scaler_mean), np.asarray(scaler_std), domain=domain, target_scale=target_scale)
    write_forest(os.path.join(model_dir, "forest.json"), forest)
    files["forest.json"] = sha256_file(os.path.join(model_dir, "forest.json"))
    with open(os.path.join(model_dir, "metrics.json"), "w") as fh:
        json.dump(metrics, fh, indent=2)
    metadata = {
        "format": FORMAT, "version": VERSION, "form": form,
        "features": list(features), "canonical_features": list(CANONICAL_FEATURES[form]),
        "targets": list(targets),
        "scaler": {"mean": [float(x) for x in scaler_mean], "std": [float(x) for x in scaler_std]},
        "metrics": metrics, "dataset_hash": dataset_hash, "hyperparameters": hyperparameters, "domain": domain,
        "target_scale": None if target_scale is None else list(target_scale),
        "xgboost_version": xgboost.__version__, "files": files, **(extra or {}),
    }
    tmp = os.path.join(model_dir, METADATA + ".tmp")
    with open(tmp, "w") as fh:
        json.dump(metadata, fh, indent=2)
    os.replace(tmp, os.path.join(model_dir, METADATA))
    return metadata


def _read_json(path: str) -> dict:
    try:
        with open(path) as fh:
            return json.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{path} not found; is this a model directory written by `hel-warp train`?") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path} is not valid JSON ({exc}); the file is truncated or corrupted") from None


def load_artifact(model_dir: str, *, boosters: bool = False, expect_features: list | None = None,
                  expect_dataset_hash: str | None = None) -> ModelArtifact:
    """Validate ``model_dir`` and return it; ``boosters=True`` also loads the XGBoost models."""
    if not os.path.isdir(model_dir):
        raise ConfigError(f"model directory {model_dir!r} not found")
    meta = _read_json(os.path.join(model_dir, METADATA))
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ConfigError(f"{model_dir}/{METADATA} is not a {FORMAT} metadata file")
    if meta.get("version") != VERSION:
        raise ConfigError(f"model metadata version {meta.get('version')!r}; this code reads version {VERSION}")
    form = meta.get("form")
    if form not in CANONICAL_FEATURES:
        raise ConfigError(f"model form {form!r} unknown; expected one of {sorted(CANONICAL_FEATURES)}")
    features, targets = meta.get("features"), meta.get("targets")
    if not isinstance(features, list) or not features or any(f not in CANONICAL_FEATURES[form] for f in features):
        raise ConfigError(f"model features {features!r} are not features of the {form!r} form "
                          f"{list(CANONICAL_FEATURES[form])}")
    if targets != list(TARGETS[form]):
        raise ConfigError(f"model targets {targets!r} differ from the {form!r} form's {list(TARGETS[form])}")
    try:
        mean = np.asarray(meta["scaler"]["mean"], dtype=np.float64)
        std = np.asarray(meta["scaler"]["std"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise ConfigError("model metadata lacks a valid scaler {mean, std}") from None
    if mean.shape != (len(features),) or std.shape != (len(features),) or np.any(~(std > 0)) \
            or not np.all(np.isfinite(mean)):
        raise ConfigError(f"model scaler must hold {len(features)} finite means and positive stds")
    files = meta.get("files")
    expected_files = [f"{t}.json" for t in targets] + ["forest.json"]
    if not isinstance(files, dict) or any(name not in files for name in expected_files):
        raise ConfigError(f"model metadata must list the sha256 of {expected_files}")
    for name in expected_files:
        path = os.path.join(model_dir, name)
        if not os.path.isfile(path):
            raise ConfigError(f"model file {path} is missing")
        if sha256_file(path) != files[name]:
            raise ConfigError(f"model file {path} does not match the sha256 in metadata.json "
                              "(corrupted, truncated or replaced); retrain or restore it")
    if expect_features is not None and list(expect_features) != features:
        raise ConfigError(f"feature mismatch: the model was trained on {features}, the data gives "
                          f"{list(expect_features)}")
    if expect_dataset_hash is not None and meta.get("dataset_hash") != expect_dataset_hash:
        raise ConfigError("the model was trained on a different data set (dataset_hash differs)")
    art = ModelArtifact(model_dir, form, features, targets, mean, std, meta)
    if boosters:
        import xgboost

        for target in targets:
            booster = xgboost.Booster()
            try:
                booster.load_model(os.path.join(model_dir, f"{target}.json"))
            except (xgboost.core.XGBoostError, UnicodeDecodeError) as exc:
                # XGBoost quotes the bytes where its parser stopped; a cut inside a multi-byte character makes
                # its own message undecodable (UnicodeDecodeError from xgboost.compat.py_str)
                first = str(exc).splitlines()[0] if isinstance(exc, xgboost.core.XGBoostError) else "malformed JSON"
                raise ConfigError(f"XGBoost cannot load {target}.json: {first}") from None
            if booster.num_features() != len(features):
                raise ConfigError(f"{target}.json expects {booster.num_features()} features, metadata lists "
                                  f"{len(features)}")
            art.boosters[target] = booster
    return art

"""Flatten XGBoost models into the node arrays the engine evaluates (``MODEL_DIR/forest.json``).

Source: each target's XGBoost native JSON model (``learner.gradient_booster.model.trees[k]``:
``split_indices, split_conditions, left_children, right_children, default_left``; at a
leaf ``split_conditions`` holds the leaf value) and ``learner_model_param.base_score``
(XGBoost >= 2 writes it as a string, XGBoost 3 as a vector string such as ``"[5E-1]"``).
Only regression trees with numerical splits and the identity link are accepted.

XGBoost semantics reproduced exactly: a row goes LEFT when ``x < split_condition`` (float32
compare), RIGHT otherwise, and to the ``default_left`` side when x is NaN (missing);
prediction = base_score + sum of the leaf values (float32).

Scaler folding. The models see ``xs = float32((float64(x) - mean)/std)`` (eq. 17, see
surrogate/features.py) with ``x`` the float32 raw feature. That map is monotone
non-decreasing, so ``xs < t`` holds exactly for ``x < T`` where ``T`` is the smallest float32
with ``float32((T - mean)/std) >= t``. We find ``T`` by bisection over the ordered float32
bit patterns, so the raw-space compare ``x < T`` takes the SAME branch as XGBoost for every
float32 input — no round-off disagreement, no in-kernel standardisation.

File format (JSON, version 2)::

    {"format": "hel_warp.forest", "version": 2,
     "form": "contact" | "paper",
     "features": [canonical feature names; node feature indices point into this list],
     "targets": [target names, one tree group each],
     "base_score": [float32 per target],
     "tree_start": [T+1 ints: trees of target t are tree_root[tree_start[t]:tree_start[t+1]]],
     "max_depth": int,
     "target_scale": [per target "none" | "cos_angle" | "sin_angle"]  (optional; absent = all "none"),
     "domain": {"features": [the canonical features], "lo": [F floats], "hi": [F floats],
                "friction": mu of the training material, "friction_bound": Coulomb guard bound (>= mu),
                "friction_bound_rule": how it was chosen, ...},
     "arrays": {name: {"dtype": "<i4" | "<f4", "shape": [n], "base64": little-endian bytes}}}

    domain: the training data's range of every canonical feature (float32 values, the engine's
            precision; surrogate/admissibility.py ``training_domain``); the engine clamps features into
            it (kernels/forest.py ``write_contact_features_in_domain``) and bounds the tangential
            impulse by ``friction_bound`` (``admissible_impulse``). Version 1 files had no domain; the
            engine refuses them (retrain).

    target_scale: the prediction of a target is its tree sum (base_score + leaves) times the row's cos_angle
            or sqrt(1 - cos_angle^2) (contact form; hel_warp/collisions/forest.py TARGET_SCALES): the trees then learn
            impulse_n / cos_angle (about 1 + e) and impulse_t / sin_angle, nearly constant in the incidence,
            which a few shallow trees fit better than the staircase of the linear dependence (surrogate/train.py).

    arrays: tree_root  int32 (n_trees)  index of each tree's root node
            node_info  int32 (n_nodes)  -1 at a leaf; else 2*feature + default_left
            node_value float32 (n_nodes) leaf value, or the folded raw-space threshold T
            node_left  int32 (n_nodes)  index of the left child (the right child is node_left+1)

Walk: ``i = root; while node_info[i] >= 0: i = node_left[i] + (0 if x < T (or NaN and
default_left) else 1)``; ``x = features[node_info[i] >> 1]``. Nodes are renumbered breadth
first per tree so that siblings are adjacent.
"""

from __future__ import annotations

import base64
import json

import numpy as np

from hel_warp.errors import ConfigError

FORMAT = "hel_warp.forest"
VERSION = 2


def parse_base_score(text) -> float:
    """``learner_model_param.base_score``: ``"0.5"``, ``"5E-1"`` or ``"[5E-1]"`` (one target) -> float."""
    s = str(text).strip()
    if s.startswith("[") and s.endswith("]"):
        parts = [p for p in s[1:-1].split(",") if p.strip()]
        if len(parts) != 1:
            raise ConfigError(f"base_score {text!r} holds {len(parts)} values; one model per target expected")
        s = parts[0]
    try:
        return float(np.float32(float(s)))
    except ValueError:
        raise ConfigError(f"cannot read XGBoost base_score {text!r}") from None


def _float32_keys(x: np.ndarray) -> np.ndarray:
    """Monotone int64 keys of float32 values (order of keys = order of values; -0 and +0 -> 0)."""
    bits = np.asarray(x, dtype=np.float32).view(np.int32).astype(np.int64)
    return np.where(bits < 0, -(bits & 0x7FFFFFFF), bits)


def _keys_to_float32(keys: np.ndarray) -> np.ndarray:
    bits = np.where(keys < 0, (-keys) | 0x80000000, keys).astype(np.int64)
    return (bits & 0xFFFFFFFF).astype(np.uint32).view(np.float32)


def fold_thresholds(thresholds: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """Raw-space float32 thresholds T with ``x < T  <=>  float32((x - mean)/std) < t`` for all float32 x.

    ``thresholds``, ``mean``, ``std``: one entry per split (std > 0). Vectorised bisection on
    float32 bit patterns between -inf (always below) and +inf (always at or above).
    """
    t = np.asarray(thresholds, dtype=np.float32)
    mean = np.asarray(mean, dtype=np.float64)
    std = np.asarray(std, dtype=np.float64)
    if np.any(~np.isfinite(t)):
        raise ConfigError("a split threshold is not finite; the model file is corrupt")

    def standardized(keys):
        x = _keys_to_float32(keys).astype(np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            return ((x - mean) / std).astype(np.float32)

    lo = np.full(t.shape, _float32_keys(np.float32(-np.inf)), dtype=np.int64)  # f(lo) < t
    hi = np.full(t.shape, _float32_keys(np.float32(np.inf)), dtype=np.int64)   # f(hi) >= t
    while True:
        open_ = hi - lo > 1
        if not open_.any():
            break
        mid = lo + (hi - lo) // 2
        above = standardized(mid) >= t
        hi = np.where(open_ & above, mid, hi)
        lo = np.where(open_ & ~above, mid, lo)
    return _keys_to_float32(hi)


def _tree_arrays(tree: dict):
    try:
        left = np.asarray(tree["left_children"], dtype=np.int64)
        right = np.asarray(tree["right_children"], dtype=np.int64)
        feat = np.asarray(tree["split_indices"], dtype=np.int64)
        cond = np.asarray(tree["split_conditions"], dtype=np.float64).astype(np.float32)
        dleft = np.asarray(tree["default_left"], dtype=np.int64)
        stype = np.asarray(tree.get("split_type", np.zeros_like(left)), dtype=np.int64)
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"XGBoost tree is missing or has a malformed field: {exc}") from None
    n = left.size
    if not (right.size == feat.size == cond.size == dleft.size == n) or n == 0:
        raise ConfigError("XGBoost tree arrays have inconsistent lengths; the model file is corrupt")
    if np.any(stype != 0):
        raise ConfigError("categorical splits are not supported by the flattened forest")
    return left, right, feat, cond, dleft


def flatten_booster_json(model: dict, *, used_to_canonical: list[int], mean: np.ndarray, std: np.ndarray):
    """One target's XGBoost JSON model -> (base_score, list of per-tree node arrays).

    ``used_to_canonical[j]``: canonical feature index of the model's feature j;
    ``mean``/``std``: the scaler of the model's features (eq. 17, train statistics).
    """
    try:
        learner = model["learner"]
        objective = learner["objective"]["name"]
        base_score = parse_base_score(learner["learner_model_param"]["base_score"])
        gbm = learner["gradient_booster"]
        trees = gbm["model"]["trees"]
        num_feature = int(learner["learner_model_param"]["num_feature"])
    except (KeyError, TypeError) as exc:
        raise ConfigError(f"not an XGBoost gbtree JSON model (missing {exc})") from None
    if gbm.get("name", "gbtree") != "gbtree":
        raise ConfigError(f"booster {gbm.get('name')!r} not supported; train with booster='gbtree'")
    if objective not in ("reg:squarederror", "reg:absoluteerror", "reg:pseudohubererror", "reg:quantileerror"):
        raise ConfigError(f"objective {objective!r} has a non-identity link; the flattened forest adds raw margins")
    if num_feature != len(used_to_canonical) or len(mean) != num_feature or len(std) != num_feature:
        raise ConfigError(f"model has {num_feature} features but the metadata lists {len(used_to_canonical)}")
    if np.any(np.asarray(std) <= 0):
        raise ConfigError("scaler std must be > 0 for every feature")
    flat = []
    for tree in trees:
        left, right, feat, cond, dleft = _tree_arrays(tree)
        # breadth-first renumbering with adjacent siblings
        order, depth_of = [0], {0: 0}
        new_index = {0: 0}
        k = 0
        while k < len(order):
            old = order[k]
            if left[old] >= 0:
                if not (0 < left[old] < left.size and 0 < right[old] < left.size):
                    raise ConfigError("XGBoost tree child index out of range; the model file is corrupt")
                for child in (left[old], right[old]):
                    new_index[int(child)] = len(order)
                    depth_of[int(child)] = depth_of[old] + 1
                    order.append(int(child))
            k += 1
            if len(order) > left.size:
                raise ConfigError("XGBoost tree is not a tree (cycle); the model file is corrupt")
        order = np.asarray(order)
        is_leaf = left[order] < 0
        f_used = feat[order]
        if np.any(~is_leaf & ((f_used < 0) | (f_used >= num_feature))):
            raise ConfigError("XGBoost split feature index out of range; the model file is corrupt")
        info = np.where(is_leaf, -1, 2 * np.asarray(used_to_canonical)[np.clip(f_used, 0, num_feature - 1)]
                        + dleft[order])
        value = cond[order].copy()
        split = ~is_leaf
        if split.any():
            j = f_used[split]
            value[split] = fold_thresholds(cond[order][split], np.asarray(mean)[j], np.asarray(std)[j])
        child = np.array([new_index[int(left[o])] if left[o] >= 0 else -1 for o in order], dtype=np.int64)
        flat.append((info.astype(np.int32), value.astype(np.float32), child.astype(np.int32),
                     max(depth_of.values())))
    return base_score, flat


def _encode(arr: np.ndarray, dtype: str) -> dict:
    a = np.ascontiguousarray(arr, dtype=np.dtype(dtype))
    return {"dtype": dtype, "shape": list(a.shape), "base64": base64.b64encode(a.tobytes()).decode("ascii")}


def flatten_models(form: str, canonical_features: list[str], used_features: list[str], targets: list[str],
                   models: dict, mean, std, *, domain: dict, target_scale: list | None = None) -> dict:
    """All targets' XGBoost JSON models (dict target -> parsed JSON) -> the forest.json document.

    ``domain``: the training domain (``surrogate.admissibility.training_domain``), written as is.
    ``target_scale``: per target a name of hel_warp.collisions.forest.TARGET_SCALES (None: not written, all unscaled).
    """
    from hel_warp.collisions.forest import _parse_domain

    _parse_domain(domain, canonical_features)
    missing = [f for f in used_features if f not in canonical_features]
    if missing:
        raise ConfigError(f"features {missing} are not features of the {form!r} form")
    used_to_canonical = [canonical_features.index(f) for f in used_features]
    roots, infos, values, lefts, bases, starts = [], [], [], [], [], [0]
    n_nodes, max_depth = 0, 0
    for target in targets:
        base, trees = flatten_booster_json(models[target], used_to_canonical=used_to_canonical, mean=mean, std=std)
        bases.append(base)
        for info, value, left, depth in trees:
            roots.append(n_nodes)
            infos.append(info)
            values.append(value)
            lefts.append(np.where(left >= 0, left + n_nodes, -1))
            n_nodes += info.size
            max_depth = max(max_depth, depth)
        starts.append(len(roots))
    cat = (lambda xs, dt: np.concatenate(xs).astype(dt) if xs else np.zeros(0, dt))
    return {
        "format": FORMAT, "version": VERSION, "form": form,
        "features": list(canonical_features), "targets": list(targets),
        "base_score": [float(b) for b in bases], "tree_start": starts, "max_depth": int(max_depth),
        "domain": dict(domain),
        **({} if target_scale is None else {"target_scale": list(target_scale)}),
        "arrays": {
            "tree_root": _encode(np.asarray(roots, dtype=np.int32), "<i4"),
            "node_info": _encode(cat(infos, np.int32), "<i4"),
            "node_value": _encode(cat(values, np.float32), "<f4"),
            "node_left": _encode(cat(lefts, np.int32), "<i4"),
        },
    }


def write_forest(path: str, document: dict) -> None:
    with open(path, "w") as fh:
        json.dump(document, fh)

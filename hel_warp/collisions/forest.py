"""Engine-side surrogate collision model: load ``MODEL_DIR/forest.json`` into Warp arrays.

The file is written by surrogate/flatten.py (format documented there); its sha256 is
checked against ``MODEL_DIR/metadata.json`` when that file is present. Needs neither
XGBoost nor Optuna. Evaluation goes through the launch wrappers of kernels/forest.py.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
from dataclasses import dataclass

import numpy as np

from hel_warp.errors import ConfigError

FORMAT = "hel_warp.forest"
VERSION = 2
"""Version 2 adds the ``domain`` section (training feature ranges, friction, Coulomb bound)."""
CANONICAL_FEATURES = {
    "paper": ("v1x", "v1y", "v1z", "v2x", "v2y", "v2z", "d1", "d2", "rho1", "rho2"),
    "contact": ("g_n", "g_t", "cos_angle", "d1", "size_ratio", "density_ratio"),
    "contact_spin": ("g_n", "g_t", "cos_angle", "d1", "size_ratio", "density_ratio", "u_along", "u_across"),
}
N_TARGETS = {"paper": 3, "contact": 2, "contact_spin": 5}
CONTACT_FORMS = ("contact", "contact_spin")
"""Contact-frame forms (the pairwise surrogate's): ``contact_spin`` adds the translational slip's components along
and across the contact points' slip, the impulse across it and the moment impulse that turns the spins
(surrogate/features.py ``contact_spin_frame``, ``apply_contact_spin_model``)."""
TARGET_SCALES = ("none", "cos_angle", "sin_angle")
"""What a target's tree sum is multiplied by (the file's ``target_scale``; the index is the kernel's code,
kernels/forest.py SCALE_*): nothing, the row's cos_angle, or sqrt(1 - cos_angle^2). Contact form only."""
PERFECT_MAX_DEPTH = 12
"""Deepest tree padded to the perfect layout (2^D - 1 nodes per tree); deeper forests use explicit children."""


def quiet_warp() -> None:
    """No greeting or module-load lines from Warp on stdout (see ``hel_warp._warp.init_warp``)."""
    from hel_warp._warp import init_warp

    init_warp()


def sha256_file(path: str) -> str:
    """Hex SHA-256 of a file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass
class FlatForest:
    """A flattened forest on the host (numpy); :meth:`to_device` gives the Warp ``Forest`` struct."""

    form: str
    features: list
    targets: list
    base_score: np.ndarray
    """(T,) float32."""
    tree_start: np.ndarray
    """(T+1,) int32."""
    tree_root: np.ndarray
    node_info: np.ndarray
    node_value: np.ndarray
    node_left: np.ndarray
    max_depth: int
    domain: dict | None = None
    """The ``domain`` section of the file (surrogate/flatten.py): ``lo``/``hi`` per canonical feature,
    ``friction``, ``friction_bound`` and how it was chosen."""
    target_scale: list | None = None
    """Per target, a name of TARGET_SCALES (None: every target unscaled, as files before the key)."""

    @property
    def scale_codes(self) -> np.ndarray:
        """(T,) int32 kernel codes of ``target_scale`` (0: unscaled)."""
        names = self.target_scale or ["none"] * len(self.targets)
        return np.asarray([TARGET_SCALES.index(n) for n in names], dtype=np.int32)

    @property
    def feature_lo(self) -> np.ndarray:
        """(F,) float32 training minimum of each canonical feature."""
        return np.asarray(self.domain["lo"], dtype=np.float32)

    @property
    def feature_hi(self) -> np.ndarray:
        """(F,) float32 training maximum of each canonical feature."""
        return np.asarray(self.domain["hi"], dtype=np.float32)

    @property
    def friction_bound(self) -> float:
        """Coulomb guard of the contact form: normalised tangential impulse b <= friction_bound * a."""
        return float(self.domain["friction_bound"])

    def domain_to_device(self, device="cpu"):
        """The Warp ``kernels.forest.ContactDomain`` of a contact-form forest (feature ranges, Coulomb bound)."""
        import warp as wp

        from kernels.forest import ContactDomain

        if self.form not in CONTACT_FORMS:
            raise ConfigError(f"a {self.form!r}-form forest has no contact-frame domain; use a contact-form model")
        domain = ContactDomain()
        domain.feature_lo = wp.array(self.feature_lo, dtype=wp.float32, device=device)
        domain.feature_hi = wp.array(self.feature_hi, dtype=wp.float32, device=device)
        domain.friction_bound = self.friction_bound
        domain.separation_slack = self.separation_slack
        return domain

    @property
    def separation_slack(self) -> float:
        """Separation guard a >= c - slack: the largest shortfall of a below cos_angle in the training DEM rows
        (``domain.separation_slack``, else ``domain.dem_admissibility.all.max_separation_deficit``; 0 without
        either: strictly separating along the first-touch normal)."""
        d = self.domain or {}
        if "separation_slack" in d:
            return max(0.0, float(d["separation_slack"]))
        deficit = ((d.get("dem_admissibility") or {}).get("all") or {}).get("max_separation_deficit")
        return max(0.0, float(deficit)) if deficit is not None else 0.0

    @property
    def n_trees(self) -> int:
        return int(self.tree_root.size)

    @property
    def n_nodes(self) -> int:
        return int(self.node_info.size)

    def packed_nodes(self) -> np.ndarray:
        """Nodes as the kernel's 8-byte ``Node`` records (kernels/forest.py): meta, value."""
        split = self.node_info >= 0
        if self.n_nodes >= 1 << 26:
            raise ConfigError(f"forest has {self.n_nodes} nodes; the packed layout holds at most 2**26")
        meta = np.where(split, (self.node_left.astype(np.int64) << 5) | self.node_info.astype(np.int64), -1)
        nodes = np.zeros(self.n_nodes, dtype=[("meta", "<i4"), ("value", "<f4")])
        nodes["meta"] = meta.astype(np.int32)
        nodes["value"] = self.node_value
        return nodes

    def perfect_layout(self):
        """Pad every tree to a perfect tree of its own depth D, level ordered (children 2i+1, 2i+2).

        A leaf above level D becomes a pass-through subtree whose every leaf at level D holds
        its value, so either branch gives the same result. Returns (nodes, tree_first_node,
        tree_depth, tree_first_leaf, leaves).
        """
        node_parts, leaf_parts = [], []
        first_node, depths, first_leaf = [], [], []
        n_nodes = n_leaves = 0
        left, info, value = self.node_left, self.node_info, self.node_value
        for root in self.tree_root:
            level = np.array([root], dtype=np.int64)
            metas, values = [], []
            while np.any(info[level] >= 0):
                split = info[level] >= 0
                metas.append(np.where(split, info[level], 0))
                values.append(np.where(split, value[level], 0.0))
                lft = np.where(split, left[level], level)
                rgt = np.where(split, left[level] + 1, level)
                level = np.stack([lft, rgt], axis=1).reshape(-1)
            depth = len(metas)
            nodes = np.zeros((1 << depth) - 1, dtype=[("meta", "<i4"), ("value", "<f4")])
            if depth:
                nodes["meta"] = np.concatenate(metas)
                nodes["value"] = np.concatenate(values)
            first_node.append(n_nodes)
            depths.append(depth)
            first_leaf.append(n_leaves)
            node_parts.append(nodes)
            leaf_parts.append(value[level].astype(np.float32))
            n_nodes += nodes.size
            n_leaves += level.size
        if not node_parts or n_nodes == 0:
            node_parts.append(np.zeros(1, dtype=[("meta", "<i4"), ("value", "<f4")]))
        return (np.concatenate(node_parts), np.asarray(first_node, np.int32), np.asarray(depths, np.int32),
                np.asarray(first_leaf, np.int32),
                np.concatenate(leaf_parts) if leaf_parts else np.zeros(1, np.float32))

    def to_device(self, device="cpu", *, layout: str = "explicit"):
        """The Warp ``Forest`` struct. ``layout``: "explicit" (children indices; what
        ``kernels.forest.walk_tree`` walks — the default, so kernels that call ``walk_tree`` with
        ``tree_root[k]`` keep working), "perfect" (padded level-ordered trees, faster; evaluate with
        ``eval_forest`` or ``tree_value``), or "auto" (perfect when the deepest tree has depth
        <= PERFECT_MAX_DEPTH)."""
        import warp as wp

        from kernels.forest import Forest, Node

        if layout == "auto":
            layout = "perfect" if self.max_depth <= PERFECT_MAX_DEPTH else "explicit"
        if layout not in ("perfect", "explicit"):
            raise ConfigError(f"forest layout must be perfect, explicit or auto, got {layout!r}")
        forest = Forest()
        forest.tree_start = wp.array(self.tree_start, dtype=wp.int32, device=device)
        forest.base_score = wp.array(self.base_score, dtype=wp.float32, device=device)
        forest.target_scale = wp.array(self.scale_codes, dtype=wp.int32, device=device)
        if layout == "perfect":
            nodes, first, depth, first_leaf, leaves = self.perfect_layout()
            forest.perfect = 1
            forest.nodes = wp.array(nodes, dtype=Node, device=device)
            forest.tree_root = wp.array(first, dtype=wp.int32, device=device)
            forest.tree_depth = wp.array(depth, dtype=wp.int32, device=device)
            forest.tree_leaf = wp.array(first_leaf, dtype=wp.int32, device=device)
            forest.leaves = wp.array(leaves, dtype=wp.float32, device=device)
        else:
            forest.perfect = 0
            forest.nodes = wp.array(self.packed_nodes(), dtype=Node, device=device)
            forest.tree_root = wp.array(self.tree_root, dtype=wp.int32, device=device)
            forest.tree_depth = wp.zeros(max(1, self.n_trees), dtype=wp.int32, device=device)
            forest.tree_leaf = wp.zeros(max(1, self.n_trees), dtype=wp.int32, device=device)
            forest.leaves = wp.zeros(1, dtype=wp.float32, device=device)
        self.layout = layout
        return forest


def _decode(spec, name: str, dtype: str) -> np.ndarray:
    try:
        if spec["dtype"] != dtype:
            raise ConfigError(f"forest array {name} has dtype {spec['dtype']}, expected {dtype}")
        raw = base64.b64decode(spec["base64"], validate=True)
        arr = np.frombuffer(raw, dtype=np.dtype(dtype))
        if list(arr.shape) != list(spec["shape"]):
            raise ConfigError(f"forest array {name} holds {arr.size} values, header says {spec['shape']}")
        return arr.astype(np.dtype(dtype).newbyteorder("="))
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"forest array {name} is malformed ({exc}); re-flatten the model") from None


def parse_forest(doc: dict) -> FlatForest:
    """Validate a forest.json document and return its arrays (every index checked in range)."""
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ConfigError(f"not a {FORMAT} file")
    if doc.get("version") != VERSION or "domain" not in doc:
        raise ConfigError(f"forest file version {doc.get('version')!r} states no training domain (this engine reads "
                          f"version {VERSION}, with feature ranges and the Coulomb bound); retrain the model with "
                          "`hel-warp train` (on a `hel-warp dataset` set)")
    form = doc.get("form")
    if form not in CANONICAL_FEATURES:
        raise ConfigError(f"forest form {form!r} unknown; expected one of {sorted(CANONICAL_FEATURES)}")
    if tuple(doc.get("features", ())) != CANONICAL_FEATURES[form]:
        raise ConfigError(f"forest features {doc.get('features')} differ from the engine's {form!r} features "
                          f"{list(CANONICAL_FEATURES[form])}")
    targets = list(doc.get("targets", []))
    if len(targets) != N_TARGETS[form]:
        raise ConfigError(f"{form!r} forest must have {N_TARGETS[form]} targets, has {targets}")
    arrays = doc.get("arrays") or {}
    try:
        root = _decode(arrays["tree_root"], "tree_root", "<i4")
        info = _decode(arrays["node_info"], "node_info", "<i4")
        value = _decode(arrays["node_value"], "node_value", "<f4")
        left = _decode(arrays["node_left"], "node_left", "<i4")
    except KeyError as exc:
        raise ConfigError(f"forest file lacks array {exc}") from None
    start = np.asarray(doc.get("tree_start", []), dtype=np.int32)
    base = np.asarray(doc.get("base_score", []), dtype=np.float32)
    n_nodes = info.size
    if not (value.size == left.size == n_nodes):
        raise ConfigError("forest node arrays have different lengths")
    if start.size != len(targets) + 1 or start[0] != 0 or start[-1] != root.size or np.any(np.diff(start) < 0):
        raise ConfigError("forest tree_start is inconsistent with the number of trees")
    if base.size != len(targets) or not np.all(np.isfinite(base)):
        raise ConfigError("forest base_score must hold one finite value per target")
    if root.size and (root.min() < 0 or root.max() >= n_nodes):
        raise ConfigError("forest tree_root index out of range")
    split = info >= 0
    if np.any(info < -1) or np.any((info[split] >> 1) >= min(len(CANONICAL_FEATURES[form]), 16)):
        raise ConfigError("forest node feature index out of range")
    if np.any(split & ((left < 0) | (left + 1 >= n_nodes))) or np.any(split & (left <= np.arange(n_nodes))):
        raise ConfigError("forest child index out of range (children must follow their parent)")
    if np.any(np.isnan(value)):
        raise ConfigError("forest holds NaN node values")
    domain = _parse_domain(doc.get("domain"), CANONICAL_FEATURES[form])
    scale = doc.get("target_scale")
    if scale is not None:
        if not isinstance(scale, list) or len(scale) != len(targets) or any(n not in TARGET_SCALES for n in scale):
            raise ConfigError(f"forest target_scale must name one of {list(TARGET_SCALES)} per target, got {scale!r}")
        if form not in CONTACT_FORMS and any(n != "none" for n in scale):
            raise ConfigError(f"a {form!r}-form forest cannot scale its targets (target_scale {scale!r})")
        scale = list(scale)
    return FlatForest(form, list(doc["features"]), targets, base, start, root, info, value, left,
                      int(doc.get("max_depth", 0)), domain, scale)


def _parse_domain(domain, features) -> dict:
    """Check the ``domain`` section: finite lo <= hi per canonical feature, friction >= 0, bound >= friction."""
    retrain = "retrain the model with `hel-warp train`"
    if not isinstance(domain, dict):
        raise ConfigError(f"forest domain must be an object with lo, hi, friction, friction_bound; {retrain}")
    try:
        lo = np.asarray(domain["lo"], dtype=np.float64)
        hi = np.asarray(domain["hi"], dtype=np.float64)
        friction = float(domain["friction"])
        bound = float(domain["friction_bound"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"forest domain lacks or has a malformed {exc}; {retrain}") from None
    if list(domain.get("features", features)) != list(features) or lo.shape != (len(features),) \
            or hi.shape != (len(features),):
        raise ConfigError(f"forest domain must give lo and hi for the features {list(features)}; {retrain}")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo <= hi)):
        raise ConfigError(f"forest domain ranges must be finite with lo <= hi; {retrain}")
    if not (np.isfinite(friction) and friction >= 0 and np.isfinite(bound) and bound >= friction):
        raise ConfigError(f"forest domain needs friction >= 0 and friction_bound >= friction (got {friction}, "
                          f"{bound}); {retrain}")
    return dict(domain)


def load_forest(model_dir: str) -> FlatForest:
    """Read ``model_dir/forest.json`` (checked against ``metadata.json``'s sha256 when present)."""
    path = os.path.join(model_dir, "forest.json") if os.path.isdir(model_dir) else model_dir
    if not os.path.isfile(path):
        raise ConfigError(f"no flattened forest at {path!r}; train a model with `hel-warp train --out DIR` first")
    meta_path = os.path.join(os.path.dirname(path), "metadata.json")
    if os.path.isfile(meta_path):
        try:
            with open(meta_path) as fh:
                expected = json.load(fh).get("files", {}).get(os.path.basename(path))
        except (json.JSONDecodeError, AttributeError, OSError) as exc:
            raise ConfigError(f"cannot read {meta_path}: {exc}") from None
        if expected is not None and expected != sha256_file(path):
            raise ConfigError(f"{path} does not match the sha256 recorded in metadata.json (corrupted or replaced)")
    try:
        with open(path) as fh:
            doc = json.load(fh)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path} is not valid JSON ({exc}); the file is truncated or corrupted") from None
    return parse_forest(doc)


class ForestPredictor:
    """Evaluate a flattened forest on a Warp device: raw features, or whole pairs (v1, v2, ...)."""

    def __init__(self, flat: FlatForest, device="cpu", *, rows_per_thread: int | None = None,
                 layout: str = "auto"):
        import warp as wp

        quiet_warp()
        self.flat = flat
        self.device = wp.get_device(device)
        self.forest = flat.to_device(self.device, layout=layout)
        self.layout = flat.layout
        # CPU: a block of rows per thread walks each tree for all of them (cache reuse);
        # GPU: one row per thread.
        # CUDA's one row per thread gives the CPU's 64 bit for bit (tests/test_device_paths.py)
        self.rows_per_thread = rows_per_thread or (64 if self.device.is_cpu else 1)
        self.domain = flat.domain_to_device(self.device) if flat.form in CONTACT_FORMS else None
        self.last_counts: dict = {}

    def predict_features(self, features) -> np.ndarray:
        """(N, F) raw features (canonical order, NaN = missing) -> (N, T) float32 predictions."""
        import warp as wp

        from kernels.forest import eval_forest

        x = np.ascontiguousarray(np.asarray(features, dtype=np.float32))
        if x.ndim != 2 or x.shape[1] != len(self.flat.features):
            raise ConfigError(f"features must have shape (N, {len(self.flat.features)}), got {x.shape}")
        x_wp = wp.array(x, dtype=wp.float32, device=self.device)
        out = wp.zeros((x.shape[0], len(self.flat.targets)), dtype=wp.float32, device=self.device)
        eval_forest(self.forest, x_wp, out, rows_per_thread=self.rows_per_thread)
        return out.numpy()

    def predict_pairs(self, v1, v2, d1, d2, rho1, rho2, normal=None, *, guard: bool = True, omega1=None,
                      omega2=None):
        """Post-collision velocities (v1', v2') of N pairs, each (N, 3) float32.

        With ``omega1`` / ``omega2`` (rad/s; contact form, guarded): spinning spheres, as the engine's
        ``particle_spin`` resolves them: the model is asked at the contact points' relative velocity, the impulse acts
        through the contact point; returns ``(v1', v2', omega1', omega2')`` (``_predict_spin``).

        ``contact`` form needs ``normal`` (unit, from 1 to 2, pairs approaching: ``(v1 - v2).n > 0``);
        the ``paper`` form ignores it. Contact form with ``guard`` (default): features clamped into the
        training domain, the predicted impulse made admissible (``kernels.forest.admissible_impulse``:
        separating, Coulomb, no energy gain); ``self.last_counts`` then holds ``pairs``, ``clamped``,
        ``guard_separation``, ``guard_coulomb``, ``guard_energy``, ``guard_any`` of this call.
        ``guard=False``: the bare trees (the raw model, for measuring it).
        """
        import warp as wp

        from kernels import forest as kf

        if omega1 is not None or omega2 is not None or self.flat.form == "contact_spin":
            out = self._predict_spin(v1, v2, d1, d2, rho1, rho2, normal, omega1, omega2, guard=guard)
            return out if (omega1 is not None or omega2 is not None) else out[:2]
        v1 = np.atleast_2d(np.asarray(v1, dtype=np.float32))
        n_pairs = v1.shape[0]
        as_vec = lambda a: wp.array(np.ascontiguousarray(np.atleast_2d(np.asarray(a, np.float32))), dtype=wp.vec3,
                                    device=self.device)
        as_f = lambda a: wp.array(np.ascontiguousarray(np.broadcast_to(np.asarray(a, np.float32), (n_pairs,))),
                                  dtype=wp.float32, device=self.device)
        w_v1, w_v2 = as_vec(v1), as_vec(v2)
        w_d1, w_d2, w_r1, w_r2 = as_f(d1), as_f(d2), as_f(rho1), as_f(rho2)
        v1_after = wp.zeros(n_pairs, dtype=wp.vec3, device=self.device)
        v2_after = wp.zeros(n_pairs, dtype=wp.vec3, device=self.device)
        n_targets = len(self.flat.targets)
        if self.flat.form == "contact":
            if normal is None:
                raise ConfigError("the contact-form model needs the contact normal of each pair")
            w_n = as_vec(normal)
            feats = wp.zeros((n_pairs, len(self.flat.features)), dtype=wp.float32, device=self.device)
            targets = wp.zeros((n_pairs, n_targets), dtype=wp.float32, device=self.device)
            if guard:
                clamped = wp.zeros(1, dtype=wp.int32, device=self.device)
                guard_counts = wp.zeros(4, dtype=wp.int32, device=self.device)
                kf.contact_features_in_domain(w_v1, w_v2, w_n, w_d1, w_d2, w_r1, w_r2, self.domain, feats, clamped)
                kf.eval_forest(self.forest, feats, targets, rows_per_thread=self.rows_per_thread)
                kf.apply_admissible_contact(w_v1, w_v2, w_n, w_d1, w_d2, w_r1, w_r2, targets, self.flat.friction_bound,
                                            v1_after, v2_after, guard_counts,
                                            separation_slack=self.flat.separation_slack)
                counts = guard_counts.numpy()
                self.last_counts = {"pairs": int(n_pairs), "clamped": int(clamped.numpy()[0]),
                                    "guard_separation": int(counts[0]), "guard_coulomb": int(counts[1]),
                                    "guard_energy": int(counts[2]), "guard_any": int(counts[3])}
            else:
                kf.contact_features(w_v1, w_v2, w_n, w_d1, w_d2, w_r1, w_r2, feats)
                kf.eval_forest(self.forest, feats, targets, rows_per_thread=self.rows_per_thread)
                kf.apply_contact(w_v1, w_v2, w_n, w_d1, w_d2, w_r1, w_r2, targets, v1_after, v2_after)
                self.last_counts = {"pairs": int(n_pairs)}
        else:
            feats = wp.zeros((2 * n_pairs, len(self.flat.features)), dtype=wp.float32, device=self.device)
            targets = wp.zeros((2 * n_pairs, n_targets), dtype=wp.float32, device=self.device)
            kf.paper_features(w_v1, w_v2, w_d1, w_d2, w_r1, w_r2, feats)
            kf.eval_forest(self.forest, feats, targets, rows_per_thread=self.rows_per_thread)
            kf.paper_velocities(targets, v1_after, v2_after)
            self.last_counts = {"pairs": int(n_pairs)}
        return v1_after.numpy(), v2_after.numpy()

    def _predict_spin(self, v1, v2, d1, d2, rho1, rho2, normal, omega1, omega2, *, guard: bool = True):
        """``predict_pairs`` of spinning spheres (or of a ``contact_spin`` model): ``(v1', v2', omega1', omega2')``,
        the engine's path (kernels/forest.py ``contact_point_velocities_kernel``, the features of the model's form
        at the contact points, ``apply_admissible_contact_spin_kernel``: the impulse through the contact point).
        Without spins (``omega1`` and ``omega2`` None: a contact_spin model in a spinless run) the engine's
        translational guard and no spin change, as ``particle_spin=False`` does; ``guard=False``: the bare trees
        (the contact form refuses it with spins: that path is the engine's)."""
        import warp as wp

        from kernels import forest as kf

        if self.flat.form not in CONTACT_FORMS or normal is None:
            raise ConfigError("spinning pairs need a contact-form model and the contact normal of each pair")
        spinning = omega1 is not None or omega2 is not None
        if not guard and self.flat.form == "contact":
            raise ConfigError("the spin path is the engine's (guarded); predict spinless pairs for the bare trees")
        v1 = np.atleast_2d(np.asarray(v1, dtype=np.float32))
        n_pairs = v1.shape[0]
        dev = self.device
        as_vec = lambda a: wp.array(np.ascontiguousarray(np.broadcast_to(np.asarray(a, np.float32), (n_pairs, 3))),
                                    dtype=wp.vec3, device=dev)
        as_f = lambda a: wp.array(np.ascontiguousarray(np.broadcast_to(np.asarray(a, np.float32), (n_pairs,))),
                                  dtype=wp.float32, device=dev)
        zero = np.zeros(3, np.float32)
        w_v1, w_v2, w_n = as_vec(v1), as_vec(v2), as_vec(normal)
        w_o1 = as_vec(zero if omega1 is None else omega1)
        w_o2 = as_vec(zero if omega2 is None else omega2)
        w_d1, w_d2, w_r1, w_r2 = as_f(d1), as_f(d2), as_f(rho1), as_f(rho2)
        c1 = wp.zeros(n_pairs, dtype=wp.vec3, device=dev)
        c2 = wp.zeros(n_pairs, dtype=wp.vec3, device=dev)
        wp.launch(kf.contact_point_velocities_kernel, dim=n_pairs, inputs=[w_v1, w_v2, w_o1, w_o2, w_n, w_d1, w_d2],
                  outputs=[c1, c2], device=dev)
        feats = wp.zeros((n_pairs, len(self.flat.features)), dtype=wp.float32, device=dev)
        targets = wp.zeros((n_pairs, len(self.flat.targets)), dtype=wp.float32, device=dev)
        clamped = wp.zeros(1, dtype=wp.int32, device=dev)
        guard_counts = wp.zeros(4, dtype=wp.int32, device=dev)
        if self.flat.form == "contact_spin":
            wp.launch(kf.contact_spin_features_in_domain_kernel, dim=n_pairs,
                      inputs=[w_v1, w_v2, c1, c2, w_n, w_d1, w_d2, w_r1, w_r2, self.domain], outputs=[feats, clamped],
                      device=dev)
        else:
            kf.contact_features_in_domain(c1, c2, w_n, w_d1, w_d2, w_r1, w_r2, self.domain, feats, clamped)
        kf.eval_forest(self.forest, feats, targets, rows_per_thread=self.rows_per_thread)
        outs = [wp.zeros(n_pairs, dtype=wp.vec3, device=dev) for _ in range(4)]
        wp.launch(kf.apply_admissible_contact_spin_kernel, dim=n_pairs,
                  inputs=[w_v1, w_v2, w_o1, w_o2, w_n, w_d1, w_d2, w_r1, w_r2, targets, float(self.flat.friction_bound),
                          float(self.flat.separation_slack), int(spinning), int(guard)],
                  outputs=[*outs, guard_counts], device=dev)
        counts = guard_counts.numpy()
        self.last_counts = {"pairs": int(n_pairs), "clamped": int(clamped.numpy()[0]),
                            "guard_separation": int(counts[0]), "guard_coulomb": int(counts[1]),
                            "guard_energy": int(counts[2]), "guard_any": int(counts[3])}
        return tuple(o.numpy() for o in outs)


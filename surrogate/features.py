"""Features and targets of the surrogate collision model, in two forms.

Rows come from the collision data set (docs/file-formats.md): ``inputs`` columns
``v1x v1y v1z v2x v2y v2z d1 d2 rho1 rho2 nx ny nz offset`` and ``outputs`` columns
``u1x u1y u1z u2x u2y u2z ...`` (post-collision velocities first).

``paper`` form (reference paper, sec. 4.2): features are the six pre-collision velocity
components of the two particles (plus diameters and densities when they vary in the
training data), targets the post-collision ``u, v, w`` of particle 1, one model each.
Particle 2 follows by symmetry (swap the pair), so every row is also used swapped
(data augmentation). The paper's configurations are all central impacts, so this form
trains on the rows with ``offset == 0`` only (a non-central impact is not determined by
the six velocities: the contact normal is missing).

``contact`` form (default, beyond the paper): features in the contact frame,
``g_n = (v1 - v2) . n`` (approach speed along the normal n from 1 to 2),
``g_t = |(v1 - v2) - g_n n|`` (tangential slip speed), ``cos_angle = g_n/|g|`` (cosine of the
impact angle; the impact offset is implied by it), ``d1``, ``size_ratio = d2/d1``,
``density_ratio = rho2/rho1``.
Targets are the impulse on particle 2, ``J = J_n n + J_t t`` (t the unit tangential
slip direction), normalised by ``m* |g|`` (``1/m* = 1/m1 + 1/m2``) so they are O(1):
``impulse_n = J_n / (m*|g|)``, ``impulse_t = J_t / (m*|g|)``. For a frictionless impact
with restitution e, ``impulse_n = (1 + e) g_n/|g|`` and ``impulse_t = 0`` exactly
(docs/physics/references.md "Binary collision outcome"). The impulse is applied equal and opposite
(:func:`apply_contact_model`), so momentum ``m1 v1 + m2 v2`` is conserved exactly,
whatever the trees predict.

Input precision: raw features are rounded to float32 first (the engine's precision), and
the standardisation of eq. (17) is evaluated in float64 on those float32 values, then
rounded to float32 (what XGBoost sees). The flattened forest folds the scaler into float32
thresholds that reproduce exactly that comparison (surrogate/flatten.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hel_warp.errors import ConfigError

INPUT_COLUMNS = ("v1x", "v1y", "v1z", "v2x", "v2y", "v2z", "d1", "d2", "rho1", "rho2", "nx", "ny", "nz", "offset")
OUTPUT_COLUMNS = ("u1x", "u1y", "u1z", "u2x", "u2y", "u2z", "w1x", "w1y", "w1z", "w2x", "w2y", "w2z",
                  "contact_duration", "max_overlap", "max_normal_force")

FORMS = ("paper", "contact", "contact_spin")
CONTACT_FORMS = ("contact", "contact_spin")
"""The contact-frame forms: the engine's pairwise surrogate takes either."""
SPIN_INPUT_COLUMNS = ("o1x", "o1y", "o1z", "o2x", "o2y", "o2z")
"""Spins before the impact (rad/s): after INPUT_COLUMNS in a set made with ``--spin-fraction`` (zeros otherwise)."""
# Canonical feature order of each form: the flattened forest indexes into this list, and the
# engine kernels (kernels/forest.py) compute exactly these, in this order.
CANONICAL_FEATURES = {
    "paper": ("v1x", "v1y", "v1z", "v2x", "v2y", "v2z", "d1", "d2", "rho1", "rho2"),
    "contact": ("g_n", "g_t", "cos_angle", "d1", "size_ratio", "density_ratio"),
    "contact_spin": ("g_n", "g_t", "cos_angle", "d1", "size_ratio", "density_ratio", "u_along", "u_across"),
}
ALWAYS_USED = {"paper": ("v1x", "v1y", "v1z", "v2x", "v2y", "v2z"), "contact": ("g_n", "g_t", "cos_angle"),
               "contact_spin": ("g_n", "g_t", "cos_angle", "u_along", "u_across")}
TARGETS = {"paper": ("u", "v", "w"), "contact": ("impulse_n", "impulse_t"),
           "contact_spin": ("impulse_n", "impulse_t", "impulse_b", "moment_t", "moment_b")}
TARGET_SCALE = {"contact": ("cos_angle", "sin_angle"),
                "contact_spin": ("cos_angle", "sin_angle", "none", "sin_angle", "none")}
"""Scale of each target when trained scaled (surrogate/train.py, ``TrainConfig.target_scale``): the trees learn
impulse_n / cos_angle (about 1 + e: nearly constant over the incidence) and impulse_t / sin_angle; the forest
multiplies its tree sum back (hel_warp/collisions/forest.py TARGET_SCALES, kernels/forest.py ``scale_factor``)."""
TANGENT_EPS = 1e-6
"""Relative slip ``g_t/|g|`` below which the tangential direction is taken as zero (float32-safe)."""
CENTRAL_OFFSET_TOL = 1e-6
"""Rows with ``offset <= CENTRAL_OFFSET_TOL`` count as central impacts (paper form)."""


@dataclass
class CollisionData:
    """Rows of the collision data set, columns as in docs/file-formats.md."""

    inputs: np.ndarray
    """(N, 14) float64, INPUT_COLUMNS."""
    outputs: np.ndarray
    """(N, >=6) float64, OUTPUT_COLUMNS (only the first six, post velocities, are used)."""
    dataset_hash: str = ""
    attrs: dict = field(default_factory=dict)
    family: np.ndarray | None = None
    """(N,) int8 collision family (0 converging, 1 parallel, 2 head-on), when known."""
    spins: np.ndarray | None = None
    """(N, 6) float64 spins before the impact, SPIN_INPUT_COLUMNS (None: a spinless set, all zero)."""

    def col(self, name: str) -> np.ndarray:
        if name in SPIN_INPUT_COLUMNS:
            if self.spins is None:
                return np.zeros(self.inputs.shape[0])
            return self.spins[:, SPIN_INPUT_COLUMNS.index(name)]
        if name in INPUT_COLUMNS:
            return self.inputs[:, INPUT_COLUMNS.index(name)]
        return self.outputs[:, OUTPUT_COLUMNS.index(name)]

    def vec3(self, prefix: str) -> np.ndarray:
        """(N, 3) columns ``prefix + x, y, z`` (e.g. ``v1``, ``u2``, ``n``)."""
        return np.column_stack([self.col(prefix + "x"), self.col(prefix + "y"), self.col(prefix + "z")])

    def take(self, rows: np.ndarray) -> "CollisionData":
        family = None if self.family is None else self.family[rows]
        spins = None if self.spins is None else self.spins[rows]
        return CollisionData(self.inputs[rows], self.outputs[rows], self.dataset_hash, self.attrs, family, spins)

    def __len__(self) -> int:
        return int(self.inputs.shape[0])


def validate_data(data: CollisionData) -> None:
    """Refuse empty data, wrong shapes, and NaN/inf in the columns the models use."""
    if data.inputs.ndim != 2 or data.inputs.shape[1] != len(INPUT_COLUMNS):
        raise ConfigError(f"data set inputs must have shape (N, {len(INPUT_COLUMNS)}), got {data.inputs.shape}")
    if data.outputs.ndim != 2 or data.outputs.shape[1] < 6 or data.outputs.shape[0] != data.inputs.shape[0]:
        raise ConfigError(f"data set outputs must have shape (N, >=6) with N = {data.inputs.shape[0]}, "
                          f"got {data.outputs.shape}")
    if len(data) == 0:
        raise ConfigError("the data set is empty (0 rows); generate it with `hel-warp dataset` first")
    if data.spins is not None and data.spins.shape != (data.inputs.shape[0], len(SPIN_INPUT_COLUMNS)):
        raise ConfigError(f"data set spins must have shape (N, 6) with N = {data.inputs.shape[0]}, got "
                          f"{data.spins.shape}")
    used = np.concatenate([data.inputs, data.outputs[:, :6]] + ([] if data.spins is None else [data.spins]), axis=1)
    bad = ~np.all(np.isfinite(used), axis=1)
    if bad.any():
        rows = np.flatnonzero(bad)
        raise ConfigError(f"the data set holds NaN or infinite values in {rows.size} row(s) "
                          f"(first: row {int(rows[0])}); regenerate or drop those rows")
    for name in ("d1", "d2", "rho1", "rho2"):
        if np.any(data.col(name) <= 0):
            raise ConfigError(f"data set column {name} must be > 0 in every row")


def load_collision_data(path: str, *, samples_limit: int | None = None) -> CollisionData:
    """Read the data set written by ``hel-warp dataset`` (schema: docs/file-formats.md).

    Goes through ``surrogate.dataset.load_dataset`` (which refuses an incomplete or corrupted
    set: chunk flags, config ids, dataset_hash), then keeps the first ``samples_limit`` rows.
    """
    import os

    if not os.path.isdir(path):
        raise ConfigError(f"data set {path!r} not found; give the directory written by `hel-warp dataset --out`")
    from surrogate.dataset import load_dataset

    ds = load_dataset(path)
    attrs = dict(ds.attrs)
    columns = tuple(attrs.get("input_columns", INPUT_COLUMNS))
    if columns not in (INPUT_COLUMNS, INPUT_COLUMNS + SPIN_INPUT_COLUMNS):
        raise ConfigError(f"data set {path!r} input_columns {attrs.get('input_columns')} differ from the "
                          f"agreed schema {list(INPUT_COLUMNS)} (+ {list(SPIN_INPUT_COLUMNS)} for a spinning set)")
    if tuple(attrs.get("output_columns", OUTPUT_COLUMNS))[:6] != OUTPUT_COLUMNS[:6]:
        raise ConfigError(f"data set {path!r} output_columns {attrs.get('output_columns')} do not start with "
                          f"{list(OUTPUT_COLUMNS[:6])}")
    n = len(ds.inputs) if samples_limit is None else min(int(samples_limit), len(ds.inputs))
    inputs = np.asarray(ds.inputs[:n], dtype=np.float64)
    spins = inputs[:, len(INPUT_COLUMNS):].copy() if columns != INPUT_COLUMNS else None
    data = CollisionData(inputs[:, :len(INPUT_COLUMNS)].copy(), np.asarray(ds.outputs[:n], dtype=np.float64),
                         str(attrs.get("dataset_hash", "")), attrs, np.asarray(ds.family[:n]), spins)
    validate_data(data)
    return data


# ---------------------------------------------------------------------------------------------
# physics shared by both forms


def sphere_mass(d, rho):
    """Mass of a sphere of diameter ``d`` (m) and density ``rho`` (kg/m^3): rho pi d^3 / 6."""
    return rho * (math.pi / 6.0) * np.asarray(d, dtype=np.float64) ** 3


def contact_frame(v1, v2, n):
    """Relative velocity ``g = v1 - v2`` split along the unit normal ``n`` (from 1 to 2).

    Returns ``(g_n, g_t, t_hat, g_mag)``: ``g_n = g . n``, ``g_t = |g - g_n n|``, the unit
    tangential direction ``t_hat`` (zero where ``g_t <= TANGENT_EPS |g|``: a central impact,
    where the direction is rounding noise) and ``|g|``.
    """
    v1, v2, n = (np.asarray(a, dtype=np.float64) for a in (v1, v2, n))
    g = v1 - v2
    g_n = np.einsum("ij,ij->i", g, n)
    g_tvec = g - g_n[:, None] * n
    g_tvec = g_tvec - np.einsum("ij,ij->i", g_tvec, n)[:, None] * n  # second Gram-Schmidt pass
    g_t = np.linalg.norm(g_tvec, axis=1)
    g_mag = np.linalg.norm(g, axis=1)
    has_t = g_t > TANGENT_EPS * g_mag
    t_hat = np.where(has_t[:, None], g_tvec / np.where(has_t, g_t, 1.0)[:, None], 0.0)
    return g_n, g_t, t_hat, g_mag


def contact_spin_frame(v1, v2, n, d1, d2, omega1=None, omega2=None):
    """The contact_spin form's frame of spinning pairs (``n`` from 1 to 2; kernels/forest.py
    ``contact_spin_frame`` is the engine's twin).

    The contact points' relative velocity ``g_c = g + (r1 omega1 + r2 omega2) x n`` (g = v1 - v2) has the normal
    part ``g_n = g.n`` and the slip ``s = g_c - g_n n``; ``t_hat = s/|s|`` (where the slip is below TANGENT_EPS
    |g_c|: the direction of g's tangential part, or zero). The translational tangential velocity
    ``u = g - g_n n`` (it turns the centre line during the contact) splits into ``u_along = u.t_hat`` and
    ``u_across = |u - u_along t_hat|`` >= 0 along ``b_hat``. Spinless: ``g_c = g``, ``u_along = |s|``, ``u_across
    = 0``. Returns ``(g_n, slip, t_hat, b_hat, gc_mag, u_along, u_across)``."""
    v1, v2, n = (np.atleast_2d(np.asarray(a, dtype=np.float64)) for a in (v1, v2, n))
    r1 = 0.5 * np.broadcast_to(np.asarray(d1, np.float64), (v1.shape[0],))
    r2 = 0.5 * np.broadcast_to(np.asarray(d2, np.float64), (v1.shape[0],))
    w1 = np.zeros_like(v1) if omega1 is None else np.atleast_2d(np.asarray(omega1, np.float64))
    w2 = np.zeros_like(v1) if omega2 is None else np.atleast_2d(np.asarray(omega2, np.float64))
    g = v1 - v2
    gc = g + np.cross(r1[:, None] * w1 + r2[:, None] * w2, n)
    g_n = np.einsum("ij,ij->i", g, n)
    s = gc - np.einsum("ij,ij->i", gc, n)[:, None] * n
    s = s - np.einsum("ij,ij->i", s, n)[:, None] * n
    u = g - g_n[:, None] * n
    u = u - np.einsum("ij,ij->i", u, n)[:, None] * n
    slip = np.linalg.norm(s, axis=1)
    gc_mag = np.sqrt(g_n**2 + slip**2)
    u_mag = np.linalg.norm(u, axis=1)
    has_s = slip > TANGENT_EPS * gc_mag
    has_u = u_mag > TANGENT_EPS * np.maximum(gc_mag, u_mag)
    t_hat = np.where(has_s[:, None], s / np.where(has_s, slip, 1.0)[:, None],
                     np.where(has_u[:, None], u / np.where(has_u, u_mag, 1.0)[:, None], 0.0))
    u_along = np.einsum("ij,ij->i", u, t_hat)
    rest = u - u_along[:, None] * t_hat
    u_across = np.linalg.norm(rest, axis=1)
    has_b = u_across > TANGENT_EPS * np.maximum(gc_mag, u_mag)
    b_hat = np.where(has_b[:, None], rest / np.where(has_b, u_across, 1.0)[:, None], 0.0)
    u_across = np.where(has_b, u_across, 0.0)
    return g_n, slip, t_hat, b_hat, gc_mag, u_along, u_across


def apply_contact_spin_model(v1, v2, n, d1, d2, rho1, rho2, predicted_targets, omega1=None, omega2=None):
    """Post-collision velocities and spins from predicted contact_spin targets: ``J = m*|g_c| (impulse_n n +
    impulse_t t_hat + impulse_b b_hat)`` on particle 2 (:func:`contact_spin_frame`): ``v1' = v1 - J/m1``,
    ``v2' = v2 + J/m2``; the spins from the moment impulse ``Lambda = int n(t) x F_1 dt = -n x J_rot``,
    ``J_rot = m*|g_c| (moment_t t_hat + moment_b b_hat)`` (the tangential impulse as the spins see it: the centre
    line turns during the contact, so ``n x J`` with the first-touch normal is not the torque's integral):
    ``omega_k' = omega_k - r_k n x J_rot / I_k``. Returns ``(v1', v2', omega1', omega2')``."""
    v1, v2, n = (np.atleast_2d(np.asarray(a, dtype=np.float64)) for a in (v1, v2, n))
    targets = np.atleast_2d(np.asarray(predicted_targets, dtype=np.float64))
    d1 = np.broadcast_to(np.asarray(d1, np.float64), (v1.shape[0],))
    d2 = np.broadcast_to(np.asarray(d2, np.float64), (v1.shape[0],))
    m1, m2 = sphere_mass(d1, rho1), sphere_mass(d2, rho2)
    m_eff = m1 * m2 / (m1 + m2)
    _, _, t_hat, b_hat, gc_mag, _, _ = contact_spin_frame(v1, v2, n, d1, d2, omega1, omega2)
    impulse = (m_eff * gc_mag)[:, None] * (targets[:, 0:1] * n + targets[:, 1:2] * t_hat + targets[:, 2:3] * b_hat)
    w1 = np.zeros_like(v1) if omega1 is None else np.atleast_2d(np.asarray(omega1, np.float64))
    w2 = np.zeros_like(v1) if omega2 is None else np.atleast_2d(np.asarray(omega2, np.float64))
    j_rot = (m_eff * gc_mag)[:, None] * (targets[:, 3:4] * t_hat + targets[:, 4:5] * b_hat)
    kick = -np.cross(n, j_rot)
    return (v1 - impulse / m1[:, None], v2 + impulse / m2[:, None], w1 + kick / (0.2 * m1 * d1)[:, None],
            w2 + kick / (0.2 * m2 * d2)[:, None])


def apply_contact_model(v1, v2, n, d1, d2, rho1, rho2, predicted_targets):
    """Post-collision velocities from predicted contact-frame impulses (contact form).

    ``predicted_targets`` (N, 2): ``impulse_n, impulse_t`` = components of the impulse on
    particle 2 along ``n`` and ``t_hat``, divided by ``m* |g|``. With
    ``J = m*|g| (impulse_n n + impulse_t t_hat)``:
    ``v1' = v1 - J/m1``, ``v2' = v2 + J/m2`` — equal and opposite, so ``m1 v1 + m2 v2`` is
    unchanged (docs/physics/references.md "Binary collision outcome"). Returns ``(v1', v2')``, (N, 3) each.
    The Warp twin is ``apply_contact_impulse`` in kernels/forest.py.
    """
    v1, v2, n = (np.atleast_2d(np.asarray(a, dtype=np.float64)) for a in (v1, v2, n))
    targets = np.atleast_2d(np.asarray(predicted_targets, dtype=np.float64))
    m1, m2 = sphere_mass(d1, rho1), sphere_mass(d2, rho2)
    m_eff = m1 * m2 / (m1 + m2)
    _, _, t_hat, g_mag = contact_frame(v1, v2, n)
    scale = (m_eff * g_mag)[:, None]
    impulse = scale * (targets[:, 0:1] * n + targets[:, 1:2] * t_hat)
    return v1 - impulse / np.asarray(m1)[..., None], v2 + impulse / np.asarray(m2)[..., None]


# ---------------------------------------------------------------------------------------------
# the two forms


def raw_features(form: str, v1, v2, n, d1, d2, rho1, rho2, omega1=None, omega2=None) -> np.ndarray:
    """All canonical features of ``form`` (CANONICAL_FEATURES order), float64, shape (N, F); ``omega1`` /
    ``omega2``: the spins (contact_spin form only; None: spinless)."""
    v1, v2 = np.atleast_2d(v1), np.atleast_2d(v2)
    d1, d2, rho1, rho2 = (np.broadcast_to(np.asarray(a, dtype=np.float64), (v1.shape[0],)) for a in (d1, d2, rho1, rho2))
    if form == "paper":
        return np.column_stack([v1, v2, d1, d2, rho1, rho2]).astype(np.float64)
    if form == "contact":
        g_n, g_t, _, g_mag = contact_frame(v1, v2, np.atleast_2d(n))
        return np.column_stack([g_n, g_t, g_n / g_mag, d1, d2 / d1, rho2 / rho1])
    if form == "contact_spin":
        g_n, slip, _, _, gc_mag, u_along, u_across = contact_spin_frame(v1, v2, n, d1, d2, omega1, omega2)
        return np.column_stack([g_n, slip, g_n / gc_mag, d1, d2 / d1, rho2 / rho1, u_along, u_across])
    raise ConfigError(f"unknown form {form!r}; choose one of {', '.join(FORMS)}")


@dataclass
class FormRows:
    """The rows of one form, ready for training: raw features, targets and the lab-frame context."""

    form: str
    features: np.ndarray
    """(N, F) float32 raw features, CANONICAL_FEATURES[form] order (all of them)."""
    targets: np.ndarray
    """(N, T) float64."""
    group: np.ndarray
    """(N,) int64 data-set row each row came from (swapped rows share it; splits go by group)."""
    data: CollisionData
    """The data-set rows, one per distinct group (index = group)."""


def form_rows(form: str, data: CollisionData) -> FormRows:
    """Features and targets of ``form`` for every usable row of ``data``."""
    validate_data(data)
    if form == "paper":
        central = np.flatnonzero(data.col("offset") <= CENTRAL_OFFSET_TOL)
        if central.size == 0:
            raise ConfigError("the paper form trains on central impacts (offset 0) and the data set has none; "
                              "use --form contact")
        sub = data.take(central)
        c = sub.col
        v1, v2, u1, u2 = sub.vec3("v1"), sub.vec3("v2"), sub.vec3("u1"), sub.vec3("u2")
        f_12 = raw_features("paper", v1, v2, None, c("d1"), c("d2"), c("rho1"), c("rho2"))
        f_21 = raw_features("paper", v2, v1, None, c("d2"), c("d1"), c("rho2"), c("rho1"))
        idx = np.arange(len(sub))
        return FormRows(form, np.concatenate([f_12, f_21]).astype(np.float32), np.concatenate([u1, u2]),
                        np.concatenate([idx, idx]), sub)
    if form == "contact":
        c = data.col
        v1, v2, n, u1, u2 = data.vec3("v1"), data.vec3("v2"), data.vec3("n"), data.vec3("u1"), data.vec3("u2")
        g_n, g_t, t_hat, g_mag = contact_frame(v1, v2, n)
        if np.any(g_mag <= 0):
            raise ConfigError(f"{int(np.sum(g_mag <= 0))} data-set row(s) have zero relative velocity "
                              "(no impact); drop them")
        m1, m2 = sphere_mass(c("d1"), c("rho1")), sphere_mass(c("d2"), c("rho2"))
        m_eff = m1 * m2 / (m1 + m2)
        # impulse on particle 2; the mean of both particles' momentum changes
        impulse = 0.5 * (m2[:, None] * (u2 - v2) - m1[:, None] * (u1 - v1))
        scale = m_eff * g_mag
        targets = np.column_stack([np.einsum("ij,ij->i", impulse, n) / scale,
                                   np.einsum("ij,ij->i", impulse, t_hat) / scale])
        feats = raw_features("contact", v1, v2, n, c("d1"), c("d2"), c("rho1"), c("rho2"))
        return FormRows(form, feats.astype(np.float32), targets, np.arange(len(data)), data)
    if form == "contact_spin":
        c = data.col
        v1, v2, n, u1, u2 = data.vec3("v1"), data.vec3("v2"), data.vec3("n"), data.vec3("u1"), data.vec3("u2")
        w1, w2 = data.vec3("o1"), data.vec3("o2")
        g_n, slip, t_hat, b_hat, gc_mag, _, _ = contact_spin_frame(v1, v2, n, c("d1"), c("d2"), w1, w2)
        if np.any(gc_mag <= 0):
            raise ConfigError(f"{int(np.sum(gc_mag <= 0))} data-set row(s) have a zero contact-point relative "
                              "velocity (no impact); drop them")
        m1, m2 = sphere_mass(c("d1"), c("rho1")), sphere_mass(c("d2"), c("rho2"))
        impulse = 0.5 * (m2[:, None] * (u2 - v2) - m1[:, None] * (u1 - v1))
        scale = (m1 * m2 / (m1 + m2)) * gc_mag
        # the moment impulse Lambda = int n(t) x F_1 dt: I_k (omega_k' - omega_k) = r_k Lambda for both spheres
        lam = 0.5 * ((0.2 * m1 * c("d1"))[:, None] * (data.vec3("w1") - w1)
                     + (0.2 * m2 * c("d2"))[:, None] * (data.vec3("w2") - w2))
        targets = np.column_stack([np.einsum("ij,ij->i", impulse, n) / scale,
                                   np.einsum("ij,ij->i", impulse, t_hat) / scale,
                                   np.einsum("ij,ij->i", impulse, b_hat) / scale,
                                   -np.einsum("ij,ij->i", lam, np.cross(n, t_hat)) / scale,
                                   -np.einsum("ij,ij->i", lam, np.cross(n, b_hat)) / scale])
        feats = raw_features("contact_spin", v1, v2, n, c("d1"), c("d2"), c("rho1"), c("rho2"), w1, w2)
        return FormRows(form, feats.astype(np.float32), targets, np.arange(len(data)), data)
    raise ConfigError(f"unknown form {form!r}; choose one of {', '.join(FORMS)}")


def rows_of_groups(rows: FormRows, groups: np.ndarray) -> np.ndarray:
    """Row indices of ``rows`` for the data-set rows ``groups``; paper form: direct, then swapped."""
    groups = np.asarray(groups, dtype=np.int64)
    if rows.form == "paper":
        return np.concatenate([groups, groups + len(rows.data)])
    return groups


def used_features(form: str, features: np.ndarray) -> list[str]:
    """Canonical features that vary in ``features`` (velocity features always kept)."""
    names = CANONICAL_FEATURES[form]
    keep = []
    for j, name in enumerate(names):
        col = features[:, j]
        if name in ALWAYS_USED[form] or (col.size and np.ptp(col) > 0):
            keep.append(name)
    return keep


def standardize(raw_f32: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """Eq. (17) exactly as the models see it: float64 ``(x - mean)/std`` of float32 ``x``, then float32."""
    x = np.asarray(raw_f32, dtype=np.float32).astype(np.float64)
    return ((x - np.asarray(mean, dtype=np.float64)) / np.asarray(std, dtype=np.float64)).astype(np.float32)


def predictions_to_lab(form: str, data: CollisionData, group: np.ndarray, predicted: np.ndarray):
    """Lab-frame post velocities of particles 1 and 2 from target predictions.

    ``paper``: rows as built by :func:`rows_of_groups` — all direct rows first (they predict
    particle 1), then the swapped rows in the same order (they predict particle 2).
    ``contact``: :func:`apply_contact_model`.
    Returns ``(rows, u1_pred, u2_pred)`` with ``rows`` the data-set rows (index into ``data``).
    """
    if form == "contact":
        sel = data.take(group)
        c = sel.col
        v1, v2, n = sel.vec3("v1"), sel.vec3("v2"), sel.vec3("n")
        u1, u2 = apply_contact_model(v1, v2, n, c("d1"), c("d2"), c("rho1"), c("rho2"), predicted)
        return group, u1, u2
    if form == "contact_spin":
        sel = data.take(group)
        c = sel.col
        u1, u2, _, _ = apply_contact_spin_model(sel.vec3("v1"), sel.vec3("v2"), sel.vec3("n"), c("d1"), c("d2"),
                                                c("rho1"), c("rho2"), predicted, sel.vec3("o1"), sel.vec3("o2"))
        return group, u1, u2
    half = predicted.shape[0] // 2
    # form_rows stacks all direct rows first, then all swapped ones; split keeps that order
    return group[:half], predicted[:half], predicted[half:]


# ---------------------------------------------------------------------------------------------
# TEST FIXTURE: analytic data set (not DEM). Used by the tests and the benchmark until (and
# besides) the DEM data set of surrogate/dataset.py.


def synthetic_collisions(samples: int, *, seed: int = 0, restitution: float = 0.9, central_fraction: float = 0.5,
                         diameter: float = 315e-6, density: float = 1000.0, polydisperse: bool = False,
                         max_speed: float = 20.0) -> CollisionData:
    """TEST FIXTURE — frictionless binary impacts with restitution ``e``, solved analytically.

    ``v1' = v1 - (1+e) m2/(m1+m2) (g.n) n``, ``v2' = v2 + (1+e) m1/(m1+m2) (g.n) n`` with
    ``g = v1 - v2`` (docs/physics/references.md "Binary collision outcome"); no spin. Velocities follow
    eq. (16) (speed uniform in [0, max_speed], direction uniform on the sphere) in the
    three families: 0 converging (independent directions), 1 parallel (same direction, the
    rear one faster), 2 head-on (opposite directions). The contact normal makes the angle
    ``asin(offset)`` with ``g``; ``central_fraction`` of rows have offset 0, the others
    uniform offset in [0, 0.95). Written in the data-set schema of docs/file-formats.md.
    """
    rng = np.random.default_rng(seed)

    def directions(k):
        phi = rng.uniform(0.0, 2.0 * math.pi, k)
        cos_t = rng.uniform(-1.0, 1.0, k)
        sin_t = np.sqrt(1.0 - cos_t ** 2)
        return np.column_stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t])  # eq. (16)

    family = rng.integers(0, 3, samples)
    s1 = rng.uniform(0.5, max_speed, samples)
    s2 = rng.uniform(0.5, max_speed, samples)
    e1 = directions(samples)
    e2 = directions(samples)
    e2 = np.where((family == 1)[:, None], e1, np.where((family == 2)[:, None], -e1, e2))
    lo, hi = np.minimum(s1, s2), np.maximum(s1, s2)
    s1 = np.where(family == 1, hi, s1)  # particle 1 is the rear, faster one
    s2 = np.where(family == 1, lo * 0.9, s2)
    v1, v2 = s1[:, None] * e1, s2[:, None] * e2
    if polydisperse:
        d1 = diameter * rng.uniform(0.6, 1.4, samples)
        d2 = diameter * rng.uniform(0.6, 1.4, samples)
        rho1 = density * rng.uniform(0.8, 1.25, samples)
        rho2 = density * rng.uniform(0.8, 1.25, samples)
    else:
        d1 = d2 = np.full(samples, diameter)
        rho1 = rho2 = np.full(samples, density)
    g = v1 - v2
    g_hat = g / np.linalg.norm(g, axis=1, keepdims=True)
    offset = np.where(rng.uniform(size=samples) < central_fraction, 0.0, rng.uniform(0.0, 0.95, samples))
    # a unit vector perpendicular to g_hat
    aux_axis = np.where((np.abs(g_hat[:, 0]) < 0.9)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    p = np.cross(g_hat, aux_axis)
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    q = np.cross(g_hat, p)
    psi = rng.uniform(0.0, 2.0 * math.pi, samples)
    perp = np.cos(psi)[:, None] * p + np.sin(psi)[:, None] * q
    n = np.sqrt(1.0 - offset ** 2)[:, None] * g_hat + offset[:, None] * perp
    m1, m2 = sphere_mass(d1, rho1), sphere_mass(d2, rho2)
    g_n = np.einsum("ij,ij->i", g, n)
    u1 = v1 - ((1 + restitution) * m2 / (m1 + m2) * g_n)[:, None] * n
    u2 = v2 + ((1 + restitution) * m1 / (m1 + m2) * g_n)[:, None] * n
    inputs = np.column_stack([v1, v2, d1, d2, rho1, rho2, n, offset])
    outputs = np.zeros((samples, len(OUTPUT_COLUMNS)))
    outputs[:, 0:3], outputs[:, 3:6] = u1, u2
    import hashlib

    digest = hashlib.sha256(inputs.tobytes() + outputs.tobytes()).hexdigest()
    attrs = {"synthetic": "analytic frictionless fixture (surrogate.features.synthetic_collisions)",
             "restitution": restitution, "seed": seed, "samples": samples,
             "input_columns": list(INPUT_COLUMNS), "output_columns": list(OUTPUT_COLUMNS), "dataset_hash": digest}
    return CollisionData(inputs, outputs, digest, attrs, family.astype(np.int8))


def write_synthetic_zarr(path: str, samples: int, **kwargs) -> CollisionData:
    """TEST FIXTURE — write :func:`synthetic_collisions` as a complete zarr data set (docs/file-formats.md schema)."""
    import zarr

    data = synthetic_collisions(samples, **kwargs)
    group = zarr.open_group(path, mode="w")
    group.create_array("inputs", data=data.inputs)
    group.create_array("outputs", data=data.outputs)
    group.create_array("config_id", data=np.arange(samples, dtype=np.int64))
    group.create_array("family", data=data.family)
    group.create_array("chunk_done", data=np.ones(1, dtype=bool))
    group.attrs.update(data.attrs | {"chunk_size": samples})
    return data


def target_scale_values(name: str, raw_features: np.ndarray) -> np.ndarray:
    """(N,) float32 multiplier of a scaled target for contact-form raw features (N, 6), as the kernel computes it
    (kernels/forest.py ``scale_factor``, float32): 1, cos_angle or sqrt(max(1 - cos_angle^2, 0))."""
    c = np.asarray(raw_features, dtype=np.float32)[:, CANONICAL_FEATURES["contact"].index("cos_angle")]
    if name == "none":
        return np.ones_like(c)
    if name == "cos_angle":
        return c.copy()
    if name == "sin_angle":
        return np.sqrt(np.maximum(np.float32(1.0) - c * c, np.float32(0.0)))
    raise ConfigError(f"unknown target scale {name!r}; expected none, cos_angle or sin_angle")


def scale_predictions(tree_sums: np.ndarray, target_scale: list | None, raw_features: np.ndarray) -> np.ndarray:
    """XGBoost's predictions (N, T) of the trees -> the model's targets: each column times its scale (float32, the
    engine's arithmetic). ``target_scale``: per target a name of TARGET_SCALE (None: unscaled)."""
    out = np.asarray(tree_sums, dtype=np.float32).copy()
    if out.ndim == 1:
        out = out[:, None]
    for k, name in enumerate(target_scale or ()):
        if name != "none":
            out[:, k] = out[:, k] * target_scale_values(name, raw_features)
    return out

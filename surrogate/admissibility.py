"""The training domain of a contact-form model and the physical admissibility of its outcomes.

Contact form (surrogate/features.py): the normalised impulse on particle 2 is ``a`` along the
first-touch normal ``n`` and ``b`` along the slip direction ``t_hat`` (units m*|g|); with
``c = g_n/|g|`` and ``s = sqrt(1 - c^2)`` the post-collision relative velocity is
``g' = |g| ((c - a) n + (s - b) t_hat)``. The engine's guard (kernels/forest.py
``admissible_impulse``) makes every outcome separate along n (``a >= c``), stay within a Coulomb
bound (``b <= friction_bound a``) and never gain kinetic energy (``|g'| <= |g|``).

What the DEM itself does (measured on the default 200,000-row sets, 315 um polyethylene, e = 0.9,
rows run in the centre-of-mass frame):

- energy: ``|g'|/|g| <= 1`` on every row (largest ``|g'|^2/|g|^2`` 1 + 5e-7: float32);
- Coulomb, in the frame of the FIRST-TOUCH normal: with mu = 0.3 the largest ``b/(mu a)`` is 0.9992
  (sliding sits at the bound), so ``friction_bound`` = mu; frictionless, ``b <= 4e-7`` (b is
  negative: the centre line turns while the soft spheres slide, docs/physics/references.md), largest ``b/a``
  0.0023 at ``a ~ 1e-4`` (89.7 deg). So ``friction_bound = max(mu, largest b/a)``;
- separation along the first-touch normal: NOT always. Beyond ~70 deg and above a few m/s the
  soft spheres slide past each other before the normal motion is reversed, and ``a < c``
  (``(v1' - v2').n > 0`` along the first-touch normal, separating along the turned centre line):
  8.4-8.8 % of the rows; 2.9 % at 70-80 deg, 33 % at 80-85 deg, 73 % beyond 85 deg; deficit
  ``c - a`` up to 0.09 (|g| ~ 40 m/s), 0.057 at 20 m/s and 85 deg. The guard's separation rule moves
  those outcomes by ``(c - a)|g|``: an error floor of the engine against the DEM, reported per angle
  band by :func:`dem_admissibility` and by the sweep (surrogate/sweep.py).
"""

from __future__ import annotations

import numpy as np

from hel_warp.errors import ConfigError

ANGLE_BANDS = ((0.0, 30.0), (30.0, 60.0), (60.0, 70.0), (70.0, 80.0), (80.0, 85.0), (85.0, 90.0))
"""Incidence-angle bands (degrees, between g and the first-touch normal) of the reports."""
RATIO_MIN_IMPULSE = 1e-4
"""Rows with a normal impulse a below this (units m*|g|, extreme grazing) do not enter the largest
b/a: there b is round-off of a 1e-5 |g| deflection (the Coulomb clip moves such an outcome by < 1e-5 |g|)."""
MATERIAL_CORRECTION = 1e-3
"""A guard correction that moves the post-collision relative velocity by more than this fraction of
|g| (0.1 %, a twentieth of the 2 % accuracy target) counts as material in the metrics."""
FLAG_FRACTION = 1e-3
"""A model is flagged when the guard moves more than this fraction of its test outcomes farther from the DEM by a
material amount, or corrects more than this fraction of the DEM outcomes themselves (the guard then contradicts
the physics it was trained on)."""


def outcome_components(features: np.ndarray, targets: np.ndarray):
    """``(c, s, a, b)`` of contact-form rows: features (N, 6) canonical, targets (N, 2)."""
    c = np.clip(np.asarray(features[:, 2], dtype=np.float64), 0.0, 1.0)
    s = np.sqrt(np.clip(1.0 - c * c, 0.0, None))
    return c, s, np.asarray(targets[:, 0], np.float64), np.asarray(targets[:, 1], np.float64)


def incidence_deg(c: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def choose_friction_bound(features: np.ndarray, targets: np.ndarray, friction: float) -> tuple[float, str, float]:
    """``(friction_bound, rule, largest b/a)``: the Coulomb guard bound from the DEM rows.

    ``friction_bound = max(mu, largest b/a over the rows with a >= RATIO_MIN_IMPULSE)``: never below
    mu, and no DEM outcome of the data is clipped by it (up to rows of a < 1e-4 m*|g|).
    """
    c, s, a, b = outcome_components(features, targets)
    ok = a >= RATIO_MIN_IMPULSE
    ratio_max = float(np.max(b[ok] / a[ok])) if ok.any() else 0.0
    bound = max(float(friction), ratio_max)
    rule = (f"max(mu = {friction:g}, largest b/a of the DEM rows with a >= {RATIO_MIN_IMPULSE:g} m*|g| "
            f"= {ratio_max:.6g}); b, a: impulse along t_hat and the first-touch normal")
    bound32 = np.float32(bound)
    if float(bound32) < bound:  # the kernel compares in float32: round up, never below the data
        bound32 = np.nextafter(bound32, np.float32(np.inf))
    return float(bound32), rule, ratio_max


def dem_admissibility(features: np.ndarray, targets: np.ndarray, friction: float, friction_bound: float) -> dict:
    """How the DEM outcomes themselves sit against the guard, per incidence band (and in all)."""
    c, s, a, b = outcome_components(features, targets)
    ang = incidence_deg(c)
    energy = (c - a) ** 2 + (s - b) ** 2
    ok = a >= RATIO_MIN_IMPULSE
    ratio = np.where(ok, b / np.where(ok, a, 1.0), -np.inf)

    def stats(m):
        if not m.any():
            return {"rows": 0}
        return {"rows": int(m.sum()),
                "frac_not_separating": float(np.mean(a[m] < c[m])),
                "max_separation_deficit": float(np.max(c[m] - a[m])),
                "max_energy_ratio": float(np.max(energy[m])),
                "max_b_over_a": float(np.max(ratio[m])) if np.any(ok[m]) else None,
                "max_b_over_mu_a": (float(np.max(ratio[m]) / friction) if friction > 0 and np.any(ok[m]) else None),
                "frac_above_friction_bound": float(np.mean(b[m] > friction_bound * a[m] * (1 + 1e-6) + 1e-12))}

    bands = {f"{lo:g}-{hi:g}": stats((ang >= lo) & (ang < hi if hi < 90 else ang <= 90)) for lo, hi in ANGLE_BANDS}
    return {"all": stats(np.ones_like(a, dtype=bool)), "bands": bands}


def training_domain(form: str, features: np.ndarray, *, friction: float, friction_bound: float, rule: str,
                    **extra) -> dict:
    """The forest's ``domain`` section: float32 min/max of each canonical feature of the training rows."""
    from surrogate.features import CANONICAL_FEATURES

    x = np.asarray(features, dtype=np.float32)
    names = CANONICAL_FEATURES[form]
    if x.ndim != 2 or x.shape[1] != len(names) or x.shape[0] == 0:
        raise ConfigError(f"training_domain needs (N, {len(names)}) features, got {x.shape}")
    lo = np.nanmin(x, axis=0)
    hi = np.nanmax(x, axis=0)
    return {"features": list(names), "lo": [float(v) for v in lo], "hi": [float(v) for v in hi],
            "friction": float(friction), "friction_bound": float(friction_bound), "friction_bound_rule": rule,
            "rows": int(x.shape[0]), **extra}


def guarded_targets(cos_angle: np.ndarray, targets: np.ndarray, friction_bound: float, separation_slack: float = 0.0):
    """``(guarded (N, 2), flags (N,))``: the Warp guard (``kernels.forest.admissible_impulse``) row by row;
    ``separation_slack`` as the engine's (``FlatForest.separation_slack``), 0 for the strict separation rule."""
    import warp as wp

    from kernels.forest import admissible_targets

    cos_w = wp.array(np.ascontiguousarray(cos_angle, dtype=np.float32), dtype=wp.float32, device="cpu")
    t_w = wp.array(np.ascontiguousarray(targets, dtype=np.float32), dtype=wp.float32, device="cpu")
    out = wp.zeros(t_w.shape, dtype=wp.float32, device="cpu")
    flags = wp.zeros(cos_w.shape[0], dtype=wp.int32, device="cpu")
    admissible_targets(cos_w, t_w, friction_bound, out, flags, separation_slack=separation_slack)
    return out.numpy().astype(np.float64), flags.numpy()

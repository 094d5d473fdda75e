"""The surrogate against the verified DEM over incidence angle and speed (the model's acceptance figure).

For each incidence angle chi (between g = v1 - v2 and the first-touch normal n), relative speed
|g| and size ratio d2/d1, one isolated sphere-sphere impact is run by the batched DEM that
``hel-warp impact`` runs (``hel_warp.collisions.impact.simulate_pairs`` with its default step: eq. (12),
40 steps per contact), all pairs in one launch, in the centre-of-mass frame. The surrogate
predicts the same pairs through the engine's path (``ForestPredictor.predict_pairs``: domain
clamp + admissibility guard; and bare, ``guard=False``). The error is
``|g'_surrogate - g'_DEM| / |g|`` of the post-collision relative velocity, in % of |g|, reported
per angle band (max and 99th percentile). ``dem_guard_floor`` is how far the DEM outcome itself
lies from the guard's admissible set (``surrogate.admissibility``): the least error any guarded
model can have there.
"""

from __future__ import annotations

import math

import numpy as np

SWEEP_ANGLES = tuple(float(a) for a in np.concatenate([np.arange(0.0, 80.0, 2.5), np.arange(80.0, 89.5, 0.5),
                                                        [89.5]]))
"""Incidence angles of the sweep, degrees (0-89.5, denser beyond 80)."""
SWEEP_SPEEDS = tuple(float(v) for v in np.geomspace(0.1, 20.0, 12))
"""Relative speeds |g| of the sweep, m/s (0.1-20, log spaced)."""
SWEEP_BANDS = ((0.0, 30.0), (30.0, 60.0), (60.0, 70.0), (70.0, 80.0), (80.0, 85.0), (85.0, 89.5))
TARGET_PERCENT = 2.0
"""Acceptance: post-collision relative velocity within 2 % of |g|."""


def sweep_pairs(*, diameter: float, size_ratios, density: float, angles=SWEEP_ANGLES, speeds=SWEEP_SPEEDS):
    """Pairs of the sweep (COM frame, sphere 1 moving along -z): dict of float64 arrays."""
    chi, speed, ratio = (a.ravel() for a in np.meshgrid(np.radians(angles), speeds, size_ratios, indexing="ij"))
    d1 = np.full(chi.shape, float(diameter))
    d2 = d1 * ratio
    m1, m2 = d1**3, d2**3  # same density: masses in proportion
    g_hat = np.array([0.0, 0.0, -1.0])
    side = np.array([1.0, 0.0, 0.0])
    normal = np.cos(chi)[:, None] * g_hat + np.sin(chi)[:, None] * side
    g = speed[:, None] * g_hat
    v1 = (m2 / (m1 + m2))[:, None] * g
    v2 = -(m1 / (m1 + m2))[:, None] * g
    return {"angle": np.degrees(chi), "speed": speed, "ratio": ratio, "d1": d1, "d2": d2,
            "rho": np.full(chi.shape, float(density)), "normal": normal, "v1": v1, "v2": v2}


def dem_outcomes(pairs: dict, material: dict, contact_model: str = "hertz") -> tuple[np.ndarray, np.ndarray]:
    """Post-collision velocities (u1, u2) of the sweep pairs from the DEM of ``hel-warp impact``."""
    from hel_warp.errors import HelWarpError
    from hel_warp.collisions.impact import place_just_apart, simulate_pairs, stable_time_step

    r1, r2 = 0.5 * pairs["d1"], 0.5 * pairs["d2"]
    e_mod, nu = float(material["youngs_modulus"]), float(material["poisson_ratio"])
    vmax = np.maximum(20.0, pairs["speed"])
    stable = np.minimum(stable_time_step(r1, pairs["rho"], e_mod, nu, vmax), stable_time_step(r2, pairs["rho"], e_mod,
                                                                                               nu, vmax))
    x1, x2 = place_just_apart(normal=pairs["normal"], velocity1=pairs["v1"], velocity2=pairs["v2"], radius1=r1,
                              radius2=r2, dt=stable)
    res = simulate_pairs(x1=x1, x2=x2, v1=pairs["v1"], v2=pairs["v2"], radius1=r1, radius2=r2,
                         density1=pairs["rho"], density2=pairs["rho"], youngs1=e_mod, poisson1=nu,
                         restitution=float(material["restitution"]), friction=float(material["friction"]),
                         rolling_friction=float(material.get("rolling_friction", 0.0)), model=contact_model)
    if not (res.touched & res.separated).all():
        raise HelWarpError(f"{int((~(res.touched & res.separated)).sum())} sweep pairs did not complete a collision")
    return res.velocity1, res.velocity2


def _band_table(angle, errors: dict) -> dict:
    table = {}
    for lo, hi in SWEEP_BANDS:
        m = (angle >= lo) & ((angle < hi) if hi < 89.5 else (angle <= hi))
        row = {"pairs": int(m.sum())}
        for name, err in errors.items():
            row[f"{name}_max_pct"] = float(np.max(err[m])) if m.any() else None
            row[f"{name}_p99_pct"] = float(np.percentile(err[m], 99)) if m.any() else None
        table[f"{lo:g}-{hi:g}"] = row
    return table


def sweep_against_dem(flat, material: dict, *, contact_model: str = "hertz", diameter: float, density: float,
                      size_ratios=None, angles=SWEEP_ANGLES, speeds=SWEEP_SPEEDS, device="cpu") -> dict:
    """The sweep of a contact-form ``FlatForest``; ``size_ratios`` default (1, an unequal one in the domain)."""
    from hel_warp.collisions.forest import CANONICAL_FEATURES, ForestPredictor
    from surrogate.admissibility import guarded_targets

    if flat.form not in ("contact", "contact_spin"):
        from hel_warp.errors import ConfigError

        raise ConfigError("the sweep needs a contact-form model")
    k = CANONICAL_FEATURES["contact"].index("size_ratio")
    ratio_hi = float(flat.feature_hi[k])
    if size_ratios is None:
        size_ratios = (1.0,) if ratio_hi < 1.0 + 1e-3 else (1.0, round(1.0 + 0.75 * (ratio_hi - 1.0), 4))
    pairs = sweep_pairs(diameter=diameter, size_ratios=size_ratios, density=density, angles=angles, speeds=speeds)
    u1, u2 = dem_outcomes(pairs, material, contact_model)
    g = pairs["v1"] - pairs["v2"]
    g_mag = np.linalg.norm(g, axis=1)
    g_dem = u1 - u2
    predictor = ForestPredictor(flat, device=device)
    args = (pairs["v1"], pairs["v2"], pairs["d1"], pairs["d2"], pairs["rho"], pairs["rho"])
    s1, s2 = predictor.predict_pairs(*args, normal=pairs["normal"], guard=True)
    counts = dict(predictor.last_counts)
    if flat.form == "contact":
        r1, r2 = predictor.predict_pairs(*args, normal=pairs["normal"], guard=False)
    else:  # the contact_spin path is always guarded: "model" is the engine's outcome
        r1, r2 = s1, s2
    engine = 100.0 * np.linalg.norm((s1 - s2) - g_dem, axis=1) / g_mag
    model = 100.0 * np.linalg.norm((r1 - r2) - g_dem, axis=1) / g_mag
    # the DEM outcome's own distance to the admissible set (normalised impulse components)
    n = pairs["normal"]
    c = np.einsum("ij,ij->i", g, n) / g_mag
    t_vec = g - (c * g_mag)[:, None] * n
    t_hat = t_vec / np.maximum(np.linalg.norm(t_vec, axis=1), 1e-300)[:, None]
    dg = g - g_dem  # = |g| (a n + b t_hat)
    dem_ab = np.column_stack([np.einsum("ij,ij->i", dg, n), np.einsum("ij,ij->i", dg, t_hat)]) / g_mag[:, None]
    guarded, _ = guarded_targets(c, dem_ab, flat.friction_bound)
    floor = 100.0 * np.linalg.norm(guarded - dem_ab, axis=1)
    errors = {"model": model, "engine": engine, "dem_guard_floor": floor}
    worst = int(np.argmax(engine))
    return {
        "reference": "hel_warp.collisions.impact.simulate_pairs (hel-warp impact's DEM, default step), sphere-sphere, COM frame",
        "angles_deg": [float(a) for a in angles], "speeds_m_s": [float(v) for v in speeds],
        "size_ratios": [float(r) for r in size_ratios], "diameter": float(diameter), "pairs": int(g_mag.size),
        "target_pct": TARGET_PERCENT, "bands": _band_table(pairs["angle"], errors),
        "model_max_pct": float(model.max()), "engine_max_pct": float(engine.max()),
        "model_within_target": bool(model.max() <= TARGET_PERCENT),
        "engine_within_target": bool(engine.max() <= TARGET_PERCENT),
        "engine_worst": {"angle_deg": float(pairs["angle"][worst]), "speed_m_s": float(pairs["speed"][worst]),
                         "size_ratio": float(pairs["ratio"][worst]), "error_pct": float(engine[worst])},
        "engine_counts": counts,
    }


SPIN_RATIOS = (0.1, 0.3, 1.0, 2.0)
"""Spin sweep: the largest surface speed r|omega| of each sphere, in units of |g| (drawn uniformly below it)."""


def spin_pairs(*, diameter: float, size_ratios, density: float, spin_ratio: float, n: int, seed: int = 0,
               speeds=(0.1, 20.0)) -> dict:
    """Random spinning pairs (COM frame): normal and slip plane isotropic, incidence of the translational g
    uniform in cos (0-89 deg), |g| log-uniform in ``speeds``, each sphere's spin axis isotropic and its surface speed
    r|omega| uniform in [0, spin_ratio |g|]; size ratio drawn from ``size_ratios``."""
    rng = np.random.default_rng(seed)
    unit = lambda a: a / np.linalg.norm(a, axis=1)[:, None]  # noqa: E731
    ratio = rng.choice(np.asarray(size_ratios, float), n)
    d1 = np.full(n, float(diameter))
    d2 = d1 * ratio
    normal = unit(rng.normal(size=(n, 3)))
    t_hat = unit(np.cross(normal, rng.normal(size=(n, 3))))
    speed = np.exp(rng.uniform(np.log(speeds[0]), np.log(speeds[1]), n))
    chi = np.arccos(rng.uniform(math.cos(math.radians(89.0)), 1.0, n))
    g = speed[:, None] * (np.cos(chi)[:, None] * normal + np.sin(chi)[:, None] * t_hat)
    m1, m2 = d1**3, d2**3
    omega1 = unit(rng.normal(size=(n, 3))) * (spin_ratio * speed * rng.uniform(0, 1, n) / (0.5 * d1))[:, None]
    omega2 = unit(rng.normal(size=(n, 3))) * (spin_ratio * speed * rng.uniform(0, 1, n) / (0.5 * d2))[:, None]
    return {"angle": np.degrees(chi), "speed": speed, "ratio": ratio, "d1": d1, "d2": d2,
            "rho": np.full(n, float(density)), "normal": normal, "v1": (m2 / (m1 + m2))[:, None] * g,
            "v2": -(m1 / (m1 + m2))[:, None] * g, "omega1": omega1, "omega2": omega2}


def spin_sweep_against_dem(flat, material: dict, *, contact_model: str = "hertz", diameter: float, density: float,
                           size_ratios=(1.0,), spin_ratios=SPIN_RATIOS, n: int = 2000, seed: int = 0,
                           device="cpu") -> dict:
    """Spinning impacts: the engine's spin path (``ForestPredictor.predict_pairs(omega1=, omega2=)``) and the spinless
    path (spins ignored, as without ``particle_spin``) against the DEM with the spins. Errors in % of the
    translational |g|: post-collision relative velocity ``g'`` and post-collision spins as surface speeds
    ``r |omega' - omega'_DEM|`` (the larger of the pair's two)."""
    from hel_warp.errors import HelWarpError
    from hel_warp.collisions.forest import ForestPredictor
    from hel_warp.collisions.impact import place_just_apart, simulate_pairs, stable_time_step

    predictor = ForestPredictor(flat, device=device)
    e_mod, nu = float(material["youngs_modulus"]), float(material["poisson_ratio"])
    rows = {}
    for k, spin_ratio in enumerate(spin_ratios):
        p = spin_pairs(diameter=diameter, size_ratios=size_ratios, density=density, spin_ratio=spin_ratio, n=n,
                       seed=seed + k)
        r1, r2 = 0.5 * p["d1"], 0.5 * p["d2"]
        vmax = np.maximum(20.0, p["speed"])
        stable = np.minimum(stable_time_step(r1, p["rho"], e_mod, nu, vmax),
                            stable_time_step(r2, p["rho"], e_mod, nu, vmax))
        x1, x2 = place_just_apart(normal=p["normal"], velocity1=p["v1"], velocity2=p["v2"], radius1=r1, radius2=r2,
                                  dt=stable)
        res = simulate_pairs(x1=x1, x2=x2, v1=p["v1"], v2=p["v2"], omega1=p["omega1"], omega2=p["omega2"],
                             radius1=r1, radius2=r2, density1=p["rho"], density2=p["rho"], youngs1=e_mod, poisson1=nu,
                             restitution=float(material["restitution"]), friction=float(material["friction"]),
                             rolling_friction=float(material.get("rolling_friction", 0.0)), model=contact_model)
        if not (res.touched & res.separated).all():
            raise HelWarpError(f"{int((~(res.touched & res.separated)).sum())} spin pairs did not complete a collision")
        n_hat = p["normal"]
        g_mag = np.linalg.norm(p["v1"] - p["v2"], axis=1)
        dem_g = res.velocity1 - res.velocity2
        args = (p["v1"], p["v2"], p["d1"], p["d2"], p["rho"], p["rho"])
        s1, s2, o1, o2 = predictor.predict_pairs(*args, normal=n_hat, omega1=p["omega1"], omega2=p["omega2"])
        z1, z2 = predictor.predict_pairs(*args, normal=n_hat)

        def spin_error(w1, w2):  # the larger sphere's surface-speed error r |omega' - omega'_DEM|
            return np.maximum(r1 * np.linalg.norm(w1 - res.omega1, axis=1),
                              r2 * np.linalg.norm(w2 - res.omega2, axis=1))

        errors = {
            "spin_g": 100.0 * np.linalg.norm((s1 - s2) - dem_g, axis=1) / g_mag,
            "spin_omega": 100.0 * spin_error(o1, o2) / g_mag,
            "spinless_g": 100.0 * np.linalg.norm((z1 - z2) - dem_g, axis=1) / g_mag,
            "spinless_omega": 100.0 * spin_error(p["omega1"], p["omega2"]) / g_mag,
        }
        rows[f"{spin_ratio:g}"] = {name: {"median_pct": float(np.median(e)), "p90_pct": float(np.percentile(e, 90)),
                                          "p99_pct": float(np.percentile(e, 99)), "max_pct": float(e.max())}
                                   for name, e in errors.items()}
    return {"reference": "hel_warp.collisions.impact.simulate_pairs with the spins (DEM), sphere-sphere, COM frame",
            "pairs_per_ratio": int(n), "spin_ratios": [float(r) for r in spin_ratios],
            "size_ratios": [float(r) for r in size_ratios], "diameter": float(diameter), "rows": rows}


def format_spin_table(sweep: dict) -> str:
    """The spin sweep as text."""
    lines = [f"spinning impacts vs DEM ({sweep['pairs_per_ratio']} pairs per spin ratio, size ratios "
             f"{sweep['size_ratios']}, d1 = {sweep['diameter'] * 1e6:.0f} um); error in % of the translational |g|, "
             "median / p90 / p99",
             f"{'r|w|/|g| <=':>12} {'spin path: g_prime':>22} {'r omega_prime':>22} {'spins ignored: g_prime':>23} "
             f"{'r omega_prime':>24}"]
    for ratio, row in sweep["rows"].items():
        cells = [f"{row[k]['median_pct']:.2f} / {row[k]['p90_pct']:.2f} / {row[k]['p99_pct']:.2f}"
                 for k in ("spin_g", "spin_omega", "spinless_g", "spinless_omega")]
        lines.append(f"{ratio:>12} {cells[0]:>22} {cells[1]:>22} {cells[2]:>22} {cells[3]:>24}")
    return "\n".join(lines)


def format_table(sweep: dict) -> str:
    """The per-band table as text."""
    lines = [f"sweep vs DEM ({sweep['pairs']} pairs, |g| {min(sweep['speeds_m_s']):g}-{max(sweep['speeds_m_s']):g} m/s, "
             f"size ratios {sweep['size_ratios']}, d1 = {sweep['diameter'] * 1e6:.0f} um); error of the post-collision "
             "relative velocity in % of |g|",
             f"{'band (deg)':>11} {'pairs':>6} {'model max':>10} {'model p99':>10} {'engine max':>11} "
             f"{'engine p99':>11} {'DEM floor':>10}"]
    for band, row in sweep["bands"].items():
        if not row["pairs"]:
            continue
        lines.append(f"{band:>11} {row['pairs']:>6} {row['model_max_pct']:>10.3f} {row['model_p99_pct']:>10.3f} "
                     f"{row['engine_max_pct']:>11.3f} {row['engine_p99_pct']:>11.3f} "
                     f"{row['dem_guard_floor_max_pct']:>10.3f}")
    w = sweep["engine_worst"]
    lines.append(f"engine worst {w['error_pct']:.3f} % at {w['angle_deg']:g} deg, {w['speed_m_s']:.3g} m/s, "
                 f"ratio {w['size_ratio']:g}; target {sweep['target_pct']:g} %: model "
                 f"{'met' if sweep['model_within_target'] else 'NOT met'}, engine "
                 f"{'met' if sweep['engine_within_target'] else 'NOT met'}")
    return "\n".join(lines)

"""Batched isolated binary impacts: N independent pairs integrated side by side, one Warp thread each.

Each pair is sphere–sphere or sphere–wall, with its own sizes, densities, elastic constants,
restitution, friction and contact model (``kernels/hertz.py``: Hertz–Mindlin or linear
spring–dashpot, damping calibrated so the clipped contact returns exactly ``e``). No gravity,
no other bodies. The time loop is here on the host: it launches ``check_every`` velocity-Verlet
steps (``kernels.hertz.step_pairs``), then reads the per-pair ``done`` flags once, until every
pair has separated. Used by ``hel-warp impact`` (a batch of one) and by the collision data set
(tens of thousands at once).

Before first touch nothing acts on a pair, so its approach is ballistic and the touch instant is
solved exactly (a partial step): every contact starts on a step boundary. In contact, velocity
Verlet (second order, symplectic for the conservative part) for translation and rotation; the
dashpot sees a second-order prediction of the end-of-step velocity, and the impulse that the
trapezoid rule misses at the t^{1/4} onset of the Hertz dashpot is added at touch
(``kernels.hertz.hertz_onset_impulse``). Separation is interpolated linearly within the last step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hel_warp.errors import ConfigError

TARGETS = ("sphere", "wall")
"""Kinds of body 2; the index is ``kernels.hertz.TARGET_SPHERE / TARGET_WALL``."""
TIME_STEP_MAX_SPEED = 20.0
"""V_max (m/s) of the Hertz step of eq. (14) used in the stability check (raised to the pair's
approach speed where that is higher)."""
STEPS_PER_CONTACT = 40.0
"""Default accuracy cap of ``simulate_pairs``: dt <= (elastic contact duration at the pair's normal
approach speed) / STEPS_PER_CONTACT. Eq. (12) is a stability limit; for the 315 um polyethylene
sphere at 20 m/s it resolves a Hertz contact with only ~10 steps. Measured at the bare eq. (12) step
(0.05-20 m/s): peak overlap 0.6 %, peak force 0.8 %, duration 0.7 %, elastic energy 0.4 %,
restitution up to 6.9 % off (Hertz, e = 0.3, 20 m/s; linear 1.4 %). With 40 steps per contact:
peaks and duration < 0.05 %, energy 0.01 %, restitution <= 0.35 % (tests/test_hertz.py)."""
PLACEMENT_STEPS = 2.0
"""``place_just_apart`` puts pairs this many time steps before first touch."""


@dataclass(frozen=True)
class PairResults:
    """Outcome of ``simulate_pairs``; arrays of shape (N,) or (N, 3), float64, SI units."""

    velocity1: np.ndarray
    """Post-collision velocity of sphere 1, m/s."""
    velocity2: np.ndarray
    """Post-collision velocity of sphere 2 (the wall's own, unchanged, for a wall), m/s."""
    omega1: np.ndarray
    """Post-collision angular velocity of sphere 1, rad/s."""
    omega2: np.ndarray
    """Post-collision angular velocity of sphere 2 (zero for a wall), rad/s."""
    position1: np.ndarray
    """Centre of sphere 1 at the end of its run, m (caller's frame)."""
    position2: np.ndarray
    """Centre of sphere 2 (or the wall's reference point) at the end of its run, m."""
    contact_duration: np.ndarray
    """Time with overlap > 0, s; touch and separation instants interpolated within the step (0 if no touch)."""
    max_overlap: np.ndarray
    """Peak overlap, m (parabolic interpolation through the three samples around the maximum)."""
    max_normal_force: np.ndarray
    """Peak normal force, N (parabolic interpolation as for the overlap)."""
    time_touch: np.ndarray
    """First-touch instant after the start, s (NaN if the pair never touched)."""
    steps: np.ndarray
    """Time steps taken by each pair (int64)."""
    dt: np.ndarray
    """Time step of each pair, s."""
    touched: np.ndarray
    """bool: the pair came into contact."""
    separated: np.ndarray
    """bool: the run of the pair ended (separated after contact, or moving apart without touching)
    within ``max_steps``; False means the outputs of that pair are not final."""


# ----------------------------------------------------------------------------- input handling


def _per_pair(name: str, value, n: int, width: int = 0) -> np.ndarray:
    """Broadcast a scalar / (N,) / (3,) / (N, 3) input to float64 (N,) or (N, 3); refuse NaN/inf."""
    arr = np.asarray(value, dtype=np.float64)
    shape = (n,) if width == 0 else (n, width)
    try:
        arr = np.broadcast_to(arr, shape).copy()
    except ValueError:
        raise ConfigError(f"{name} must be a scalar or have shape {shape} (got shape {arr.shape})") from None
    bad = ~np.isfinite(arr) if width == 0 else ~np.all(np.isfinite(arr), axis=1)
    if np.any(bad):
        k = int(np.argmax(bad))
        raise ConfigError(f"{name} of pair {k} must be finite (got {arr[k]}); give a real number")
    return arr


def _choice(name: str, value, options: tuple[str, ...], n: int) -> np.ndarray:
    """Per-pair choice given as a name, an index or an array of them -> int32 index array."""
    arr = np.asarray(value)
    if arr.dtype.kind in "US":
        lookup = {o: k for k, o in enumerate(options)}
        flat = np.atleast_1d(arr)
        bad = [v for v in flat if str(v) not in lookup]
        if bad:
            raise ConfigError(f"{name} must be one of {', '.join(options)} (got {bad[0]!r})")
        arr = np.vectorize(lambda v: lookup[str(v)], otypes=[np.int32])(arr)
    arr = np.broadcast_to(np.asarray(arr, dtype=np.int64), (n,))
    if np.any((arr < 0) | (arr >= len(options))):
        raise ConfigError(f"{name} index must lie in [0, {len(options)}) ({', '.join(options)})")
    return arr.astype(np.int32)


def _first_bad(mask: np.ndarray) -> int:
    return int(np.argmax(mask))


def stable_time_step(radius, density, youngs, poisson, max_speed=TIME_STEP_MAX_SPEED) -> np.ndarray:
    """Eq. (12) stable DEM step (s) per sphere, from ``Material.time_step``, vectorised.

    The Rayleigh, Hertz and Cundall steps of eqs. (13)-(15) are all proportional to the radius
    (Hertz: ``(m^2/r)^{0.2} ~ (r^6/r)^{0.2} = r``), and Hertz scales as ``V_max^{-0.2}``; so the
    step is computed once per distinct material at a unit radius and scaled.
    """
    from hel_warp.material import Material

    radius, density, youngs, poisson, max_speed = np.broadcast_arrays(
        *(np.asarray(a, dtype=np.float64) for a in (radius, density, youngs, poisson, max_speed)))
    out = np.empty(radius.shape)
    keys = np.stack([density.ravel(), youngs.ravel(), poisson.ravel()], axis=1)
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    ray = np.empty(len(uniq))
    hz = np.empty(len(uniq))
    cun = np.empty(len(uniq))
    factor = 1.0
    for k, (rho, e_mod, nu) in enumerate(uniq):
        step = Material(density=float(rho), youngs_modulus=float(e_mod), poisson_ratio=float(nu)).time_step(
            1.0, max_speed=TIME_STEP_MAX_SPEED)
        ray[k], hz[k], cun[k], factor = step.rayleigh, step.hertz, step.cundall, step.factor
    r = radius.ravel()
    hertz = hz[inverse] * r * (TIME_STEP_MAX_SPEED / max_speed.ravel()) ** 0.2
    out.ravel()[:] = factor * np.minimum(np.minimum(ray[inverse] * r, hertz), cun[inverse] * r)
    return out


def place_just_apart(*, normal, velocity1, velocity2=0.0, radius1, radius2=0.0, target="sphere", dt,
                     steps: float = PLACEMENT_STEPS):
    """Starting centres so that each pair first touches after ``steps`` time steps.

    ``normal`` (N, 3) or (3,) is the unit contact normal from sphere 1 to body 2 at first touch;
    body 2 (sphere centre, or a point of the wall plane ``normal . (x - x2) = 0``) starts at the
    origin, sphere 1 at ``x2 - (r1 + r2) n - (v1 - v2) t0`` (wall: ``x2 - r1 n - (v1 - v2) t0``),
    ``t0 = steps dt``. The relative velocity must approach along ``normal``; then the distance
    is larger at every earlier instant (a convex quadratic in time), so nothing starts overlapped.
    Returns ``(x1, x2)`` as float64 (N, 3) arrays.
    """
    n = 1
    for arr in (normal, velocity1, velocity2):
        if np.ndim(arr) == 2:
            n = max(n, len(arr))
    for arr in (radius1, radius2, dt, target):
        if not isinstance(arr, str) and np.ndim(arr) == 1:
            n = max(n, len(arr))
    normal = _per_pair("normal", normal, n, 3)
    norm = np.linalg.norm(normal, axis=1)
    if np.any(norm <= 0.0):
        raise ConfigError(f"contact normal of pair {_first_bad(norm <= 0)} is zero; give a direction")
    normal = normal / norm[:, None]
    v1 = _per_pair("velocity1", velocity1, n, 3)
    v2 = _per_pair("velocity2", velocity2, n, 3)
    r1 = _per_pair("radius1", radius1, n)
    r2 = _per_pair("radius2", radius2, n)
    dt = _per_pair("dt", dt, n)
    wall = _choice("target", target, TARGETS, n) == 1
    g = v1 - v2
    approach = np.einsum("ij,ij->i", g, normal)
    if np.any(approach <= 0.0):
        k = _first_bad(approach <= 0.0)
        raise ConfigError(f"pair {k}: the relative velocity v1 - v2 does not approach along the contact normal "
                          f"(normal speed {approach[k]:.3g} m/s); make v1 - v2 point from sphere 1 towards body 2")
    reach = np.where(wall, r1, r1 + r2)
    x2 = np.zeros((n, 3))
    x1 = x2 - reach[:, None] * normal - g * (steps * dt)[:, None]
    return x1, x2


# ----------------------------------------------------------------------------- the runner


def simulate_pairs(*, x1, x2, v1, v2=0.0, omega1=0.0, omega2=0.0,
                   radius1, radius2=None, density1, density2=None,
                   youngs1, poisson1, youngs2=None, poisson2=None,
                   restitution, friction=0.0, model="hertz", target="sphere", wall_normal=(0.0, 0.0, 1.0),
                   rolling_friction=0.0, tangential_damping=0.0, damping_form="calibrated",
                   linear_stiffness=None, reference_speed=None, dt=None,
                   steps_per_contact: float | None = STEPS_PER_CONTACT, max_steps=None,
                   check_every: int = 16, device=None) -> PairResults:
    """Integrate N isolated pairs until each has separated; return a ``PairResults``.

    Every argument is keyword-only and per pair: a scalar (same for all), an (N,) array, or for
    vectors a (3,) / (N, 3) array. N is taken from the longest input. SI units.

    x1, x2
        Centres of sphere 1 and of sphere 2, m; for a wall, ``x2`` is a point of the wall plane.
        Must not overlap (``|x2 - x1| > r1 + r2``; wall: ``(x1 - x2) . wall_normal > r1``).
        ``place_just_apart`` builds them so that first touch comes after ~2 steps.
    v1, v2, omega1, omega2
        Velocities (m/s) and angular velocities (rad/s). A wall moves at ``v2`` (rigid, infinite
        mass, no rotation: ``omega2`` ignored).
    radius1, radius2, density1, density2
        m, kg/m^3, > 0. ``radius2`` / ``density2`` default to sphere 1's (unused for a wall).
    youngs1, poisson1, youngs2, poisson2
        Pa and (-1, 0.5). Body 2 defaults to sphere 1's material; for a wall the default
        (``youngs2=None``, or ``inf``) is rigid, a finite ``youngs2`` gives the wall that material.
    restitution
        Normal restitution e in (0, 1] that the clipped contact reproduces (``damping_form``
        "calibrated"; "tsuji" / "liggghts" select the raw forms, which give a higher e).
    friction, rolling_friction, tangential_damping
        Coulomb mu >= 0; rolling mu_r >= 0 (constant torque); dimensionless c_t >= 0.
    model
        "hertz" (Hertz + Mindlin) or "linear" (Cundall–Strack spring–dashpot), or an index array.
    target
        "sphere" or "wall", or an index array (0 sphere, 1 wall).
    wall_normal
        Unit normal of the wall plane pointing towards sphere 1 (default +z).
    linear_stiffness, reference_speed
        k_n of the linear model (N/m); default ``contact_law.linear_stiffness_matching_hertz`` at
        ``reference_speed`` (m/s, default ``contact_law.REFERENCE_SPEED`` = 1 m/s).
    dt
        Time step per pair, s; default the eq. (12) step of the smaller sphere of the pair
        (``stable_time_step``), reduced to ``t_c / steps_per_contact``; a dt above eq. (12) is
        refused (``Material.check_time_step``).
    steps_per_contact
        Accuracy cap of the default dt (``STEPS_PER_CONTACT`` = 40 steps per elastic contact
        duration at the normal approach speed); None: exactly the eq. (12) step. Ignored when
        ``dt`` is given.
    max_steps
        Step limit per pair; default 4x the steps of the estimated approach plus contact time
        (Hertz t_c, or pi sqrt(m*/k_n)) + 100. Pairs that hit it have ``separated = False``.
    check_every
        Steps launched between reads of the ``done`` flags (the only host synchronisation).
    device
        Warp device (default: Warp's default device).

    Raises ``ConfigError`` (a message saying what to change) for bad sizes, densities, moduli,
    Poisson ratios, restitution, friction, NaN/inf, overlapping starts, or dt above eq. (12).
    """
    import warp as wp

    from hel_warp.collisions.contact_law import (DAMPING_FORMS, MODELS, REFERENCE_SPEED, damping_coefficient,
                                      hertz_contact_duration, linear_stiffness_matching_hertz)
    from kernels import hertz as hz

    vec_inputs = {"x1": x1, "x2": x2, "v1": v1, "v2": v2, "omega1": omega1, "omega2": omega2,
                  "wall_normal": wall_normal}
    scalar_inputs = {"radius1": radius1, "radius2": radius2, "density1": density1, "density2": density2,
                     "youngs1": youngs1, "poisson1": poisson1, "youngs2": youngs2, "poisson2": poisson2,
                     "restitution": restitution, "friction": friction, "model": model, "target": target,
                     "rolling_friction": rolling_friction, "tangential_damping": tangential_damping,
                     "linear_stiffness": linear_stiffness, "reference_speed": reference_speed, "dt": dt}
    n = 1
    for value in vec_inputs.values():
        if np.ndim(value) == 2:
            n = max(n, np.shape(value)[0])
    for value in scalar_inputs.values():
        if value is not None and not isinstance(value, str) and np.ndim(value) == 1:
            n = max(n, len(value))

    wall = _choice("target", target, TARGETS, n) == 1
    model_idx = _choice("model", model, MODELS, n)
    if damping_form not in DAMPING_FORMS:
        raise ConfigError(f"damping_form must be one of {', '.join(DAMPING_FORMS)} (got {damping_form!r})")
    vec = {k: _per_pair(k, v, n, 3) for k, v in vec_inputs.items()}
    r1 = _per_pair("radius1", radius1, n)
    rho1 = _per_pair("density1", density1, n)
    e1 = _per_pair("youngs1", youngs1, n)
    nu1 = _per_pair("poisson1", poisson1, n)
    r2 = r1.copy() if radius2 is None else _per_pair("radius2", radius2, n)
    rho2 = rho1.copy() if density2 is None else _per_pair("density2", density2, n)
    nu2 = nu1.copy() if poisson2 is None else _per_pair("poisson2", poisson2, n)
    if youngs2 is None:
        e2 = np.where(wall, np.inf, e1)
    else:
        e2 = np.asarray(np.broadcast_to(np.asarray(youngs2, dtype=np.float64), (n,)), dtype=np.float64).copy()
        if np.any(np.isnan(e2) | (~np.isfinite(e2) & ~wall)):
            k = _first_bad(np.isnan(e2) | (~np.isfinite(e2) & ~wall))
            raise ConfigError(f"youngs2 of pair {k} must be finite (got {e2[k]}); give a real number")
    rest = _per_pair("restitution", restitution, n)
    mu = _per_pair("friction", friction, n)
    mu_r = _per_pair("rolling_friction", rolling_friction, n)
    c_t = _per_pair("tangential_damping", tangential_damping, n)

    for name, arr, unit in (("radius1", r1, "m"), ("density1", rho1, "kg/m^3"), ("youngs1", e1, "Pa")):
        if np.any(arr <= 0.0):
            k = _first_bad(arr <= 0.0)
            raise ConfigError(f"{name} of pair {k} must be > 0 (got {arr[k]} {unit}); give a positive value")
    for name, arr, unit in (("radius2", r2, "m"), ("density2", rho2, "kg/m^3"), ("youngs2", e2, "Pa")):
        bad = (arr <= 0.0) & ~wall
        if name == "youngs2":
            bad = bad | (wall & (arr <= 0.0))
        if np.any(bad):
            k = _first_bad(bad)
            raise ConfigError(f"{name} of pair {k} must be > 0 (got {arr[k]} {unit}); give a positive value")
    for name, arr in (("poisson1", nu1), ("poisson2", nu2)):
        bad = ~((arr > -1.0) & (arr < 0.5))
        if np.any(bad):
            k = _first_bad(bad)
            raise ConfigError(f"{name} of pair {k} must lie in (-1, 0.5) (got {arr[k]}); "
                              "0.3-0.45 is typical for polymers")
    bad = ~((rest > 0.0) & (rest <= 1.0))
    if np.any(bad):
        k = _first_bad(bad)
        raise ConfigError(f"restitution of pair {k} must lie in (0, 1] (got {rest[k]})")
    for name, arr in (("friction", mu), ("rolling_friction", mu_r), ("tangential_damping", c_t)):
        if np.any(arr < 0.0):
            k = _first_bad(arr < 0.0)
            raise ConfigError(f"{name} of pair {k} must be >= 0 (got {arr[k]})")
    wn = vec["wall_normal"]
    wn_len = np.linalg.norm(wn, axis=1)
    if np.any(wall & (wn_len <= 0.0)):
        raise ConfigError(f"wall_normal of pair {_first_bad(wall & (wn_len <= 0.0))} is zero; give a direction")
    wn = wn / np.where(wn_len > 0.0, wn_len, 1.0)[:, None]

    # geometry: refuse overlapping (or touching) starts; work in a per-pair frame centred on the
    # start midpoint so float32 keeps the overlap resolution whatever the caller's coordinates
    sep = vec["x2"] - vec["x1"]
    gap = np.where(wall, np.einsum("ij,ij->i", -sep, wn) - r1, np.linalg.norm(sep, axis=1) - r1 - r2)
    if np.any(gap <= 0.0):
        k = _first_bad(gap <= 0.0)
        what = "the wall" if wall[k] else "sphere 2"
        raise ConfigError(f"pair {k}: sphere 1 starts overlapping {what} (gap {gap[k]:.3e} m); start the "
                          "bodies apart, e.g. with hel_warp.collisions.impact.place_just_apart")
    origin = 0.5 * (vec["x1"] + vec["x2"])

    mass1 = rho1 * 4.0 / 3.0 * np.pi * r1**3
    mass2 = np.where(wall, np.inf, rho2 * 4.0 / 3.0 * np.pi * r2**3)
    inertia1 = 0.4 * mass1 * r1**2
    inertia2 = 0.4 * mass2 * r2**2
    g = vec["v1"] - vec["v2"]
    speed = np.linalg.norm(g, axis=1)

    # contact parameters
    damping = np.empty(n)
    for k_model, name in enumerate(MODELS):
        sel = model_idx == k_model
        if np.any(sel):
            damping[sel] = damping_coefficient(rest[sel], name, damping_form)
    inv_e = (1.0 - nu1**2) / e1 + np.where(np.isfinite(e2), (1.0 - nu2**2) / e2, 0.0)
    youngs_eff = 1.0 / inv_e
    radius_eff = np.where(wall, r1, r1 * r2 / (r1 + r2))
    mass_eff = np.where(wall, mass1, mass1 * mass2 / np.where(wall, 1.0, mass1 + mass2))
    if linear_stiffness is None:
        v_ref = REFERENCE_SPEED if reference_speed is None else reference_speed
        v_ref = _per_pair("reference_speed", v_ref, n)
        if np.any(v_ref <= 0.0):
            raise ConfigError("reference_speed must be > 0 m/s")
        k_lin = linear_stiffness_matching_hertz(youngs_eff, radius_eff, mass_eff, v_ref)
    else:
        k_lin = _per_pair("linear_stiffness", linear_stiffness, n)
        if np.any(k_lin <= 0.0):
            raise ConfigError(f"linear_stiffness of pair {_first_bad(k_lin <= 0)} must be > 0 N/m")

    # elastic contact duration at the normal approach speed (Hertz: Johnson 1985 §11.4; linear: pi sqrt(m*/k_n))
    approach = np.einsum("ij,ij->i", g, np.where(wall[:, None], -wn, sep / np.linalg.norm(sep, axis=1)[:, None]))
    t_contact = np.where(model_idx == 1, np.pi * np.sqrt(mass_eff / k_lin),
                         hertz_contact_duration(youngs_eff, radius_eff, mass_eff, np.maximum(approach, 1e-12)))
    # time step: eq. (12) for the smaller sphere (the smaller stable step of the two materials)
    vmax = np.maximum(TIME_STEP_MAX_SPEED, speed)
    stable = stable_time_step(r1, rho1, e1, nu1, vmax)
    stable2 = stable_time_step(np.where(wall, r1, r2), np.where(wall, rho1, rho2), np.where(wall, e1, e2),
                               np.where(wall, nu1, nu2), vmax)
    stable = np.where(wall, stable, np.minimum(stable, stable2))
    if dt is None:
        step = stable
    else:
        step = _per_pair("dt", dt, n)
        bad = (step <= 0.0) | (step > stable * (1.0 + 1e-9))
        if np.any(bad):
            from hel_warp.material import Material

            k = _first_bad(bad)
            s1 = Material(density=rho1[k], youngs_modulus=e1[k], poisson_ratio=nu1[k])
            s2 = None if wall[k] else Material(density=rho2[k], youngs_modulus=e2[k], poisson_ratio=nu2[k])
            try:
                s1.check_time_step(float(step[k]), float(r1[k]), max_speed=float(vmax[k]))
                if s2 is not None:
                    s2.check_time_step(float(step[k]), float(r2[k]), max_speed=float(vmax[k]))
            except ConfigError as exc:
                raise ConfigError(f"pair {k}: {exc}") from None
            raise ConfigError(f"pair {k}: time step dt = {step[k]:.3e} s is above the stable step "
                              f"{stable[k]:.3e} s; use --dt {stable[k]:.3e} or smaller")

    if steps_per_contact is not None:
        if not steps_per_contact > 0:
            raise ConfigError(f"steps_per_contact must be > 0 (got {steps_per_contact})")
        if dt is None:
            step = np.where(approach > 0.0, np.minimum(step, t_contact / steps_per_contact), step)

    # step limit from the expected approach + contact time
    if max_steps is None:
        t_gap = np.where(approach > 0.0, gap / np.maximum(approach, 1e-300), 0.0)
        est = np.minimum(4.0 * (t_gap + t_contact) / step + 100.0, 1e7)
        max_steps = int(np.max(est))
    max_steps = int(max_steps)
    if max_steps < 1:
        raise ConfigError(f"max_steps must be >= 1 (got {max_steps})")
    if check_every < 1:
        raise ConfigError(f"check_every must be >= 1 (got {check_every})")

    # device arrays
    f32 = np.float32
    dev = wp.get_device(device)

    def a(values, dtype=float):
        return wp.array(np.ascontiguousarray(values, dtype=f32 if dtype is not wp.int32 else np.int32),
                        dtype=dtype, device=dev)

    def v3(values):
        return wp.array(np.ascontiguousarray(values, dtype=f32), dtype=wp.vec3, device=dev)

    kind = a(wall.astype(np.int32), wp.int32)
    arrays = {
        "model": a(model_idx, wp.int32), "kind": kind,
        "youngs1": a(e1), "poisson1": a(nu1), "youngs2": a(np.where(np.isfinite(e2), e2, 0.0)), "poisson2": a(nu2),
        "radius1": a(r1), "radius2": a(np.where(wall, 0.0, r2)), "mass1": a(mass1),
        "mass2": a(np.where(wall, 0.0, mass2)), "normal_damping": a(damping), "linear_stiffness": a(k_lin),
        "friction": a(mu), "tangential_damping": a(c_t), "rolling_friction": a(mu_r),
    }
    params = wp.empty(n, dtype=hz.ContactParams, device=dev)
    hz.launch_build_pair_params(arrays, params, device=dev)

    bodies = hz.PairBodies()
    bodies.kind = kind
    bodies.params = params
    bodies.radius1 = arrays["radius1"]
    bodies.radius2 = arrays["radius2"]
    bodies.inv_mass1 = a(1.0 / mass1)
    bodies.inv_mass2 = a(np.where(wall, 0.0, 1.0 / np.where(wall, 1.0, mass2)))
    bodies.inv_inertia1 = a(1.0 / inertia1)
    bodies.inv_inertia2 = a(np.where(wall, 0.0, 1.0 / np.where(wall, 1.0, inertia2)))
    bodies.wall_normal = v3(wn)
    bodies.dt = a(step)

    state = hz.PairState()
    state.x1 = v3(vec["x1"] - origin)
    state.x2 = v3(vec["x2"] - origin)
    state.v1 = v3(vec["v1"])
    state.v2 = v3(vec["v2"])
    state.omega1 = v3(vec["omega1"])
    state.omega2 = v3(np.where(wall[:, None], 0.0, vec["omega2"]))
    for name in ("force1", "torque1", "torque2", "shear", "touch_separation", "displacement"):
        setattr(state, name, wp.zeros(n, dtype=wp.vec3, device=dev))

    record = hz.PairRecord()
    for name in ("steps", "done", "touched"):
        setattr(record, name, wp.zeros(n, dtype=wp.int32, device=dev))
    for name in ("time", "time_touch", "contact_time", "peak_overlap", "peak_normal_force"):
        setattr(record, name, wp.zeros(n, dtype=float, device=dev))
    record.overlap_samples = wp.zeros(n, dtype=wp.vec3, device=dev)
    record.force_samples = wp.zeros(n, dtype=wp.vec3, device=dev)

    taken = 0
    while taken < max_steps:
        burst = min(check_every, max_steps - taken)
        hz.launch_step_pairs(bodies, state, record, n, steps=burst, device=dev)
        taken += burst
        if record.done.numpy().all():
            break

    done = record.done.numpy().astype(bool)
    touched = record.touched.numpy().astype(bool)
    t_touch = record.time_touch.numpy().astype(np.float64)
    duration = np.where(touched, record.contact_time.numpy().astype(np.float64), 0.0)
    return PairResults(
        velocity1=state.v1.numpy().astype(np.float64),
        velocity2=np.where(wall[:, None], vec["v2"], state.v2.numpy().astype(np.float64)),
        omega1=state.omega1.numpy().astype(np.float64),
        omega2=np.where(wall[:, None], 0.0, state.omega2.numpy().astype(np.float64)),
        position1=state.x1.numpy().astype(np.float64) + origin,
        position2=state.x2.numpy().astype(np.float64) + origin,
        contact_duration=duration,
        max_overlap=record.peak_overlap.numpy().astype(np.float64),
        max_normal_force=record.peak_normal_force.numpy().astype(np.float64),
        time_touch=np.where(touched, t_touch, np.nan),
        steps=record.steps.numpy().astype(np.int64),
        dt=step,
        touched=touched,
        separated=done,
    )

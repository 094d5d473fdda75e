"""Hertz–Mindlin contact law (and a linear spring–dashpot option) as pure ``@wp.func``s,
plus the one-step kernel of the batched isolated-pair runner with its launch wrapper.

Equations (SI units; contact normal ``n`` points from body 1 to body 2; overlap ``delta > 0``
in contact; ``v_rel`` = velocity of the contact point on body 1 minus that on body 2):

Effective quantities (Johnson, *Contact Mechanics*, 1985, §4.2 and §5.3; Mindlin 1949)::

    1/E* = (1 - nu1^2)/E1 + (1 - nu2^2)/E2
    1/G* = 2 (2 - nu1)(1 + nu1)/E1 + 2 (2 - nu2)(1 + nu2)/E2
    1/R* = 1/R1 + 1/R2,   1/m* = 1/m1 + 1/m2
    rigid wall (E2 -> inf, R2 -> inf, m2 -> inf): its terms vanish, R* = R1, m* = m1

Normal force, model ``MODEL_HERTZ`` (Hertz 1882, Johnson 1985 §4.2; damping form of
Tsuji, Tanaka & Ishida 1992, Powder Technol. 71: 239-250)::

    k_H = 4/3 E* sqrt(R*)
    F_n = max(0, k_H delta^{3/2} + c sqrt(m* k_H) delta^{1/4} v_n),   v_n = v_rel . n

Normal force, model ``MODEL_LINEAR`` (Cundall & Strack 1979, Geotechnique 29: 47-65)::

    F_n = max(0, k_n delta + c sqrt(m* k_n) v_n)

The total normal force is clipped at zero (no attraction). The dimensionless damping ``c``
is computed on the host (``hel_warp.collisions.contact_law.damping_coefficient``) so that the clipped
contact returns exactly the requested restitution ``e`` (c depends on e alone — see
docs/physics/references.md "damping pitfall"); the raw Tsuji and LIGGGHTS forms are host options too.
Thornton, Cummins & Cleary (2013), Powder Technol. 233: 30-46, discuss why the clipped
contact needs its own calibration.

Tangential force (Mindlin 1949, J. Appl. Mech. 16: 259-268; incremental history as in
Cundall & Strack 1979 and LIGGGHTS ``tangential_model history``)::

    S_t = 8 G* sqrt(R* delta)                  (MODEL_HERTZ)
    S_t = (4 G*/E*) k_n                        (MODEL_LINEAR: the same S_t/S_n ratio as Mindlin/Hertz)
    xi  <- xi projected on the current tangent plane, rescaled to its old length
    xi  <- xi + slip_increment                 (slip_increment = v_t dt, v_t = v_rel - v_n n)
    F_t = -S_t xi - c_t sqrt(m* S_t) v_t
    |F_t| <= mu F_n; when capped, F_t = mu F_n F_t/|F_t| and xi = -(F_t + c_t sqrt(m* S_t) v_t)/S_t

Rolling resistance (constant torque, Ai et al. 2011 model A): torque on body 1
``-mu_r R* F_n w_t/|w_t|`` with ``w_t`` the tangential part of ``omega1 - omega2``; body 2 gets
the opposite. Contact torques are ``r x F`` with the lever arm to the contact point.

Stable API for other rooms (N-body DEM in ``kernels/contacts.py``, the HEL ``dem`` strategy)
----------------------------------------------------------------------------------------
- ``ContactParams`` (``@wp.struct``): per-pair parameters, built on the host or by
  ``pair_params(...)`` below. Fields documented in the class.
- ``contact_force(n, overlap, v_rel, shear, p, dt) -> (force1: vec3, shear_new: vec3, fn: float)``
  the whole law for one contact; force on body 1 (body 2 gets ``-force1``). Call only when
  ``overlap > 0``; when the contact opens, reset the caller's shear history to zero.
- ``contact_force_split(n, overlap, v_rel, slip_increment, shear, p)``: the same with the
  slip increment given separately (a Verlet integrator passes the half-step velocity times
  dt for the slip and a predicted end-of-step velocity for the damping).
- ``rolling_torque(p, n, omega_rel, fn) -> vec3``: rolling-resistance torque on body 1.
- ``hertz_onset_impulse(p, normal_speed, dt) -> float``: the impulse a fixed-step trapezoid
  (Verlet) misses at the start of a Hertz contact that begins on a step boundary.
- ``pair_params(E1, nu1, E2, nu2, r1, r2, m1, m2, wall, model, damping, k_linear, mu, c_t, mu_r)``:
  effective quantities; ``wall != 0`` means body 2 is a wall (``E2 <= 0`` means a rigid wall).
- ``effective_youngs``, ``effective_shear``, ``hertz_stiffness``, ``hertz_normal_force``,
  ``linear_normal_force``, ``mindlin_stiffness``: the pieces.

Isolated-pair runner (bottom of the file): ``PairBodies`` / ``PairState`` / ``PairRecord`` structs,
the ``step_pairs`` kernel and its wrappers ``launch_build_pair_params`` / ``launch_step_pairs``;
host side in ``hel_warp.collisions.impact.simulate_pairs``.

Note on the tangential history: the spring force is ``S_t(delta) xi`` with the current stiffness
(the LIGGGHTS/Di Renzo & Di Maio 2004 form), so it relaxes with the normal load on unloading. With
nu = 0.4 a stuck contact does a near-full tangential oscillation at small impact angles: the
contact-point tangential velocity reverses (Maw et al. 1976) only from ~25-30 deg upwards
(measured: vt'/vt = +0.69 at 5 deg, -0.36 at 35 deg, -0.41 at 45 deg; gross sliding from
tan(theta) >= 3.5 mu (1 + e)).
"""

from __future__ import annotations

import warp as wp

MODEL_HERTZ = wp.constant(0)
"""``ContactParams.model`` value of the Hertz normal law (with Mindlin tangential stiffness)."""
MODEL_LINEAR = wp.constant(1)
"""``ContactParams.model`` value of the linear spring–dashpot normal law."""
ZETA_MINUS_QUARTER = wp.constant(-0.320451264228577)
"""Riemann zeta(-1/4): trapezoid-rule error coefficient of an integrand ~ t^{1/4} (Navot 1961)."""
ZETA_MINUS_THREE_HALVES = wp.constant(-0.025485201889833)
"""Riemann zeta(-3/2): the same for an integrand ~ t^{3/2}."""
TARGET_SPHERE = wp.constant(0)
"""Pair kind: body 2 is a sphere."""
TARGET_WALL = wp.constant(1)
"""Pair kind: body 2 is a plane wall (infinite mass, no rotation)."""


@wp.struct
class ContactParams:
    """Parameters of one contact pair (SI units)."""

    model: int
    """MODEL_HERTZ (0) or MODEL_LINEAR (1)."""
    youngs_eff: float
    """E*, Pa."""
    shear_eff: float
    """G*, Pa."""
    radius_eff: float
    """R*, m."""
    mass_eff: float
    """m*, kg."""
    normal_damping: float
    """Dimensionless c of the normal dashpot (from ``contact_law.damping_coefficient``)."""
    linear_stiffness: float
    """k_n of MODEL_LINEAR, N/m (unused by MODEL_HERTZ)."""
    friction: float
    """Coulomb sliding friction coefficient mu."""
    tangential_damping: float
    """Dimensionless c_t of the tangential dashpot (0 = none)."""
    rolling_friction: float
    """Rolling friction coefficient mu_r (0 = none)."""


# --------------------------------------------------------------------------- effective quantities


@wp.func
def effective_youngs(youngs1: float, poisson1: float, youngs2: float, poisson2: float):
    """E* of two bodies; ``youngs2 <= 0`` means body 2 is rigid (its term vanishes)."""
    inv = (1.0 - poisson1 * poisson1) / youngs1
    if youngs2 > 0.0:
        inv = inv + (1.0 - poisson2 * poisson2) / youngs2
    return 1.0 / inv


@wp.func
def effective_shear(youngs1: float, poisson1: float, youngs2: float, poisson2: float):
    """G* of Mindlin: 1/G* = 2(2-nu1)(1+nu1)/E1 + 2(2-nu2)(1+nu2)/E2; rigid body 2 if ``youngs2 <= 0``."""
    inv = 2.0 * (2.0 - poisson1) * (1.0 + poisson1) / youngs1
    if youngs2 > 0.0:
        inv = inv + 2.0 * (2.0 - poisson2) * (1.0 + poisson2) / youngs2
    return 1.0 / inv


@wp.func
def effective_harmonic(a1: float, a2: float, wall: int):
    """1/(1/a1 + 1/a2) for R* and m*; a wall (``wall != 0``) has an infinite a2, so the result is a1."""
    if wall != 0:
        return a1
    return a1 * a2 / (a1 + a2)


@wp.func
def pair_params(youngs1: float, poisson1: float, youngs2: float, poisson2: float,
                radius1: float, radius2: float, mass1: float, mass2: float, wall: int,
                model: int, normal_damping: float, linear_stiffness: float,
                friction: float, tangential_damping: float, rolling_friction: float):
    """Build ``ContactParams`` from the two bodies' properties (``youngs2 <= 0``: rigid body 2)."""
    p = ContactParams()
    p.model = model
    p.youngs_eff = effective_youngs(youngs1, poisson1, youngs2, poisson2)
    p.shear_eff = effective_shear(youngs1, poisson1, youngs2, poisson2)
    p.radius_eff = effective_harmonic(radius1, radius2, wall)
    p.mass_eff = effective_harmonic(mass1, mass2, wall)
    p.normal_damping = normal_damping
    p.linear_stiffness = linear_stiffness
    p.friction = friction
    p.tangential_damping = tangential_damping
    p.rolling_friction = rolling_friction
    return p


# --------------------------------------------------------------------------- normal law


@wp.func
def hertz_stiffness(youngs_eff: float, radius_eff: float):
    """k_H = 4/3 E* sqrt(R*), N/m^1.5 (F_n = k_H delta^1.5)."""
    return 4.0 / 3.0 * youngs_eff * wp.sqrt(radius_eff)


@wp.func
def hertz_normal_force(p: ContactParams, overlap: float, normal_speed: float):
    """Clipped damped Hertz force magnitude: max(0, k_H d^1.5 + c sqrt(m* k_H) d^0.25 v_n)."""
    k_hertz = hertz_stiffness(p.youngs_eff, p.radius_eff)
    root4 = wp.sqrt(wp.sqrt(overlap))
    elastic = k_hertz * overlap * wp.sqrt(overlap)
    viscous = p.normal_damping * wp.sqrt(p.mass_eff * k_hertz) * root4 * normal_speed
    return wp.max(elastic + viscous, 0.0)


@wp.func
def linear_normal_force(p: ContactParams, overlap: float, normal_speed: float):
    """Clipped linear spring–dashpot force magnitude: max(0, k_n d + c sqrt(m* k_n) v_n)."""
    k_n = p.linear_stiffness
    return wp.max(k_n * overlap + p.normal_damping * wp.sqrt(p.mass_eff * k_n) * normal_speed, 0.0)


@wp.func
def mindlin_stiffness(p: ContactParams, overlap: float):
    """Tangential stiffness S_t: 8 G* sqrt(R* d) (Hertz) or (4 G*/E*) k_n (linear), N/m."""
    if p.model == MODEL_LINEAR:
        return 4.0 * p.shear_eff / p.youngs_eff * p.linear_stiffness
    return 8.0 * p.shear_eff * wp.sqrt(p.radius_eff * overlap)


# --------------------------------------------------------------------------- whole law


@wp.func
def contact_force_split(n: wp.vec3, overlap: float, v_rel: wp.vec3, slip_increment: wp.vec3,
                        shear: wp.vec3, p: ContactParams):
    """Force on body 1, new shear history, normal force magnitude (see the module docstring).

    ``v_rel`` (contact-point velocity of 1 minus 2) feeds the dashpots; ``slip_increment`` (m)
    is the tangential displacement of the contact over the step. Call only when overlap > 0.
    """
    normal_speed = wp.dot(v_rel, n)
    fn = float(0.0)
    if p.model == MODEL_LINEAR:
        fn = linear_normal_force(p, overlap, normal_speed)
    else:
        fn = hertz_normal_force(p, overlap, normal_speed)

    # shear history: rotate onto the current tangent plane (keep its length), then add the slip
    old_len = wp.length(shear)
    xi = shear - wp.dot(shear, n) * n
    new_len = wp.length(xi)
    if new_len > 0.0:
        xi = xi * (old_len / new_len)
    xi = xi + (slip_increment - wp.dot(slip_increment, n) * n)

    v_t = v_rel - normal_speed * n
    s_t = mindlin_stiffness(p, overlap)
    eta_t = p.tangential_damping * wp.sqrt(p.mass_eff * s_t)
    f_t = -s_t * xi - eta_t * v_t
    f_t_len = wp.length(f_t)
    cap = p.friction * fn
    if f_t_len > cap:
        if f_t_len > 0.0:
            f_t = f_t * (cap / f_t_len)
        else:
            f_t = wp.vec3(0.0)
        if s_t > 0.0:
            xi = -(f_t + eta_t * v_t) / s_t
        else:
            xi = wp.vec3(0.0)
    force1 = -fn * n + f_t
    return force1, xi, fn


@wp.func
def contact_force(n: wp.vec3, overlap: float, v_rel: wp.vec3, shear: wp.vec3, p: ContactParams, dt: float):
    """The whole contact law: (force on body 1, new shear history, F_n). Slip increment = v_t dt."""
    return contact_force_split(n, overlap, v_rel, v_rel * dt, shear, p)


@wp.func
def hertz_onset_impulse(p: ContactParams, normal_speed: float, dt: float):
    """Normal impulse (N s, repulsive) that the trapezoid rule of velocity Verlet misses over a
    Hertz contact that starts exactly on a step boundary.

    Near touch delta = v_n t, so the dashpot force is A t^{1/4} (A = c sqrt(m* k_H) v_n^{5/4})
    and the elastic force B t^{3/2} (B = k_H v_n^{3/2}). For an integrand ~ t^a the trapezoid
    sum exceeds the integral by zeta(-a) A dt^{1+a} (generalised Euler–Maclaurin, Navot 1961,
    J. Math. Phys. 40: 271); zeta(-1/4) < 0, so without this the dashpot loses
    0.32 A dt^{5/4}: an O((dt/t_c)^{1/4}) restitution error (e +1.2 % at e = 0.3, 40 steps).
    Returns -zeta(-1/4) A dt^{5/4} - zeta(-3/2) B dt^{5/2}; 0 for the linear model (smooth).
    """
    if p.model != MODEL_HERTZ or normal_speed <= 0.0:
        return 0.0
    k_hertz = hertz_stiffness(p.youngs_eff, p.radius_eff)
    damp = p.normal_damping * wp.sqrt(p.mass_eff * k_hertz) * wp.pow(normal_speed * dt, 1.25)
    elastic = k_hertz * wp.pow(normal_speed * dt, 1.5) * dt
    return -ZETA_MINUS_QUARTER * damp - ZETA_MINUS_THREE_HALVES * elastic


@wp.func
def rolling_torque(p: ContactParams, n: wp.vec3, omega_rel: wp.vec3, fn: float):
    """Constant rolling-resistance torque on body 1 (body 2 gets the opposite); omega_rel = w1 - w2."""
    w_t = omega_rel - wp.dot(omega_rel, n) * n
    w_len = wp.length(w_t)
    if p.rolling_friction <= 0.0 or w_len <= 0.0:
        return wp.vec3(0.0)
    return -p.rolling_friction * p.radius_eff * fn * (w_t / w_len)


# =========================================================================== isolated-pair runner
# One thread per independent pair (sphere–sphere or sphere–wall), one step per launch. Used by
# ``hel_warp.collisions.impact.simulate_pairs``; host code calls the wrappers at the bottom.
#
# Before first touch no force acts (no gravity), so the motion is ballistic and the touch
# instant is solved exactly: a pair whose touch falls inside the coming step moves just to the
# touch point (a partial step). Contact therefore starts exactly on a step boundary, which
# removes the O(dt) onset error of a dashpot force that jumps (linear model) or rises as
# delta^{1/4} (Hertz) at first touch. In contact: velocity Verlet (below).


@wp.struct
class PairBodies:
    """Fixed data of N isolated pairs (arrays of shape (N,))."""

    kind: wp.array(dtype=wp.int32)
    """TARGET_SPHERE or TARGET_WALL."""
    params: wp.array(dtype=ContactParams)
    """Contact parameters of each pair."""
    radius1: wp.array(dtype=float)
    """m."""
    radius2: wp.array(dtype=float)
    """m (unused for a wall)."""
    inv_mass1: wp.array(dtype=float)
    """1/kg."""
    inv_mass2: wp.array(dtype=float)
    """1/kg (0 for a wall)."""
    inv_inertia1: wp.array(dtype=float)
    """1/(kg m^2), sphere: 1/(2/5 m r^2)."""
    inv_inertia2: wp.array(dtype=float)
    """1/(kg m^2) (0 for a wall)."""
    wall_normal: wp.array(dtype=wp.vec3)
    """Unit normal of the wall plane pointing towards sphere 1 (unused for sphere pairs)."""
    dt: wp.array(dtype=float)
    """Time step of each pair, s."""


@wp.struct
class PairState:
    """Changing data of N pairs, updated in place by ``step_pairs``."""

    x1: wp.array(dtype=wp.vec3)
    """Centre of sphere 1, m (in the pair's own frame)."""
    x2: wp.array(dtype=wp.vec3)
    """Centre of sphere 2, or a point of the wall plane, m."""
    v1: wp.array(dtype=wp.vec3)
    """m/s."""
    v2: wp.array(dtype=wp.vec3)
    """m/s (a wall's own, constant)."""
    omega1: wp.array(dtype=wp.vec3)
    """rad/s."""
    omega2: wp.array(dtype=wp.vec3)
    """rad/s (0 for a wall)."""
    force1: wp.array(dtype=wp.vec3)
    """Contact force on body 1 at the current positions, N (body 2 gets the opposite)."""
    torque1: wp.array(dtype=wp.vec3)
    """N m."""
    torque2: wp.array(dtype=wp.vec3)
    """N m."""
    shear: wp.array(dtype=wp.vec3)
    """Tangential displacement history, m."""
    touch_separation: wp.array(dtype=wp.vec3)
    """x2 - x1 at first touch, scaled to length r1 + r2 (spheres), m; set at touch."""
    displacement: wp.array(dtype=wp.vec3)
    """(x2 - x1) now minus at first touch, m: the overlap is computed from this small vector, so
    float32 resolves it to ~1e-7 of itself instead of ~1e-7 of the radius."""


@wp.struct
class PairRecord:
    """Per-pair measurements, updated in place by ``step_pairs``."""

    steps: wp.array(dtype=wp.int32)
    """Steps taken (the partial step to first touch counts as one)."""
    done: wp.array(dtype=wp.int32)
    """1 once the pair has separated after contact, or when it can no longer touch."""
    touched: wp.array(dtype=wp.int32)
    """1 once the pair has come into contact."""
    time: wp.array(dtype=float)
    """Time of the current state since the start, s."""
    time_touch: wp.array(dtype=float)
    """First-touch instant, s (exact: ballistic approach)."""
    contact_time: wp.array(dtype=float)
    """Time spent in contact so far; at separation the last step is cut at the linearly
    interpolated zero crossing of the overlap, s."""
    overlap_samples: wp.array(dtype=wp.vec3)
    """Last three overlap samples (oldest first), m."""
    force_samples: wp.array(dtype=wp.vec3)
    """Last three normal-force samples (oldest first), N."""
    peak_overlap: wp.array(dtype=float)
    """m."""
    peak_normal_force: wp.array(dtype=float)
    """N."""


@wp.func
def parabolic_peak(samples: wp.vec3, current_peak: float):
    """Max of ``current_peak``, the newest sample and, when the middle of 3 equally spaced
    samples is a local maximum, the vertex of the parabola through them."""
    y0 = samples[0]
    y1 = samples[1]
    y2 = samples[2]
    peak = wp.max(current_peak, y2)
    curvature = 2.0 * y1 - y0 - y2
    if y1 >= y0 and y1 > y2 and curvature > 0.0:
        peak = wp.max(peak, y1 + (y2 - y0) * (y2 - y0) / (8.0 * curvature))
    return peak


@wp.func
def time_to_touch(kind: int, x1: wp.vec3, x2: wp.vec3, v1: wp.vec3, v2: wp.vec3, radius1: float,
                  radius2: float, wall_normal: wp.vec3):
    """Ballistic time until first touch, s; negative when the bodies will never touch.

    Spheres: smallest root of |d0 - g t| = r1 + r2 (d0 = x2 - x1, g = v1 - v2), written in the
    cancellation-free form t = c / (b + sqrt(b^2 - a c)). Wall: gap / approach speed.
    """
    g = v1 - v2
    if kind == TARGET_WALL:
        gap = wp.dot(x1 - x2, wall_normal) - radius1
        approach = -wp.dot(g, wall_normal)
        if approach <= 0.0:
            return -1.0
        return wp.max(gap, 0.0) / approach
    d0 = x2 - x1
    dist = wp.length(d0)
    reach = radius1 + radius2
    a = wp.dot(g, g)
    b = wp.dot(d0, g)
    c = (dist - reach) * (dist + reach)
    disc = b * b - a * c
    if b <= 0.0 or disc < 0.0:
        return -1.0
    return wp.max(c, 0.0) / (b + wp.sqrt(disc))


@wp.func
def pair_geometry(kind: int, touch_separation: wp.vec3, displacement: wp.vec3, reach: float,
                  wall_normal: wp.vec3):
    """(unit normal from 1 to 2, overlap) from the separation at touch d0 (|d0| = reach = r1 + r2)
    and the relative displacement since touch D, without cancellation:
    overlap = reach - |d0 + D| = -(2 d0.D + D.D) / (reach + |d0 + D|); wall (n_wall pointing
    towards sphere 1): overlap = D.n_wall."""
    if kind == TARGET_WALL:
        return -wall_normal, wp.dot(displacement, wall_normal)
    d = touch_separation + displacement
    dist = wp.length(d)
    overlap = -(2.0 * wp.dot(touch_separation, displacement) + wp.dot(displacement, displacement)) / (reach + dist)
    return d / dist, overlap


@wp.kernel
def build_pair_params(model: wp.array(dtype=wp.int32), kind: wp.array(dtype=wp.int32),
                      youngs1: wp.array(dtype=float), poisson1: wp.array(dtype=float),
                      youngs2: wp.array(dtype=float), poisson2: wp.array(dtype=float),
                      radius1: wp.array(dtype=float), radius2: wp.array(dtype=float),
                      mass1: wp.array(dtype=float), mass2: wp.array(dtype=float),
                      normal_damping: wp.array(dtype=float), linear_stiffness: wp.array(dtype=float),
                      friction: wp.array(dtype=float), tangential_damping: wp.array(dtype=float),
                      rolling_friction: wp.array(dtype=float),
                      # outputs
                      params: wp.array(dtype=ContactParams)):
    i = wp.tid()
    params[i] = pair_params(youngs1[i], poisson1[i], youngs2[i], poisson2[i], radius1[i], radius2[i],
                            mass1[i], mass2[i], kind[i], model[i], normal_damping[i], linear_stiffness[i],
                            friction[i], tangential_damping[i], rolling_friction[i])


@wp.kernel
def step_pairs(bodies: PairBodies,
               # outputs (updated in place)
               state: PairState, record: PairRecord):
    """One step of each unfinished pair (translation and rotation, no gravity).

    Before touch: ballistic, cut at the exact touch instant (see the section comment).
    In contact, velocity Verlet: kick v(t+dt/2) = v + F dt/(2m); drift x += v(t+dt/2) dt; force
    at x(t+dt) from the slip v_rel(t+dt/2) dt and the dashpot velocity predicted at t+dt
    (v(t+dt/2) + F(t) dt/(2m), second order); kick v(t+dt) = v(t+dt/2) + F(t+dt) dt/(2m).
    Same for omega with the torques.
    """
    i = wp.tid()
    if record.done[i] != 0:
        return
    kind = bodies.kind[i]
    dt = bodies.dt[i]
    r1 = bodies.radius1[i]
    r2 = bodies.radius2[i]
    wall_normal = bodies.wall_normal[i]
    p = bodies.params[i]
    record.steps[i] = record.steps[i] + 1

    if record.touched[i] == 0:
        v1 = state.v1[i]
        v2 = state.v2[i]
        tau = time_to_touch(kind, state.x1[i], state.x2[i], v1, v2, r1, r2, wall_normal)
        if tau < 0.0:
            record.done[i] = 1  # moving apart or missing: never touches
            return
        t = record.time[i]
        if tau > dt:
            state.x1[i] = state.x1[i] + v1 * dt
            state.x2[i] = state.x2[i] + v2 * dt
            record.time[i] = t + dt
            return
        x1 = state.x1[i] + v1 * tau
        x2 = state.x2[i] + v2 * tau
        state.x1[i] = x1
        state.x2[i] = x2
        record.time[i] = t + tau
        record.time_touch[i] = t + tau
        record.touched[i] = 1
        n = -wall_normal
        if kind != TARGET_WALL:
            n = wp.normalize(x2 - x1)
        state.touch_separation[i] = (r1 + r2) * n
        state.displacement[i] = wp.vec3(0.0)
        arm1 = r1 * n
        arm2 = -r2 * n
        if kind == TARGET_WALL:
            arm2 = wp.vec3(0.0)
        w1 = state.omega1[i]
        w2 = state.omega2[i]
        v_rel = v1 + wp.cross(w1, arm1) - v2 - wp.cross(w2, arm2)
        # force at the touch instant (overlap 0): zero for Hertz, the dashpot alone for linear
        f0, xi0, fn0 = contact_force_split(n, 0.0, v_rel, wp.vec3(0.0), wp.vec3(0.0), p)
        # Verlet applies force1 dt/2 in the first half kick: carry the missed onset impulse there
        f0 = f0 - (2.0 * hertz_onset_impulse(p, wp.dot(v_rel, n), dt) / dt) * n
        state.force1[i] = f0
        state.torque1[i] = wp.cross(arm1, f0)
        state.torque2[i] = -wp.cross(arm2, f0)
        state.shear[i] = xi0
        record.overlap_samples[i] = wp.vec3(0.0)
        record.force_samples[i] = wp.vec3(0.0, 0.0, fn0)
        record.peak_normal_force[i] = fn0
        return

    half = 0.5 * dt
    im1 = bodies.inv_mass1[i]
    im2 = bodies.inv_mass2[i]
    ii1 = bodies.inv_inertia1[i]
    ii2 = bodies.inv_inertia2[i]
    f_old = state.force1[i]
    tq1_old = state.torque1[i]
    tq2_old = state.torque2[i]
    v1h = state.v1[i] + f_old * (half * im1)
    v2h = state.v2[i] - f_old * (half * im2)
    w1h = state.omega1[i] + tq1_old * (half * ii1)
    w2h = state.omega2[i] + tq2_old * (half * ii2)
    state.x1[i] = state.x1[i] + v1h * dt
    state.x2[i] = state.x2[i] + v2h * dt
    displacement = state.displacement[i] + (v2h - v1h) * dt
    state.displacement[i] = displacement
    n, overlap = pair_geometry(kind, state.touch_separation[i], displacement, r1 + r2, wall_normal)

    force1 = wp.vec3(0.0)
    torque1 = wp.vec3(0.0)
    torque2 = wp.vec3(0.0)
    shear = wp.vec3(0.0)
    fn = float(0.0)
    if overlap > 0.0:
        arm1 = (r1 - 0.5 * overlap) * n
        arm2 = -(r2 - 0.5 * overlap) * n
        if kind == TARGET_WALL:
            arm2 = wp.vec3(0.0)
        v1p = v1h + f_old * (half * im1)
        v2p = v2h - f_old * (half * im2)
        w1p = w1h + tq1_old * (half * ii1)
        w2p = w2h + tq2_old * (half * ii2)
        v_rel_half = v1h + wp.cross(w1h, arm1) - v2h - wp.cross(w2h, arm2)
        v_rel_pred = v1p + wp.cross(w1p, arm1) - v2p - wp.cross(w2p, arm2)
        force1, shear, fn = contact_force_split(n, overlap, v_rel_pred, v_rel_half * dt, state.shear[i], p)
        roll = rolling_torque(p, n, w1p - w2p, fn)
        torque1 = wp.cross(arm1, force1) + roll
        torque2 = -wp.cross(arm2, force1) - roll
    state.shear[i] = shear
    state.force1[i] = force1
    state.torque1[i] = torque1
    state.torque2[i] = torque2
    state.v1[i] = v1h + force1 * (half * im1)
    state.v2[i] = v2h - force1 * (half * im2)
    state.omega1[i] = w1h + torque1 * (half * ii1)
    state.omega2[i] = w2h + torque2 * (half * ii2)
    record.time[i] = record.time[i] + dt

    ov = record.overlap_samples[i]
    overlap_prev = ov[2]
    ov = wp.vec3(ov[1], ov[2], overlap)
    record.overlap_samples[i] = ov
    fs = record.force_samples[i]
    fs = wp.vec3(fs[1], fs[2], fn)
    record.force_samples[i] = fs
    record.peak_overlap[i] = parabolic_peak(ov, record.peak_overlap[i])
    record.peak_normal_force[i] = parabolic_peak(fs, record.peak_normal_force[i])
    if overlap > 0.0:
        record.contact_time[i] = record.contact_time[i] + dt
    else:
        # separated: the overlap crossed zero within this step (linear interpolation)
        record.contact_time[i] = record.contact_time[i] + dt * overlap_prev / (overlap_prev - overlap)
        record.done[i] = 1


def launch_build_pair_params(arrays: dict, params, device=None) -> None:
    """Fill ``params`` (wp.array of ContactParams) from per-pair Warp arrays named as the kernel inputs."""
    wp.launch(build_pair_params, dim=params.shape[0], device=device,
              inputs=[arrays[name] for name in (
                  "model", "kind", "youngs1", "poisson1", "youngs2", "poisson2", "radius1", "radius2",
                  "mass1", "mass2", "normal_damping", "linear_stiffness", "friction",
                  "tangential_damping", "rolling_friction")],
              outputs=[params])


def launch_step_pairs(bodies: PairBodies, state: PairState, record: PairRecord, n_pairs: int,
                      steps: int = 1, device=None) -> None:
    """Advance every unfinished pair by ``steps`` steps (no host synchronisation)."""
    for _ in range(steps):
        wp.launch(step_pairs, dim=n_pairs, inputs=[bodies], outputs=[state, record], device=device)

"""Parcel-wall reflection against the analytic SDF geometry (HEL walls, Table 1: e_n = e_t = 0.8).

MP-PIC parcels meet the wall as points (Snider 2001; Andrews & O'Rourke 1996): a parcel whose
centre has crossed the wall during the push (signed distance ``d = sdf_union(x) > 0``,
``kernels/sdf.py``: negative inside the fluid) is reflected with restitution coefficients:

    n   = grad d / |grad d|                    (unit normal, out of the fluid; ``sdf_union_normal``)
    v_n = (v . n) n,   v_t = v - v_n
    v'  = -e_n v_n + e_t v_t                   only when v . n > 0 (moving into the wall)
    with the tangential loss capped by Coulomb friction (``friction`` mu > 0): the wall's tangential
    impulse is at most mu times its normal impulse, |dv_t| <= mu (1 + e_n) |v_n|. A grazing or sliding
    parcel (|v_t| > (1 + e_n) mu |v_n| / (1 - e_t)) then slows as mu times the normal impulse, as
    under the Hertz-Mindlin wall contact of ``kernels/walls.py``; without the cap a parcel pressed
    onto a wall (gravity, a curved path) is reflected every step and loses a factor e_t of its speed
    per step, i.e. more the smaller dt (measured on the rig: the HEL runs at 1e-4 s fell 0.6 m/s behind
    the dem reference downstream). Impacts steeper than that limit keep e_t exactly.
    x'  = x - (1 + e_n) d n                    (the depth travelled past the wall comes back
                                                shortened by e_n, as the normal speed is)

With ``WallParams.spin`` the parcel is a rough solid sphere that carries its spin (``reflect_spin``): the wall
acts at its contact point, so a sphere already rolling along the wall keeps its tangential speed, where the
spinless law takes a factor e_t from it at every impact (the dem reference's spheres roll: on the rig's arms the
spinless parcels fell 8 % behind them; ``python scripts/collision_events.py``).

A point near a corner may still lie outside after one reflection (the second wall); the
reflection repeats (``max_iterations``) and, should it still be outside, the parcel is moved
onto the fluid side along the normal (position only). A parcel moving away from the wall
(v . n <= 0) but outside is moved back the same way, its velocity unchanged. The result:
every live parcel ends with ``d <= 0`` (up to ``margin``) after the call.
"""

import warp as wp

from kernels.sdf import SdfShapes, sdf_union, sdf_union_normal


@wp.struct
class WallParams:
    """Restitution of parcel-wall impacts."""

    restitution_normal: float
    """e_n in [0, 1]: normal speed kept (reversed)."""
    restitution_tangential: float
    """e_t in [0, 1]: tangential speed kept."""
    friction: float
    """Coulomb coefficient mu capping the tangential impulse at mu x the normal one; <= 0: no cap."""
    margin: float
    """Distance (m) a parcel is placed inside the fluid when it has to be moved back onto the wall."""
    max_iterations: int
    """Reflections tried per parcel per step (corners need two)."""
    surface: int
    """1: a parcel meets the wall with its surface, as the DEM's spheres do: the wall acts at d = sdf + r > 0 (the
    centre a particle radius from the wall); 0: as a point (MP-PIC, d = sdf > 0)."""
    spin: int
    """1: the parcel is a solid sphere that carries its spin (``Particles.omega``) and the wall acts at its contact
    point (``reflect_spin``: Walton's rough-sphere law, ``spin_restitution`` and the Coulomb cap; ``e_t`` unused);
    0: the spinless law of ``reflect_velocity`` (Table 1)."""
    spin_restitution: float
    """beta in [-1, 1] of ``reflect_spin``: the contact point's tangential velocity after a sticking impact is -beta
    times the one before (0: the sphere leaves rolling; -1: a smooth wall)."""


@wp.func
def reflect_velocity(v: wp.vec3, n: wp.vec3, e_n: float, e_t: float, friction: float):
    """v' = -e_n (v.n) n + e_t (v - (v.n) n): restitution against a wall of unit normal n; with
    ``friction`` > 0 the tangential loss (1 - e_t)|v_t| is capped at friction (1 + e_n)|v.n|."""
    v_n = wp.dot(v, n) * n
    v_t = v - v_n
    speed_t = wp.length(v_t)
    loss = (1.0 - e_t) * speed_t
    if friction > 0.0:
        loss = wp.min(loss, friction * (1.0 + e_n) * wp.length(v_n))
    kept = v_t
    if speed_t > 0.0:
        kept = v_t * ((speed_t - loss) / speed_t)
    return -e_n * v_n + kept


@wp.func
def reflect_spin(v: wp.vec3, omega: wp.vec3, n: wp.vec3, radius: float, e_n: float, beta: float, friction: float):
    """(v', omega') of a solid sphere (I = 2/5 m r^2) of ``radius`` meeting a wall of unit normal n (out of the fluid,
    into the wall) with v . n > 0 (Walton 1993; Foerster et al. 1994, Phys. Fluids 6:1108): the contact point at
    r n moves at u = v + omega x (r n); the normal speed is reversed with e_n and the contact point's tangential
    velocity u_t becomes -beta u_t, which takes dv_t = -(2/7)(1 + beta) u_t (a tangential impulse at the contact
    changes u_t 7/2 times as much as v_t), unless that exceeds the Coulomb bound ``friction`` (1 + e_n) v.n: then
    dv_t = -friction (1 + e_n) (v.n) u_t/|u_t| (sliding; ``friction`` <= 0: no bound). omega' = omega + (5 / (2 r))
    n x dv_t. A sphere rolling along the wall (u_t = 0) keeps v_t; one without spin leaves a sticking impact with
    v_t' = (5/7) v_t (beta = 0), as the Hertz-Mindlin wall of the dem strategy gives on average over 5-60 degrees of
    incidence (0.59-0.88, beta -0.58...+0.42; ``hel-warp impact --target wall``)."""
    vn = wp.dot(v, n)
    u = v + wp.cross(omega, radius * n)
    u_t = u - wp.dot(u, n) * n
    dv_t = -(2.0 / 7.0) * (1.0 + beta) * u_t
    if friction > 0.0:
        bound = friction * (1.0 + e_n) * vn
        size = wp.length(dv_t)
        if size > bound:
            dv_t = dv_t * (bound / size)
    v_new = v - (1.0 + e_n) * vn * n + dv_t
    omega_new = omega
    if radius > 0.0:
        omega_new = omega + (2.5 / radius) * wp.cross(n, dv_t)
    return v_new, omega_new


@wp.func
def wall_impact(params: WallParams, v: wp.vec3, omega: wp.vec3, n: wp.vec3, radius: float):
    """(v', omega') at a wall of normal n: ``reflect_spin`` with ``params.spin``, else ``reflect_velocity`` (omega
    kept)."""
    if params.spin != 0:
        v_new, omega_new = reflect_spin(v, omega, n, radius, params.restitution_normal, params.spin_restitution,
                                        params.friction)
        return v_new, omega_new
    return reflect_velocity(v, n, params.restitution_normal, params.restitution_tangential, params.friction), omega


CROSSING_BISECTIONS = 30
"""Bisections of the step's segment for the wall crossing (``reflect_kernel`` with start positions): 2^-30 of a
step's path, below float32's resolution of the position."""


@wp.kernel
def reflect_kernel(
    shapes: SdfShapes,
    params: WallParams,
    particle_alive: wp.array(dtype=wp.int32),
    particle_radius: wp.array(dtype=float),
    particle_x_start: wp.array(dtype=wp.vec3),
    use_start: int,
    # outputs (in place)
    particle_x: wp.array(dtype=wp.vec3),
    particle_v: wp.array(dtype=wp.vec3),
    particle_omega: wp.array(dtype=wp.vec3),
    wall_hits: wp.array(dtype=wp.int32),
):
    """``use_start`` = 1: the parcel moved on a straight segment from ``particle_x_start`` (inside the fluid) to its
    position; the first reflection is against the tangent plane where that segment crosses the wall (bisection),
    not at the end point's nearest wall: at a concave corner (the rig's dead-end supply channels) a parcel that went
    deep past one face is nearer another, whose normal would send it the wrong way."""
    tid = wp.tid()
    if particle_alive[tid] == 0:
        return
    x = particle_x[tid]
    v = particle_v[tid]
    omega = wp.vec3(0.0, 0.0, 0.0)
    radius = float(0.0)
    if params.spin != 0:
        omega = particle_omega[tid]
        radius = particle_radius[tid]
    offset = float(0.0)
    if params.surface != 0:
        offset = particle_radius[tid]
    d = sdf_union(shapes, x) + offset
    if d <= 0.0:
        return
    hit = int(0)
    if use_start != 0:
        x0 = particle_x_start[tid]
        if sdf_union(shapes, x0) + offset <= 0.0:
            lo = float(0.0)
            hi = float(1.0)
            for _ in range(CROSSING_BISECTIONS):
                mid = 0.5 * (lo + hi)
                if sdf_union(shapes, x0 + mid * (x - x0)) + offset > 0.0:
                    hi = mid
                else:
                    lo = mid
            xc = x0 + hi * (x - x0)
            n = sdf_union_normal(shapes, xc)
            depth = wp.dot(x - xc, n)
            if depth > 0.0 and wp.dot(v, n) > 0.0:
                v, omega = wall_impact(params, v, omega, n, radius)
                x = x - (1.0 + params.restitution_normal) * depth * n
                hit = 1
                d = sdf_union(shapes, x) + offset
    for _ in range(params.max_iterations):
        if d > 0.0:
            n = sdf_union_normal(shapes, x)
            if wp.dot(v, n) > 0.0:
                v, omega = wall_impact(params, v, omega, n, radius)
                x = x - (1.0 + params.restitution_normal) * d * n
                hit = 1
            else:
                x = x - (d + params.margin) * n
            d = sdf_union(shapes, x) + offset
    if d > 0.0:  # still outside (a corner deeper than the iterations reach): back along the normal
        n = sdf_union_normal(shapes, x)
        x = x - (d + params.margin) * n
    particle_x[tid] = x
    particle_v[tid] = v
    if params.spin != 0:
        particle_omega[tid] = omega
    if hit == 1:
        wp.atomic_add(wall_hits, 0, 1)


@wp.kernel
def outside_count_kernel(
    shapes: SdfShapes,
    particle_x: wp.array(dtype=wp.vec3),
    particle_alive: wp.array(dtype=wp.int32),
    # outputs
    outside: wp.array(dtype=wp.int32),
):
    """Count live parcels whose centre is not inside the fluid (d >= 0)."""
    tid = wp.tid()
    if particle_alive[tid] != 0 and sdf_union(shapes, particle_x[tid]) >= 0.0:
        wp.atomic_add(outside, 0, 1)


# ---------------------------------------------------------------- launch wrappers

def make_wall_params(*, restitution_normal: float = 0.8, restitution_tangential: float = 0.8,
                     friction: float = 0.0, margin: float = 1.0e-9, max_iterations: int = 3,
                     surface: bool = False, spin: bool = False, spin_restitution: float = 0.0) -> WallParams:
    """The kernel-side ``WallParams`` (Table 1 defaults e_n = e_t = 0.8; ``friction`` 0: no Coulomb cap;
    ``surface``: the wall meets the parcel's surface, a particle radius from its centre, instead of its centre;
    ``spin``: the rough-sphere law with spin of ``reflect_spin``, ``spin_restitution`` its beta)."""
    if not -1.0 <= spin_restitution <= 1.0:
        raise ValueError(f"spin_restitution must be in [-1, 1] (got {spin_restitution})")
    p = WallParams()
    p.surface = 1 if surface else 0
    p.spin = 1 if spin else 0
    p.spin_restitution = float(spin_restitution)
    p.restitution_normal = float(restitution_normal)
    p.restitution_tangential = float(restitution_tangential)
    p.friction = float(friction)
    p.margin = float(margin)
    p.max_iterations = int(max_iterations)
    return p


def reflect_at_walls(shapes: SdfShapes, params: WallParams, particle_alive, particle_x, particle_v, wall_hits,
                     particle_radius=None, particle_x_start=None, particle_omega=None) -> None:
    """Reflect, in place, the live parcels that crossed the wall; ``wall_hits[0]`` += how many were reflected.
    ``particle_radius`` is needed when ``params.surface`` or ``params.spin`` is set, ``particle_omega`` (updated in
    place) with ``params.spin``. ``particle_x_start``: the positions the parcels moved from in a straight line this
    step (the push's start): the first reflection is then against the wall where that path crossed it (None: the
    end point's nearest wall)."""
    if particle_radius is None:
        if params.surface != 0 or params.spin != 0:
            raise ValueError("surface wall contact and wall spin need particle_radius")
        particle_radius = wp.zeros(1, dtype=float, device=particle_x.device)
    if particle_omega is None:
        if params.spin != 0:
            raise ValueError("wall spin needs particle_omega")
        particle_omega = wp.zeros(1, dtype=wp.vec3, device=particle_x.device)
    use_start = 0 if particle_x_start is None else 1
    start = particle_x if particle_x_start is None else particle_x_start
    wp.launch(reflect_kernel, dim=particle_x.shape[0], device=particle_x.device,
              inputs=[shapes, params, particle_alive, particle_radius, start, use_start],
              outputs=[particle_x, particle_v, particle_omega, wall_hits])


def count_outside(shapes: SdfShapes, particle_x, particle_alive, outside) -> None:
    """``outside[0]`` += the live parcels with sdf >= 0 (zero it first)."""
    wp.launch(outside_count_kernel, dim=particle_x.shape[0], device=particle_x.device,
              inputs=[shapes, particle_x, particle_alive], outputs=[outside])

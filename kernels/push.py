"""Parcel push: drag correlations and the particle equation of motion, eq. (4).

    du_p/dt = F_D (u_f - u_p) + g (rho_p - rho_f)/rho_p - grad(p')/rho_p + a_coll        (4)

``p'`` is the modified gas pressure p - rho_f g.x (the grid side exposes its gradient), so
buoyancy appears once, through g (rho_p - rho_f)/rho_p. ``a_coll`` is the collision
acceleration (KTGF: -grad(p_s)/(eps_s rho_p), see ``kernels/ktgf.py``; 0 for ``none``).

Drag is semi-implicit, so dt = 1e-3 s stays stable however short the drag response time:

    v_new = (v + dt (F_D u_f + g (rho_p - rho_f)/rho_p - grad(p')/rho_p + a_coll)) / (1 + dt F_D)

with F_D evaluated at the current slip |u_f - v|. The drag impulse the gas gives one parcel
over the step, ``weight * m * F_D dt (u_f - v_new)``, is recorded so that the deposition puts
exactly minus it into the gas (momentum balances to round-off).

Drag laws, all written as the per-particle relaxation rate F_D (1/s):

- Schiller & Naumann (1933): Cd = 24/Re (1 + 0.15 Re^0.687), Re <= 1000; 0.44 above;
  Re = rho_f |u_f - u_p| d / mu_f;  F_D = 18 mu Cd Re / (24 rho_p d^2).
- Wen & Yu (1966): beta = 3/4 Cd eps_s eps_f rho_f |du| eps_f^-2.65 / d, Cd at Re_e = eps_f Re;
- Ergun (1952): beta = 150 eps_s^2 mu / (eps_f d^2) + 1.75 rho_f eps_s |du| / d;
- Gidaspow (1994): Ergun for eps_f <= 0.8, Wen-Yu above (MFIX ``drag_gs.f``, Fluent).
For the beta laws F_D = beta / (eps_s rho_p); the eps_s cancels analytically, so the
functions below return F_D directly and stay finite as eps_s -> 0.
"""

from __future__ import annotations

import math

import warp as wp

from kernels.interp import ParcelArrays
from kernels.launches import LaunchCache, launch

PI_OVER_SIX = wp.constant(wp.float64(math.pi / 6.0))  # float64 (wp.pi is float32)

DRAG_SCHILLER_NAUMANN = wp.constant(0)
DRAG_WEN_YU = wp.constant(1)
DRAG_GIDASPOW = wp.constant(2)
DRAG_ERGUN = wp.constant(3)

#: CLI / config name -> law id used in the kernels.
DRAG_LAWS = {"schiller-naumann": 0, "wen-yu": 1, "gidaspow": 2, "ergun": 3}


@wp.func
def cd_times_re(re: float):
    """Schiller-Naumann Cd * Re: 24 (1 + 0.15 Re^0.687) for Re <= 1000, 0.44 Re above (finite at Re = 0)."""
    if re > 1000.0:
        return 0.44 * re
    return 24.0 * (1.0 + 0.15 * wp.pow(re, 0.687))


@wp.func
def drag_rate_schiller_naumann(slip: float, diameter: float, rho_p: float, rho_f: float, mu_f: float):
    """F_D = 18 mu Cd Re / (24 rho_p d^2), Re = rho_f slip d / mu (single sphere, Schiller & Naumann 1933)."""
    re = rho_f * slip * diameter / mu_f
    return 18.0 * mu_f * cd_times_re(re) / (24.0 * rho_p * diameter * diameter)


@wp.func
def drag_rate_wen_yu(eps_f: float, voidage: float, slip: float, diameter: float, rho_p: float, rho_f: float,
                     mu_f: float):
    """beta/(eps_s rho_p) of Wen & Yu (1966): 3/4 Cd(Re_e) Re_e mu eps_f^-2.65 / (rho_p d^2), Re_e = eps_f Re;
    ``voidage`` = eps_f^-2.65 (``drag_voidage``).

    From beta = 3/4 Cd eps_s eps_f rho_f |du| eps_f^-2.65 / d with Cd |du| = (Cd Re_e) mu / (eps_f rho_f d).
    """
    re_e = eps_f * rho_f * slip * diameter / mu_f
    return 0.75 * cd_times_re(re_e) * mu_f * voidage / (rho_p * diameter * diameter)


@wp.func
def drag_rate_ergun(viscous: float, slip: float, diameter: float, rho_p: float, rho_f: float):
    """beta/(eps_s rho_p) of Ergun (1952): [150 eps_s mu / (eps_f d^2) + 1.75 rho_f |du| / d] / rho_p;
    ``viscous`` = 150 eps_s mu / (eps_f d^2) (``drag_voidage``)."""
    return (viscous + 1.75 * rho_f * slip / diameter) / rho_p


@wp.func
def drag_uses_ergun(law: int, eps_f: float, gidaspow_switch: float):
    """True where the law is Ergun's: ``ergun``, or ``gidaspow`` at eps_f <= gidaspow_switch."""
    return law == DRAG_ERGUN or (law == DRAG_GIDASPOW and eps_f <= gidaspow_switch)


@wp.func
def drag_voidage(law: int, eps_s: float, diameter: float, mu_f: float, gidaspow_switch: float):
    """The law's factor that does not depend on the slip: Wen-Yu's eps_f^-2.65, Ergun's viscous term
    150 eps_s mu / (eps_f d^2), 0 for Schiller-Naumann. :func:`drag_rate` is :func:`drag_rate_at` with it (bit for
    bit, by construction); a caller whose eps_s and d stay fixed over several slips (the implicit exchange's
    passes) computes it once."""
    eps_f = 1.0 - eps_s
    if law == DRAG_SCHILLER_NAUMANN:
        return 0.0
    if drag_uses_ergun(law, eps_f, gidaspow_switch):
        return 150.0 * eps_s * mu_f / (eps_f * diameter * diameter)
    return wp.pow(eps_f, -2.65)


@wp.func
def drag_rate_at(law: int, eps_s: float, voidage: float, slip: float, diameter: float, rho_p: float, rho_f: float,
                 mu_f: float, gidaspow_switch: float):
    """:func:`drag_rate` with the law's slip-free factor given (``voidage``, :func:`drag_voidage` at eps_s and d)."""
    eps_f = 1.0 - eps_s
    if law == DRAG_SCHILLER_NAUMANN:
        return drag_rate_schiller_naumann(slip, diameter, rho_p, rho_f, mu_f)
    if drag_uses_ergun(law, eps_f, gidaspow_switch):
        return drag_rate_ergun(voidage, slip, diameter, rho_p, rho_f)
    return drag_rate_wen_yu(eps_f, voidage, slip, diameter, rho_p, rho_f, mu_f)


@wp.func
def drag_rate(law: int, eps_s: float, slip: float, diameter: float, rho_p: float, rho_f: float, mu_f: float,
              gidaspow_switch: float):
    """Per-particle drag relaxation rate F_D (1/s) of the chosen law; Gidaspow switches at eps_f = gidaspow_switch."""
    return drag_rate_at(law, eps_s, drag_voidage(law, eps_s, diameter, mu_f, gidaspow_switch), slip, diameter, rho_p,
                        rho_f, mu_f, gidaspow_switch)


@wp.struct
class PushParams:
    """Constants of the push. gravity m/s^2; fluid_density kg/m^3; fluid_viscosity Pa s; dt s."""

    gravity: wp.vec3
    fluid_density: float
    fluid_viscosity: float
    drag_law: int
    gidaspow_switch: float
    """eps_f at which Gidaspow switches from Ergun to Wen-Yu (0.8)."""
    eps_s_max: float
    """eps_s seen by the drag law is clipped to [0, eps_s_max] (packing limit 0.63)."""
    dt: float


@wp.func
def body_acceleration(params: PushParams, rho_p: float, grad_p: wp.vec3, a_coll: wp.vec3):
    """Non-drag terms of eq. (4): buoyancy-corrected gravity, -grad(p')/rho_p, a_coll (m/s^2)."""
    return params.gravity * ((rho_p - params.fluid_density) / rho_p) - grad_p / rho_p + a_coll


@wp.func
def parcel_drag_rate(params: PushParams, u_f: wp.vec3, v: wp.vec3, eps_s: float, diameter: float, rho_p: float):
    """F_D (1/s) of the configured law at the slip |u_f - v| and the clipped eps_s."""
    eps = wp.clamp(eps_s, 0.0, params.eps_s_max)
    return drag_rate(params.drag_law, eps, wp.length(u_f - v), diameter, rho_p, params.fluid_density,
                     params.fluid_viscosity, params.gidaspow_switch)


@wp.func
def parcel_voidage(params: PushParams, eps_s: float, diameter: float):
    """The configured law's slip-free factor (:func:`drag_voidage`) at the clipped eps_s."""
    eps = wp.clamp(eps_s, 0.0, params.eps_s_max)
    return drag_voidage(params.drag_law, eps, diameter, params.fluid_viscosity, params.gidaspow_switch)


@wp.func
def parcel_drag_rate_at(params: PushParams, u_f: wp.vec3, v: wp.vec3, eps_s: float, voidage: float, diameter: float,
                        rho_p: float):
    """:func:`parcel_drag_rate` with the law's slip-free factor given (:func:`parcel_voidage`), bit for bit."""
    eps = wp.clamp(eps_s, 0.0, params.eps_s_max)
    return drag_rate_at(params.drag_law, eps, voidage, wp.length(u_f - v), diameter, rho_p, params.fluid_density,
                        params.fluid_viscosity, params.gidaspow_switch)


@wp.func
def parcel_mass(weight: float, rho_p: float, diameter: float):
    """weight * rho_p * pi d^3 / 6 (kg, float64): the mass a parcel stands for."""
    d = wp.float64(diameter)
    return wp.float64(weight) * wp.float64(rho_p) * PI_OVER_SIX * d * d * d


@wp.func
def push_step(params: PushParams, x: wp.vec3, v: wp.vec3, u_f: wp.vec3, f_d: float, rho_p: float,
              diameter: float, weight: float, body: wp.vec3):
    """One semi-implicit step of eq. (4) towards the gas velocity ``u_f`` at the drag rate ``f_d``.

    Returns x_new, v_new, the drag impulse weight * m * F_D dt (u_f - v_new) (N s, float64) and the
    rate weight * m * F_D (kg/s, float64)."""
    dt = params.dt
    v_new = (v + dt * (f_d * u_f + body)) / (1.0 + dt * f_d)
    rate = parcel_mass(weight, rho_p, diameter) * wp.float64(f_d)
    du = u_f - v_new
    rdt = rate * wp.float64(dt)
    impulse = wp.vec3d(rdt * wp.float64(du[0]), rdt * wp.float64(du[1]), rdt * wp.float64(du[2]))
    return x + dt * v_new, v_new, impulse, rate


@wp.kernel
def push_kernel(
    params: PushParams,
    parcels: ParcelArrays,
    parcel_u_f: wp.array(dtype=wp.vec3),
    parcel_grad_p: wp.array(dtype=wp.vec3),
    parcel_eps_s: wp.array(dtype=float),
    parcel_a_coll: wp.array(dtype=wp.vec3),
    # outputs (may alias parcels.x / parcels.v: each thread reads its parcel before writing it)
    particle_x_out: wp.array(dtype=wp.vec3),
    particle_v_out: wp.array(dtype=wp.vec3),
    parcel_drag_impulse: wp.array(dtype=wp.vec3d),
    parcel_drag_coeff: wp.array(dtype=wp.float64),
):
    tid = wp.tid()
    if parcels.alive[tid] == 0:
        parcel_drag_impulse[tid] = wp.vec3d(0.0, 0.0, 0.0)
        parcel_drag_coeff[tid] = wp.float64(0.0)
        return
    v = parcels.v[tid]
    u_f = parcel_u_f[tid]
    rho_p = parcels.density[tid]
    diameter = 2.0 * parcels.radius[tid]
    f_d = parcel_drag_rate(params, u_f, v, parcel_eps_s[tid], diameter, rho_p)
    body = body_acceleration(params, rho_p, parcel_grad_p[tid], parcel_a_coll[tid])
    x_new, v_new, impulse, rate = push_step(params, parcels.x[tid], v, u_f, f_d, rho_p, diameter,
                                            parcels.weight[tid], body)
    particle_v_out[tid] = v_new
    particle_x_out[tid] = x_new
    parcel_drag_impulse[tid] = impulse
    parcel_drag_coeff[tid] = rate


@wp.kernel
def push_at_rate_kernel(
    params: PushParams,
    parcels: ParcelArrays,
    parcel_u_target: wp.array(dtype=wp.vec3),
    parcel_rate: wp.array(dtype=float),
    parcel_grad_p: wp.array(dtype=wp.vec3),
    parcel_a_coll: wp.array(dtype=wp.vec3),
    # outputs (may alias parcels.x / parcels.v)
    particle_x_out: wp.array(dtype=wp.vec3),
    particle_v_out: wp.array(dtype=wp.vec3),
    parcel_drag_impulse: wp.array(dtype=wp.vec3d),
    parcel_drag_coeff: wp.array(dtype=wp.float64),
):
    """The push of :func:`push_kernel` with F_D given (``parcel_rate``) and drag towards ``parcel_u_target``
    (the implicit-exchange gas velocity of ``kernels/deposit.py``)."""
    tid = wp.tid()
    if parcels.alive[tid] == 0:
        parcel_drag_impulse[tid] = wp.vec3d(0.0, 0.0, 0.0)
        parcel_drag_coeff[tid] = wp.float64(0.0)
        return
    rho_p = parcels.density[tid]
    body = body_acceleration(params, rho_p, parcel_grad_p[tid], parcel_a_coll[tid])
    x_new, v_new, impulse, rate = push_step(params, parcels.x[tid], parcels.v[tid], parcel_u_target[tid],
                                            parcel_rate[tid], rho_p, 2.0 * parcels.radius[tid],
                                            parcels.weight[tid], body)
    particle_v_out[tid] = v_new
    particle_x_out[tid] = x_new
    parcel_drag_impulse[tid] = impulse
    parcel_drag_coeff[tid] = rate


@wp.kernel
def drag_rate_kernel(
    law: int,
    gidaspow_switch: float,
    eps_s: wp.array(dtype=float),
    slip: wp.array(dtype=float),
    diameter: wp.array(dtype=float),
    rho_p: wp.array(dtype=float),
    rho_f: float,
    mu_f: float,
    # outputs
    rate: wp.array(dtype=float),
):
    tid = wp.tid()
    rate[tid] = drag_rate(law, eps_s[tid], slip[tid], diameter[tid], rho_p[tid], rho_f, mu_f, gidaspow_switch)


@wp.kernel
def remove_beyond_plane_kernel(
    point: wp.vec3,
    normal: wp.vec3,
    particle_x: wp.array(dtype=wp.vec3),
    # outputs
    particle_alive: wp.array(dtype=wp.int32),
    removed_count: wp.array(dtype=wp.int32),
):
    """Outlet: a live parcel with (x - point).normal > 0 leaves the domain (alive = 0)."""
    tid = wp.tid()
    if particle_alive[tid] != 0 and wp.dot(particle_x[tid] - point, normal) > 0.0:
        particle_alive[tid] = 0
        wp.atomic_add(removed_count, 0, 1)


# ---------------------------------------------------------------- launch wrappers

def push(params: PushParams, parcels: ParcelArrays, parcel_u_f, parcel_grad_p, parcel_eps_s, parcel_a_coll,
         parcel_drag_impulse, parcel_drag_coeff, *, particle_x_out=None, particle_v_out=None):
    """Advance velocities and positions by eq. (4) (into ``parcels.x``/``parcels.v`` unless ``*_out`` are
    given); record drag impulses. ``parcels``: see ``kernels.interp.parcel_arrays``."""
    x_out = parcels.x if particle_x_out is None else particle_x_out
    v_out = parcels.v if particle_v_out is None else particle_v_out
    wp.launch(push_kernel, dim=parcels.x.shape[0], device=parcels.x.device,
              inputs=[params, parcels, parcel_u_f, parcel_grad_p, parcel_eps_s, parcel_a_coll],
              outputs=[x_out, v_out, parcel_drag_impulse, parcel_drag_coeff])


def push_at_rate(params: PushParams, parcels: ParcelArrays, parcel_u_target, parcel_rate, parcel_grad_p,
                 parcel_a_coll, parcel_drag_impulse, parcel_drag_coeff, *, particle_x_out, particle_v_out,
                 launches: LaunchCache | None = None):
    """:func:`push` with the drag rate given per parcel and drag towards ``parcel_u_target``."""
    launch(push_at_rate_kernel, dim=parcels.x.shape[0], device=parcels.x.device,
           inputs=[params, parcels, parcel_u_target, parcel_rate, parcel_grad_p, parcel_a_coll],
           outputs=[particle_x_out, particle_v_out, parcel_drag_impulse, parcel_drag_coeff], cache=launches)


def eval_drag_rate(law: int, eps_s, slip, diameter, rho_p, rho_f: float, mu_f: float, rate,
                   gidaspow_switch: float = 0.8):
    """F_D (1/s) of ``law`` for arrays of eps_s, slip (m/s), diameter (m), rho_p (kg/m^3), into ``rate``."""
    wp.launch(drag_rate_kernel, dim=slip.shape[0], device=slip.device,
              inputs=[int(law), float(gidaspow_switch), eps_s, slip, diameter, rho_p, float(rho_f), float(mu_f)],
              outputs=[rate])


def remove_beyond_plane(point, normal, particle_x, particle_alive, removed_count):
    """Mark parcels past the outlet plane dead; ``removed_count[0]`` is incremented by how many."""
    wp.launch(remove_beyond_plane_kernel, dim=particle_x.shape[0], device=particle_x.device,
              inputs=[wp.vec3(*point), wp.vec3(*normal), particle_x], outputs=[particle_alive, removed_count])

"""Particle -> grid deposition (MP-PIC, Andrews & O'Rourke 1996; Snider 2001).

Each live parcel spreads, with the trilinear weights w_c of ``kernels/interp.py`` (the same
weights the gas velocity is read with):

- solid volume       sum weight * V_p * w_c                    -> cell_solid_volume (m^3)
- momentum source    sum -(drag impulse of the parcel) * w_c   -> cell_momentum_source (N s over the step)
- drag coefficient   sum weight * m_p * F_D * w_c  (= beta V)   -> cell_drag_coeff (kg/s)
- solid mass         sum weight * m_p * w_c                     -> cell_solid_mass (kg)
- solid momentum     sum weight * m_p * v_p * w_c              -> cell_solid_momentum (kg m/s)

then ``cell_eps_s = cell_solid_volume / h^3`` and the mass-averaged solids velocity.

The parcel kernels take a ``kernels.interp.ParcelStencil`` (the cached trilinear stencils, or an empty one)
and index the cell arrays flat (``flat_cells``; the launch wrappers take the (nx, ny, nz) arrays).

Accumulation is in float64 with atomics, and this module compiles with Warp's deterministic
atomics (``DeterministicMode.RUN_TO_RUN``, Warp >= 1.19): the additions into a cell are done in
an order that does not depend on thread scheduling, so a rerun on the same device is
bit-identical (docs/developer/conventions.md rule 10; tested by running twice).
"""

from __future__ import annotations

import math
import sys

import warp as wp

from kernels.launches import LaunchCache, launch
from kernels.interp import (CellGrid, ParcelArrays, ParcelStencil, cell_offset, flat_cells, parcel_cell,
                            parcel_stencil, parcel_support, stencil_holds, stencil_or_empty, store_stencil)
from kernels.push import PushParams, body_acceleration, parcel_drag_rate_at, parcel_mass
from kernels.push import parcel_voidage as parcel_voidage_of

SPHERE_VOLUME_FACTOR = wp.constant(wp.float64(4.0 * math.pi / 3.0))  # float64 (wp.pi is float32)


@wp.func
def solid_volume(parcels: ParcelArrays, tid: int, weight: wp.float64):
    """``weight`` real particles of parcel ``tid``, m^3 (float64; the product in the deposit's order)."""
    r = wp.float64(parcels.radius[tid])
    return weight * SPHERE_VOLUME_FACTOR * r * r * r
vec9d = wp.types.vector(length=9, dtype=wp.float64)
"""The deposit's per-cell sums in one record: solid volume, momentum source (3), drag coefficient, solid mass, solid
momentum (3)."""
NO_EXCHANGE = wp.constant(wp.float64(math.inf))
"""``cell_exchange_divisor`` of a cell the correction leaves out (outside the fluid, or A_c = 0): w / inf = 0."""

DETERMINISTIC = hasattr(wp.config, "DeterministicMode")
TRILINEAR_RECORDS = 8
"""Atomic additions per thread and target of a trilinear parcel (its 8 corners): the bound the module compiles with
first. Warp's static analysis cannot bound the tent's loop, whose length is the parcel's."""
if DETERMINISTIC:
    wp.set_module_options({"deterministic": wp.config.DeterministicMode.RUN_TO_RUN,
                           "deterministic_max_records": TRILINEAR_RECORDS})
_records = TRILINEAR_RECORDS


def reserve_records(need: int) -> int:
    """Make Warp's deterministic atomics of this module hold ``need`` additions per thread and target; returns the
    bound in force.

    On CUDA, ``DeterministicMode.RUN_TO_RUN`` keeps each thread's additions as records in a buffer of
    ``deterministic_max_records`` per thread and target, fixed when the module compiles, and fails a launch whose
    thread makes more (``WarpDeterminismError``; first seen on an H200, the CPU device has no such buffer). A parcel
    of half-width K adds into (2K)^3 cells. The module is rebuilt when the bound grows (once per run in practice: the
    weights are the injection's); ``hel_warp.parcels.coupling`` asks for the largest live parcel's tent before the step's
    tent deposits on CUDA. Memory: parcels x (2K)^3 records of the target's type, ~230 bytes per real particle at
    any weight (8 K^3 ~ 2.8 w)."""
    global _records
    if DETERMINISTIC and need > _records:
        _records = int(need)
        wp.set_module_options({"deterministic_max_records": _records}, module=sys.modules[__name__])
    return _records


@wp.kernel
def deposit_kernel(
    grid: CellGrid,
    stencil: ParcelStencil,
    parcels: ParcelArrays,
    parcel_drag_impulse: wp.array(dtype=wp.vec3d),
    parcel_drag_coeff: wp.array(dtype=wp.float64),
    # outputs (flat, accumulated into; zero it first)
    cell_sums: wp.array(dtype=vec9d),
):
    """The five sums of the module header into one ``vec9d`` per cell (``finish_cells`` unpacks them)."""
    tid = wp.tid()
    x = parcels.x[tid]
    weight = parcels.weight[tid]
    cache = stencil.x.shape[0] > 0 and parcel_support(grid, weight, tid) == 1
    if cache:  # the step's first pass at these positions: it fills the cache (dead parcels too)
        store_stencil(grid, stencil, tid, x)
    if parcels.alive[tid] == 0:
        return
    volume = solid_volume(parcels, tid, wp.float64(parcels.weight[tid]))
    mass = volume * wp.float64(parcels.density[tid])
    v = parcels.v[tid]
    source = -parcel_drag_impulse[tid]
    sums = vec9d(volume, source[0], source[1], source[2], parcel_drag_coeff[tid], mass,
                 mass * wp.float64(v[0]), mass * wp.float64(v[1]), mass * wp.float64(v[2]))
    if cache:
        for corner in range(8):
            wp.atomic_add(cell_sums, stencil.cell[tid, corner], stencil.weight[tid, corner] * sums)
    else:
        base, frac, kw, b, norm = parcel_stencil(grid, x, weight, tid)
        for corner in range(8 * kw * kw * kw):
            idx, w = parcel_cell(grid, base, frac, kw, b, norm, corner)
            wp.atomic_add(cell_sums, cell_offset(grid, idx), w * sums)


@wp.kernel
def cloud_volume_kernel(
    grid: CellGrid,
    parcels: ParcelArrays,
    # outputs (flat, accumulated into; zero it first)
    cell_solid_volume: wp.array(dtype=wp.float64),
):
    """The live parcels' solid volume w V_p into the cells with the weight rule's stencils (``grid`` without
    cloud widths): what ``cloud_width_kernel`` reads the parcels' surroundings from."""
    tid = wp.tid()
    if parcels.alive[tid] == 0:
        return
    volume = solid_volume(parcels, tid, wp.float64(parcels.weight[tid]))
    base, frac, kw, b, norm = parcel_stencil(grid, parcels.x[tid], parcels.weight[tid], tid)
    for corner in range(8 * kw * kw * kw):
        idx, w = parcel_cell(grid, base, frac, kw, b, norm, corner)
        wp.atomic_add(cell_solid_volume, cell_offset(grid, idx), w * volume)


@wp.kernel
def cloud_width_kernel(
    grid: CellGrid,
    parcels: ParcelArrays,
    cell_solid_volume: wp.array(dtype=wp.float64),
    # outputs
    parcel_cloud: wp.array(dtype=wp.float32),
):
    """Per parcel the width b (cells) of the cloud it couples through (``kernels/interp.py`` ``cloud_weight``): its
    w real particles stand on a cube lattice at the spacing l = n^(-1/3) of the real particles around it, per-axis
    variance (w^(2/3) - 1) l^2 / 12, which a uniform cloud of width

        b = sqrt(w^(2/3) - 1) min(1, (n h^3)^(-1/3)),   n = eps_env / V_p,

    has. eps_env is the solids fraction of the *other* parcels at the parcel, read from ``cloud_volume_kernel``'s
    deposit with the parcel's own weight-rule stencil W_c: sum_c W_c (V_c - w V_p W_c) / h^3 (its own deposit
    taken out exactly: alone, a parcel's particles would otherwise make their own density). Where the others are
    sparser than one particle per cell (n h^3 < 1) the spacing is taken as h: the widest cloud, b =
    sqrt(w^(2/3) - 1), as wide as the weight rule's tent in second moment. Weight 1 (and dead slots): b = 0, the
    trilinear stencil."""
    tid = wp.tid()
    b = wp.float64(0.0)
    weight = parcels.weight[tid]
    if parcels.alive[tid] != 0 and weight > 1.0 and grid.spread != 0:
        vp = solid_volume(parcels, tid, wp.float64(1.0))
        w64 = wp.float64(weight)
        base, frac, kw, b0, norm = parcel_stencil(grid, parcels.x[tid], weight, tid)
        read = wp.float64(0.0)
        own = wp.float64(0.0)
        for corner in range(8 * kw * kw * kw):
            idx, w = parcel_cell(grid, base, frac, kw, b0, norm, corner)
            read = read + w * cell_solid_volume[cell_offset(grid, idx)]
            own = own + w * w
        h3 = grid.spacing * grid.spacing * grid.spacing
        others = wp.max(read - w64 * vp * own, wp.float64(0.0))  # eps_env h^3, m^3
        spacing = wp.float64(1.0)  # l / h
        if others > vp:
            spacing = wp.pow(vp / others, wp.float64(1.0 / 3.0))
        b = wp.sqrt(wp.max(wp.pow(w64, wp.float64(2.0 / 3.0)) - wp.float64(1.0), wp.float64(0.0))) * spacing
    parcel_cloud[tid] = float(b)


@wp.kernel
def finish_cells_kernel(
    cell_volume: wp.float64,
    cell_sums: wp.array(dtype=vec9d),
    # outputs
    cell_solid_volume: wp.array(dtype=wp.float64),
    cell_momentum_source: wp.array(dtype=wp.vec3d),
    cell_drag_coeff: wp.array(dtype=wp.float64),
    cell_solid_mass: wp.array(dtype=wp.float64),
    cell_solid_momentum: wp.array(dtype=wp.vec3d),
    cell_eps_s: wp.array(dtype=float),
    cell_solid_velocity: wp.array(dtype=wp.vec3),
):
    """The five sums out of the deposit's record; eps_s = V_s / V_cell and the mass-averaged solids velocity (cell
    arrays flat)."""
    c = wp.tid()
    sums = cell_sums[c]
    volume = sums[0]
    mass = sums[5]
    momentum = wp.vec3d(sums[6], sums[7], sums[8])
    cell_solid_volume[c] = volume
    cell_momentum_source[c] = wp.vec3d(sums[1], sums[2], sums[3])
    cell_drag_coeff[c] = sums[4]
    cell_solid_mass[c] = mass
    cell_solid_momentum[c] = momentum
    cell_eps_s[c] = float(volume / cell_volume)
    u = wp.vec3(0.0, 0.0, 0.0)
    if mass > wp.float64(0.0):
        p = momentum / mass
        u = wp.vec3(float(p[0]), float(p[1]), float(p[2]))
    cell_solid_velocity[c] = u


@wp.kernel
def to_float32_kernel(
    cell_momentum_source: wp.array(dtype=wp.vec3d),
    cell_drag_coeff: wp.array(dtype=wp.float64),
    # outputs
    cell_momentum_source_f32: wp.array(dtype=wp.vec3),
    cell_drag_coeff_f32: wp.array(dtype=float),
):
    c = wp.tid()
    s = cell_momentum_source[c]
    cell_momentum_source_f32[c] = wp.vec3(float(s[0]), float(s[1]), float(s[2]))
    cell_drag_coeff_f32[c] = float(cell_drag_coeff[c])


# ---------------------------------------------------------------- implicit momentum exchange
#
# The drag exchange of a step, solved implicitly for gas and parcels together (the explicit hand-back
# of the parcels' impulses to the gas overshoots by ~ dt K_sg / (eps_f rho_f), e.g. x40 at eps_s = 0.3,
# dt = 1e-3 s: the gas velocity then grows without bound in dense cells). Per cell c, with
# D_i = weight m_i dt F_D / (1 + dt F_D) (kg; the semi-implicit push moves v*_i = v_i + dt a_body
# by D_i/(weight m_i) (u - v*_i)) and the CIC weights w_ic:
#
#   A_c = sum_i w_ic D_i,   B_c = sum_i w_ic D_i v*_i,   M_c = rho_f eps_f V_c  (gas mass)
#   u_eq_c = (M_c u_c + B_c) / (M_c + A_c)      -- the joint backward-Euler solution of the cell
#   G_c = M_c (u_eq_c - u_c)                    -- the impulse the gas receives (next gas step)
#
# the parcels are pushed towards u_eq interpolated with the same weights (impulses J_i), and the
# mismatch delta_c = G_c + sum_i w_ic J_i (non-zero only because interpolation mixes cells) is taken
# back from the parcels in proportion to w_ic D_i / A_c: dJ_i = -D_i sum_c w_ic delta_c / A_c. Then
# sum_i (J_i + dJ_i) = -sum_c G_c exactly (float64): the exchange conserves momentum, and neither
# phase overshoots the common velocity. Cells outside the fluid keep the explicit hand-back (their
# impulses go to the walls in the gas step, as before).
#
# The correction reads A_c through ``cell_exchange_divisor`` (A_c, or +inf for a cell it leaves out) so that its
# corner loop has no branch and no fluid-mask read (~2x faster on the CPU): an excluded cell adds
# (w / inf) delta_c = +-0, which leaves the sum as it is (it starts at +0 and a sum is -0 only when both terms
# are), the same bits as skipping it while delta_c is finite.


@wp.kernel
def exchange_voidage_kernel(
    params: PushParams,
    parcels: ParcelArrays,
    parcel_eps_s: wp.array(dtype=float),
    # outputs
    parcel_voidage: wp.array(dtype=float),
):
    """The drag law's slip-free factor per parcel (``kernels.push.parcel_voidage``), once for the exchange's
    passes (eps_s and d do not change between them)."""
    tid = wp.tid()
    parcel_voidage[tid] = parcel_voidage_of(params, parcel_eps_s[tid], 2.0 * parcels.radius[tid])


@wp.kernel
def exchange_rate_kernel(
    params: PushParams,
    parcels: ParcelArrays,
    parcel_u_f: wp.array(dtype=wp.vec3),
    parcel_eps_s: wp.array(dtype=float),
    parcel_voidage: wp.array(dtype=float),
    # outputs
    parcel_rate: wp.array(dtype=float),
    parcel_exchange: wp.array(dtype=wp.float64),
):
    """F_D at the slip against ``parcel_u_f`` and D_i (see above)."""
    tid = wp.tid()
    if parcels.alive[tid] == 0:
        parcel_rate[tid] = 0.0
        parcel_exchange[tid] = wp.float64(0.0)
        return
    rho_p = parcels.density[tid]
    diameter = 2.0 * parcels.radius[tid]
    f_d = parcel_drag_rate_at(params, parcel_u_f[tid], parcels.v[tid], parcel_eps_s[tid], parcel_voidage[tid],
                              diameter, rho_p)
    parcel_rate[tid] = f_d
    fdt = wp.float64(params.dt) * wp.float64(f_d)
    parcel_exchange[tid] = parcel_mass(parcels.weight[tid], rho_p, diameter) * fdt / (wp.float64(1.0) + fdt)


@wp.kernel
def exchange_deposit_kernel(
    grid: CellGrid,
    stencil: ParcelStencil,
    params: PushParams,
    parcels: ParcelArrays,
    parcel_grad_p: wp.array(dtype=wp.vec3),
    parcel_a_coll: wp.array(dtype=wp.vec3),
    parcel_exchange: wp.array(dtype=wp.float64),
    # outputs (cell array flat, accumulated into; zero it first)
    cell_exchange_sums: wp.array(dtype=wp.vec4d),
):
    """(A_c, B_c) (see above) as one vec4d per cell, from ``exchange_rate_kernel``'s D_i."""
    tid = wp.tid()
    if parcels.alive[tid] == 0:
        return
    d = parcel_exchange[tid]
    v_star = parcels.v[tid] + params.dt * body_acceleration(params, parcels.density[tid], parcel_grad_p[tid],
                                                            parcel_a_coll[tid])
    dv = wp.vec4d(d, d * wp.float64(v_star[0]), d * wp.float64(v_star[1]), d * wp.float64(v_star[2]))
    x = parcels.x[tid]
    weight = parcels.weight[tid]
    if stencil_holds(stencil, tid, x, parcel_support(grid, weight, tid)):
        for corner in range(8):
            wp.atomic_add(cell_exchange_sums, stencil.cell[tid, corner], stencil.weight[tid, corner] * dv)
    else:
        base, frac, kw, b, norm = parcel_stencil(grid, x, weight, tid)
        for corner in range(8 * kw * kw * kw):
            idx, w = parcel_cell(grid, base, frac, kw, b, norm, corner)
            wp.atomic_add(cell_exchange_sums, cell_offset(grid, idx), w * dv)


@wp.kernel
def exchange_cells_kernel(
    gas_mass_full: wp.float64,
    eps_f_min: float,
    cell_fluid: wp.array(dtype=wp.int32),
    cell_eps_s: wp.array(dtype=float),
    cell_velocity: wp.array(dtype=wp.vec3),
    cell_exchange_sums: wp.array(dtype=wp.vec4d),
    pressure_scale: wp.float64,
    cell_grad_p: wp.array(dtype=wp.vec3),
    # outputs
    cell_exchange_coeff: wp.array(dtype=wp.float64),
    cell_exchange_momentum: wp.array(dtype=wp.vec3d),
    cell_u_eq: wp.array(dtype=wp.vec3),
    cell_gas_impulse: wp.array(dtype=wp.vec3d),
    cell_mismatch: wp.array(dtype=wp.vec3d),
    cell_exchange_divisor: wp.array(dtype=wp.float64),
):
    """A_c and B_c from the deposit's sums; u_eq_c and G_c (``gas_mass_full`` = rho_f V_c, the gas mass of a
    particle-free cell); mismatch = G_c; the correction's divisor A_c (``NO_EXCHANGE`` where the cell is left out).
    Cell arrays flat (``flat_cells``: one index instead of three per access).

    The gas relaxes with the parcels while its pressure gradient, held over the step, accelerates it by
    s = -``pressure_scale`` grad p' (``pressure_scale`` = dt / rho_f; 0: the gas's inertia alone):
    u_eq = (M (u + s) + B) / (M + A), G = M (u_eq - u - s), the drag impulse alone (the gas step applies the
    pressure itself). Backward Euler of both phases under their held forces, so in a steady state the drag equals
    the pressure force; with the inertia alone a packed bed's drag is capped near M u / dt."""
    c = wp.tid()
    u = cell_velocity[c]
    sums = cell_exchange_sums[c]
    a = sums[0]
    b = wp.vec3d(sums[1], sums[2], sums[3])
    cell_exchange_coeff[c] = a
    cell_exchange_momentum[c] = b
    zero = wp.vec3d(0.0, 0.0, 0.0)
    if cell_fluid[c] == 0 or a <= wp.float64(0.0):
        cell_u_eq[c] = u
        cell_gas_impulse[c] = zero
        cell_mismatch[c] = zero
        cell_exchange_divisor[c] = NO_EXCHANGE
        return
    cell_exchange_divisor[c] = a
    eps_f = wp.max(1.0 - cell_eps_s[c], eps_f_min)
    m = gas_mass_full * wp.float64(eps_f)
    ud = wp.vec3d(wp.float64(u[0]), wp.float64(u[1]), wp.float64(u[2]))
    gp = cell_grad_p[c]
    held = -pressure_scale * wp.vec3d(wp.float64(gp[0]), wp.float64(gp[1]), wp.float64(gp[2]))
    u_eq = (m * (ud + held) + b) / (m + a)
    g = m * (u_eq - ud - held)
    cell_u_eq[c] = wp.vec3(float(u_eq[0]), float(u_eq[1]), float(u_eq[2]))
    cell_gas_impulse[c] = g
    cell_mismatch[c] = g


@wp.kernel
def impulse_deposit_kernel(
    grid: CellGrid,
    stencil: ParcelStencil,
    parcels: ParcelArrays,
    parcel_drag_impulse: wp.array(dtype=wp.vec3d),
    # outputs (flat, accumulated into)
    cell_mismatch: wp.array(dtype=wp.vec3d),
):
    """cell_mismatch += sum_i w_ic J_i at the parcels' positions before the push (``parcels.x``)."""
    tid = wp.tid()
    if parcels.alive[tid] == 0:
        return
    j = parcel_drag_impulse[tid]
    x = parcels.x[tid]
    weight = parcels.weight[tid]
    if stencil_holds(stencil, tid, x, parcel_support(grid, weight, tid)):
        for corner in range(8):
            wp.atomic_add(cell_mismatch, stencil.cell[tid, corner], stencil.weight[tid, corner] * j)
    else:
        base, frac, kw, b, norm = parcel_stencil(grid, x, weight, tid)
        for corner in range(8 * kw * kw * kw):
            idx, w = parcel_cell(grid, base, frac, kw, b, norm, corner)
            wp.atomic_add(cell_mismatch, cell_offset(grid, idx), w * j)


@wp.kernel
def exchange_correct_kernel(
    grid: CellGrid,
    stencil: ParcelStencil,
    dt: float,
    cell_exchange_divisor: wp.array(dtype=wp.float64),
    cell_mismatch: wp.array(dtype=wp.vec3d),
    parcels: ParcelArrays,
    parcel_exchange: wp.array(dtype=wp.float64),
    # in/out: the pushed state and impulses (parcels.x: the positions before the push)
    particle_x_out: wp.array(dtype=wp.vec3),
    particle_v_out: wp.array(dtype=wp.vec3),
    parcel_drag_impulse: wp.array(dtype=wp.vec3d),
):
    """dJ_i = -D_i sum_c w_ic delta_c / A_c over fluid cells with A_c > 0 (``cell_exchange_divisor``: A_c, inf for
    the others); v and x (= x + dt v) follow (cell arrays flat)."""
    tid = wp.tid()
    if parcels.alive[tid] == 0:
        return
    corr = wp.vec3d(0.0, 0.0, 0.0)
    x = parcels.x[tid]
    weight = parcels.weight[tid]
    if stencil_holds(stencil, tid, x, parcel_support(grid, weight, tid)):
        for corner in range(8):
            c = stencil.cell[tid, corner]
            corr = corr + (stencil.weight[tid, corner] / cell_exchange_divisor[c]) * cell_mismatch[c]
    else:
        base, frac, kw, b, norm = parcel_stencil(grid, x, weight, tid)
        for corner in range(8 * kw * kw * kw):
            idx, w = parcel_cell(grid, base, frac, kw, b, norm, corner)
            c = cell_offset(grid, idx)
            corr = corr + (w / cell_exchange_divisor[c]) * cell_mismatch[c]
    dj = -parcel_exchange[tid] * corr
    parcel_drag_impulse[tid] = parcel_drag_impulse[tid] + dj
    dv64 = dj / parcel_mass(parcels.weight[tid], parcels.density[tid], 2.0 * parcels.radius[tid])
    dv = wp.vec3(float(dv64[0]), float(dv64[1]), float(dv64[2]))
    particle_v_out[tid] = particle_v_out[tid] + dv
    particle_x_out[tid] = particle_x_out[tid] + dt * dv


# ---------------------------------------------------------------- launch wrappers

def deposit(grid: CellGrid, parcels: ParcelArrays, parcel_drag_impulse, parcel_drag_coeff, *, cell_sums,
            stencil: ParcelStencil | None = None, launches: LaunchCache | None = None):
    """Zero the (nx, ny, nz) ``vec9d`` record ``cell_sums`` and deposit every live parcel into it (``parcels``: see
    ``kernels.interp.parcel_arrays``; :func:`finish_cells` unpacks it: one accumulation of nine float64 per corner
    instead of five arrays, ~10-20 ns per parcel less on the CPU); ``stencil``: a ``ParcelStencil`` filled here
    with every trilinear parcel's row at ``parcels.x`` (the deposit is the step's first pass at new positions),
    None: no cache."""
    cell_sums.zero_()
    launch(deposit_kernel, dim=parcels.x.shape[0], device=parcels.x.device,
           inputs=[grid, stencil_or_empty(stencil, parcels.x), parcels, parcel_drag_impulse, parcel_drag_coeff],
           outputs=[flat_cells(cell_sums)], cache=launches)


def cloud_widths(grid: CellGrid, parcels: ParcelArrays, *, cell_solid_volume, parcel_cloud,
                 launches: LaunchCache | None = None):
    """Every parcel's cloud width from the real particles around it (``cloud_width_kernel``) into
    ``parcel_cloud``; ``grid``: without cloud widths (the weight rule's tents read the surroundings);
    ``cell_solid_volume``: float64 cells, overwritten (scratch)."""
    cell_solid_volume.zero_()
    n = parcels.x.shape[0]
    launch(cloud_volume_kernel, dim=n, device=parcels.x.device, inputs=[grid, parcels],
           outputs=[flat_cells(cell_solid_volume)], cache=launches)
    launch(cloud_width_kernel, dim=n, device=parcels.x.device,
           inputs=[grid, parcels, flat_cells(cell_solid_volume)], outputs=[parcel_cloud], cache=launches)


def finish_cells(cell_volume: float, cell_sums, *, cell_solid_volume, cell_momentum_source, cell_drag_coeff,
                 cell_solid_mass, cell_solid_momentum, cell_eps_s, cell_solid_velocity,
                 launches: LaunchCache | None = None):
    """The five sums out of :func:`deposit`'s record, the solid volume fraction and the mass-averaged solids
    velocity."""
    launch(finish_cells_kernel, dim=cell_eps_s.size, device=cell_eps_s.device,
           inputs=[wp.float64(cell_volume), flat_cells(cell_sums)],
           outputs=[flat_cells(a) for a in (cell_solid_volume, cell_momentum_source, cell_drag_coeff, cell_solid_mass,
                                            cell_solid_momentum, cell_eps_s, cell_solid_velocity)], cache=launches)


def to_float32(cell_momentum_source, cell_drag_coeff, *, cell_momentum_source_f32, cell_drag_coeff_f32,
               launches: LaunchCache | None = None):
    """Copy the float64 sums into float32 cell arrays (the gas solver's inputs)."""
    launch(to_float32_kernel, dim=cell_drag_coeff.size, device=cell_drag_coeff.device,
           inputs=[flat_cells(cell_momentum_source), flat_cells(cell_drag_coeff)],
           outputs=[flat_cells(cell_momentum_source_f32), flat_cells(cell_drag_coeff_f32)], cache=launches)


def exchange_voidage(params, parcels: ParcelArrays, parcel_eps_s, *, parcel_voidage,
                     launches: LaunchCache | None = None):
    """The drag law's slip-free factor per parcel, for the exchange's passes (implicit exchange, step 0)."""
    launch(exchange_voidage_kernel, dim=parcels.x.shape[0], device=parcels.x.device,
           inputs=[params, parcels, parcel_eps_s], outputs=[parcel_voidage], cache=launches)


def exchange_deposit(grid: CellGrid, params, parcels: ParcelArrays, parcel_u_f, parcel_eps_s, parcel_voidage,
                     parcel_grad_p, parcel_a_coll, *, parcel_rate, parcel_exchange, cell_exchange_sums,
                     stencil: ParcelStencil | None = None, launches: LaunchCache | None = None):
    """F_D and D_i (``parcel_voidage``: :func:`exchange_voidage`'s), then zero (A, B) and deposit (D_i, D_i v*_i)
    into one vec4d per cell (implicit exchange, step 1; ``stencil``: as :func:`deposit`). Two parcel passes: the
    drag law alone is short enough for the CPU to overlap parcels, and a vec4d is one accumulation of four float64
    per corner (~30 ns per parcel and pass less than the fused pass into two arrays)."""
    n = parcels.x.shape[0]
    launch(exchange_rate_kernel, dim=n, device=parcels.x.device,
           inputs=[params, parcels, parcel_u_f, parcel_eps_s, parcel_voidage], outputs=[parcel_rate, parcel_exchange],
           cache=launches)
    cell_exchange_sums.zero_()
    launch(exchange_deposit_kernel, dim=n, device=parcels.x.device,
           inputs=[grid, stencil_or_empty(stencil, parcels.x), params, parcels, parcel_grad_p, parcel_a_coll,
                   parcel_exchange],
           outputs=[flat_cells(cell_exchange_sums)], cache=launches)


def exchange_cells(gas_mass_full: float, eps_f_min: float, cell_fluid, cell_eps_s, cell_velocity,
                   cell_exchange_sums, *, cell_exchange_coeff, cell_exchange_momentum, cell_u_eq, cell_gas_impulse,
                   cell_mismatch, cell_exchange_divisor, cell_grad_p=None, pressure_scale: float = 0.0,
                   launches: LaunchCache | None = None):
    """A and B from :func:`exchange_deposit`'s sums, u_eq, the gas impulse G and the mismatch's start value G per
    cell (implicit exchange, step 2), and the divisor the correction reads (A, or inf where a cell is left out:
    outside the fluid or A = 0). ``cell_grad_p`` (grad p', Pa/m) with ``pressure_scale`` = dt / rho_f: the gas
    relaxes under its held pressure gradient (``exchange_cells_kernel``); None: its inertia alone."""
    if cell_grad_p is None:
        cell_grad_p, pressure_scale = cell_velocity, 0.0  # any vec3 cell array, scaled by 0
    launch(exchange_cells_kernel, dim=cell_eps_s.size, device=cell_eps_s.device,
           inputs=[wp.float64(gas_mass_full), float(eps_f_min)]
           + [flat_cells(a) for a in (cell_fluid, cell_eps_s, cell_velocity, cell_exchange_sums)]
           + [wp.float64(pressure_scale), flat_cells(cell_grad_p)],
           outputs=[flat_cells(a) for a in (cell_exchange_coeff, cell_exchange_momentum, cell_u_eq, cell_gas_impulse,
                                            cell_mismatch, cell_exchange_divisor)], cache=launches)


def exchange_correct(grid: CellGrid, dt: float, cell_exchange_divisor, cell_mismatch,
                     parcels: ParcelArrays, parcel_exchange, parcel_drag_impulse, *, particle_x_out, particle_v_out,
                     stencil: ParcelStencil | None = None, launches: LaunchCache | None = None):
    """Deposit the push's impulses into the mismatch and take it back from the parcels (steps 4-5);
    ``cell_exchange_divisor``: :func:`exchange_cells`'s; ``parcels.x``: the positions before the push
    (``stencil``: as :func:`deposit`)."""
    n = parcels.x.shape[0]
    stencil = stencil_or_empty(stencil, parcels.x)
    mismatch = flat_cells(cell_mismatch)
    launch(impulse_deposit_kernel, dim=n, device=parcels.x.device,
           inputs=[grid, stencil, parcels, parcel_drag_impulse], outputs=[mismatch], cache=launches)
    launch(exchange_correct_kernel, dim=n, device=parcels.x.device,
           inputs=[grid, stencil, float(dt), flat_cells(cell_exchange_divisor), mismatch, parcels,
                   parcel_exchange],
           outputs=[particle_x_out, particle_v_out, parcel_drag_impulse], cache=launches)

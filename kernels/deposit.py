"""Particle -> grid deposition (MP-PIC, Andrews & O'Rourke 1996; Snider 2001).

Each live parcel spreads, with the trilinear weights w_c of ``kernels/interp.py`` (the same
weights the gas velocity is read with):

- solid volume       sum weight * V_p * w_c                    -> cell_solid_volume (m^3)
- momentum source    sum -(drag impulse of the parcel) * w_c   -> cell_momentum_source (N s over the step)
- drag coefficient   sum weight * m_p * F_D * w_c  (= beta V)   -> cell_drag_coeff (kg/s)
- solid mass         sum weight * m_p * w_c                     -> cell_solid_mass (kg)
- solid momentum     sum weight * m_p * v_p * w_c              -> cell_solid_momentum (kg m/s)

then ``cell_eps_s = cell_solid_volume / h^3`` and the mass-averaged solids velocity.

Accumulation is in float64 with atomics, and this module compiles with Warp's deterministic
atomics (``DeterministicMode.RUN_TO_RUN``, Warp >= 1.19): the additions into a cell are done in
an order that does not depend on thread scheduling, so a rerun on the same device is
bit-identical (CONVENTIONS rule 10; tested by running twice).
"""

from __future__ import annotations

import math

import warp as wp

from kernels.interp import CellGrid, cic_corner, cic_stencil

SPHERE_VOLUME_FACTOR = wp.constant(wp.float64(4.0 * math.pi / 3.0))  # float64 (wp.pi is float32)

if hasattr(wp.config, "DeterministicMode"):
    wp.set_module_options({"deterministic": wp.config.DeterministicMode.RUN_TO_RUN})


@wp.kernel
def deposit_kernel(
    grid: CellGrid,
    particle_x: wp.array(dtype=wp.vec3),
    particle_v: wp.array(dtype=wp.vec3),
    particle_radius: wp.array(dtype=float),
    particle_density: wp.array(dtype=float),
    particle_weight: wp.array(dtype=float),
    particle_alive: wp.array(dtype=wp.int32),
    parcel_drag_impulse: wp.array(dtype=wp.vec3d),
    parcel_drag_coeff: wp.array(dtype=wp.float64),
    # outputs (accumulated into; zero them first)
    cell_solid_volume: wp.array3d(dtype=wp.float64),
    cell_momentum_source: wp.array3d(dtype=wp.vec3d),
    cell_drag_coeff: wp.array3d(dtype=wp.float64),
    cell_solid_mass: wp.array3d(dtype=wp.float64),
    cell_solid_momentum: wp.array3d(dtype=wp.vec3d),
):
    tid = wp.tid()
    if particle_alive[tid] == 0:
        return
    r = wp.float64(particle_radius[tid])
    volume = wp.float64(particle_weight[tid]) * SPHERE_VOLUME_FACTOR * r * r * r
    mass = volume * wp.float64(particle_density[tid])
    v = particle_v[tid]
    momentum = mass * wp.vec3d(wp.float64(v[0]), wp.float64(v[1]), wp.float64(v[2]))
    source = -parcel_drag_impulse[tid]
    coeff = parcel_drag_coeff[tid]
    base, frac = cic_stencil(grid, particle_x[tid])
    for corner in range(8):
        idx, w = cic_corner(grid, base, frac, corner)
        i = idx[0]
        j = idx[1]
        k = idx[2]
        wp.atomic_add(cell_solid_volume, i, j, k, w * volume)
        wp.atomic_add(cell_momentum_source, i, j, k, w * source)
        wp.atomic_add(cell_drag_coeff, i, j, k, w * coeff)
        wp.atomic_add(cell_solid_mass, i, j, k, w * mass)
        wp.atomic_add(cell_solid_momentum, i, j, k, w * momentum)


@wp.kernel
def finish_cells_kernel(
    cell_volume: wp.float64,
    cell_solid_volume: wp.array3d(dtype=wp.float64),
    cell_solid_mass: wp.array3d(dtype=wp.float64),
    cell_solid_momentum: wp.array3d(dtype=wp.vec3d),
    # outputs
    cell_eps_s: wp.array3d(dtype=float),
    cell_solid_velocity: wp.array3d(dtype=wp.vec3),
):
    i, j, k = wp.tid()
    cell_eps_s[i, j, k] = float(cell_solid_volume[i, j, k] / cell_volume)
    mass = cell_solid_mass[i, j, k]
    u = wp.vec3(0.0, 0.0, 0.0)
    if mass > wp.float64(0.0):
        p = cell_solid_momentum[i, j, k] / mass
        u = wp.vec3(float(p[0]), float(p[1]), float(p[2]))
    cell_solid_velocity[i, j, k] = u


@wp.kernel
def to_float32_kernel(
    cell_momentum_source: wp.array3d(dtype=wp.vec3d),
    cell_drag_coeff: wp.array3d(dtype=wp.float64),
    # outputs
    cell_momentum_source_f32: wp.array3d(dtype=wp.vec3),
    cell_drag_coeff_f32: wp.array3d(dtype=float),
):
    i, j, k = wp.tid()
    s = cell_momentum_source[i, j, k]
    cell_momentum_source_f32[i, j, k] = wp.vec3(float(s[0]), float(s[1]), float(s[2]))
    cell_drag_coeff_f32[i, j, k] = float(cell_drag_coeff[i, j, k])


# ---------------------------------------------------------------- launch wrappers

def deposit(grid: CellGrid, particle_x, particle_v, particle_radius, particle_density, particle_weight,
            particle_alive, parcel_drag_impulse, parcel_drag_coeff, *, cell_solid_volume, cell_momentum_source,
            cell_drag_coeff, cell_solid_mass, cell_solid_momentum):
    """Zero the five accumulators and deposit every live parcel into them."""
    for arr in (cell_solid_volume, cell_momentum_source, cell_drag_coeff, cell_solid_mass, cell_solid_momentum):
        arr.zero_()
    wp.launch(deposit_kernel, dim=particle_x.shape[0], device=particle_x.device,
              inputs=[grid, particle_x, particle_v, particle_radius, particle_density, particle_weight,
                      particle_alive, parcel_drag_impulse, parcel_drag_coeff],
              outputs=[cell_solid_volume, cell_momentum_source, cell_drag_coeff, cell_solid_mass,
                       cell_solid_momentum])


def finish_cells(cell_volume: float, cell_solid_volume, cell_solid_mass, cell_solid_momentum, *, cell_eps_s,
                 cell_solid_velocity):
    """Solid volume fraction and mass-averaged solids velocity from the deposited sums."""
    wp.launch(finish_cells_kernel, dim=cell_eps_s.shape, device=cell_eps_s.device,
              inputs=[wp.float64(cell_volume), cell_solid_volume, cell_solid_mass, cell_solid_momentum],
              outputs=[cell_eps_s, cell_solid_velocity])


def to_float32(cell_momentum_source, cell_drag_coeff, *, cell_momentum_source_f32, cell_drag_coeff_f32):
    """Copy the float64 sums into float32 cell arrays (the gas solver's inputs)."""
    wp.launch(to_float32_kernel, dim=cell_drag_coeff.shape, device=cell_drag_coeff.device,
              inputs=[cell_momentum_source, cell_drag_coeff],
              outputs=[cell_momentum_source_f32, cell_drag_coeff_f32])

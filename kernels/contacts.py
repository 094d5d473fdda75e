"""Neighbour search and persistent contact lists for N-body DEM (one thread per particle).

What it computes
- A Verlet neighbour list (Verlet 1967; LAMMPS ``neighbor`` with ``skin`` and ``check yes``):
  particle i lists every j with ``|x_i - x_j| < r_i + r_j + skin``, found with ``wp.HashGrid``
  (cell size ``2 r_max + skin``). The list is rebuilt only when some particle has moved more than
  ``skin / 2`` since the last build (:func:`flag_rebuild`), so no contact can appear unseen.
- Each list row is sorted by partner id and has a fixed capacity; a particle with more
  candidates than the capacity raises the ``overflow`` counter (the host turns it into an error).
- The row carries the Mindlin tangential shear displacement of each contact; on a rebuild the
  old row is merged with the new one by partner id, so contact history survives rebuilds.
- Contact forces (:func:`contact_forces`): thread i sums its own contacts with the Hertz-Mindlin
  law of ``kernels/hertz.py`` — a *full* list (i sees j and j sees i), so no atomics and a sum
  order fixed by the sorted row: bitwise deterministic by construction (tested on the CPU;
  the CUDA path is untested here).
- A compact pair list (i < j, touching only) for collision-rate and statistics kernels.
- A spatial sort (gather by hash-grid cell order) that keeps neighbours close in memory.

Layout: ``contact_partner`` (N, capacity) int32, -1 where empty; ``contact_count`` (N,) int32;
``contact_shear`` (N, capacity) vec3, m (tangential spring displacement, Mindlin 1949).
"""

from __future__ import annotations

from typing import Any

import warp as wp

from kernels.hertz import ContactParams, contact_force, rolling_torque
from kernels.integrate import SphereArrays, sphere_mass


@wp.struct
class ContactRows:
    """Per-particle contact rows (layout in the module docstring)."""

    partner: wp.array2d(dtype=wp.int32)
    """(N, capacity) partner index, -1 where empty; row i sorted ascending."""
    count: wp.array(dtype=wp.int32)
    """(N,) entries used in row i."""
    shear: wp.array2d(dtype=wp.vec3)
    """(N, capacity) Mindlin shear displacement of each contact, m."""


@wp.func
def with_bodies(base: ContactParams, radius_eff: float, mass_eff: float):
    """``base`` (material constants E*, G*, damping, friction of a material pair) with R* and m* set."""
    p = base
    p.radius_eff = radius_eff
    p.mass_eff = mass_eff
    return p


@wp.kernel
def flag_rebuild(
    spheres: SphereArrays,
    particle_x_at_build: wp.array[wp.vec3],
    half_skin: float,
    # outputs
    rebuild_flag: wp.array[wp.int32],
):
    """Set ``rebuild_flag[0] = 1`` when a particle moved more than skin/2 since the last build."""
    i = wp.tid()
    if spheres.alive[i] == 0:
        return
    if wp.length(spheres.x[i] - particle_x_at_build[i]) > half_skin:
        rebuild_flag[0] = 1  # every writer stores the same value: race-free in effect


@wp.kernel
def build_contact_list(
    grid: wp.uint64,
    spheres: SphereArrays,
    max_radius: float,
    skin: float,
    old: ContactRows,
    # outputs
    rows: ContactRows,
    particle_x_at_build: wp.array[wp.vec3],
    overflow: wp.array[wp.int32],
):
    """Row i: partners j with ``|x_i - x_j| < r_i + r_j + skin``, sorted by j; shear carried by partner id.

    ``overflow[0]`` receives the largest candidate count of a row that did not fit (integer atomic max).
    """
    i = wp.tid()
    particle_x = spheres.x
    particle_radius = spheres.radius
    particle_alive = spheres.alive
    contact_partner = rows.partner
    old_partner = old.partner
    capacity = contact_partner.shape[1]
    xi = particle_x[i]
    particle_x_at_build[i] = xi
    n = int(0)
    if particle_alive[i] != 0:
        ri = particle_radius[i]
        query = wp.hash_grid_query(grid, xi, ri + max_radius + skin)
        for j in query:
            if j != i and particle_alive[j] != 0:
                cut = ri + particle_radius[j] + skin
                if wp.length_sq(particle_x[j] - xi) < cut * cut:
                    # sorted insert by partner id; when full keep the smallest ids (deterministic)
                    k = int(-1)
                    if n < capacity:
                        k = n
                    elif contact_partner[i, capacity - 1] > j:
                        k = capacity - 1
                    if k >= 0:
                        while k > 0 and contact_partner[i, k - 1] > j:
                            contact_partner[i, k] = contact_partner[i, k - 1]
                            k = k - 1
                        contact_partner[i, k] = j
                    n = n + 1
    if n > capacity:
        wp.atomic_max(overflow, 0, n)
    m = wp.min(n, capacity)
    rows.count[i] = m
    for k in range(m, capacity):
        contact_partner[i, k] = -1
    # merge with the old row (both sorted by partner id) to carry the shear history
    old_n = old.count[i]
    o = int(0)
    for k in range(m):
        j = contact_partner[i, k]
        s = wp.vec3(0.0)
        while o < old_n and old_partner[i, o] < j:
            o = o + 1
        if o < old_n:
            if old_partner[i, o] == j:
                s = old.shear[i, o]
        rows.shear[i, k] = s


@wp.kernel
def contact_forces(
    spheres: SphereArrays,
    params: ContactParams,
    dt: float,
    # outputs (rows.shear is read and updated in place, row i by thread i only)
    rows: ContactRows,
    particle_f: wp.array[wp.vec3],
    particle_torque: wp.array[wp.vec3],
):
    """Sum of Hertz-Mindlin contact forces (N) and torques (N m) on particle i over its own row.

    ``params`` holds the material-pair constants (E*, G*, damping, friction); R* = r_i r_j/(r_i + r_j)
    and m* = m_i m_j/(m_i + m_j) are set per contact. Convention of ``kernels/hertz.py``: body 1 = i,
    normal ``n`` from i to j, contact point ``r_i n`` from the centre of i, relative contact velocity
    ``v_i - v_j + (r_i w_i + r_j w_j) x n``. A contact with zero or negative overlap exerts no force
    and loses its shear history.
    """
    i = wp.tid()
    particle_x = spheres.x
    particle_v = spheres.v
    particle_omega = spheres.omega
    particle_radius = spheres.radius
    particle_density = spheres.density
    contact_partner = rows.partner
    contact_shear = rows.shear
    xi = particle_x[i]
    vi = particle_v[i]
    wi = particle_omega[i]
    ri = particle_radius[i]
    mi = sphere_mass(ri, particle_density[i])
    f = wp.vec3(0.0)
    t = wp.vec3(0.0)
    for k in range(rows.count[i]):
        j = contact_partner[i, k]
        d = particle_x[j] - xi
        dist = wp.length(d)
        rj = particle_radius[j]
        overlap = ri + rj - dist
        if overlap > 0.0 and dist > 0.0:
            n = d / dist
            wj = particle_omega[j]
            v_rel = vi - particle_v[j] + wp.cross(ri * wi + rj * wj, n)
            mj = sphere_mass(rj, particle_density[j])
            p = with_bodies(params, ri * rj / (ri + rj), mi * mj / (mi + mj))
            fc, shear_new, fn = contact_force(n, overlap, v_rel, contact_shear[i, k], p, dt)
            contact_shear[i, k] = shear_new
            f = f + fc
            t = t + wp.cross(ri * n, fc)
            if p.rolling_friction > 0.0:
                t = t + rolling_torque(p, n, wi - wj, fn)
        else:
            contact_shear[i, k] = wp.vec3(0.0)
    particle_f[i] = f
    particle_torque[i] = t


@wp.func
def is_touching_partner(particle_x: wp.array[wp.vec3], particle_radius: wp.array[wp.float32], i: int, j: int):
    """True for a partner j > i that overlaps sphere i: |x_i - x_j| < r_i + r_j."""
    if j > i:
        return wp.length(particle_x[i] - particle_x[j]) < particle_radius[i] + particle_radius[j]
    return False


@wp.kernel
def count_touching_pairs(
    particle_x: wp.array[wp.vec3],
    particle_radius: wp.array[wp.float32],
    contact_partner: wp.array2d[wp.int32],
    contact_count: wp.array[wp.int32],
    # outputs
    pair_count: wp.array[wp.int32],
):
    """pair_count[i] = number of partners j > i with overlap > 0."""
    i = wp.tid()
    c = int(0)
    for k in range(contact_count[i]):
        if is_touching_partner(particle_x, particle_radius, i, contact_partner[i, k]):
            c = c + 1
    pair_count[i] = c


@wp.kernel
def fill_touching_pairs(
    particle_x: wp.array[wp.vec3],
    particle_radius: wp.array[wp.float32],
    contact_partner: wp.array2d[wp.int32],
    contact_count: wp.array[wp.int32],
    pair_offset: wp.array[wp.int32],
    # outputs
    pair_i: wp.array[wp.int32],
    pair_j: wp.array[wp.int32],
):
    """Write the touching pairs (i < j) of row i at ``pair_offset[i]`` (exclusive scan of the counts)."""
    i = wp.tid()
    c = pair_offset[i]
    for k in range(contact_count[i]):
        j = contact_partner[i, k]
        if is_touching_partner(particle_x, particle_radius, i, j):
            pair_i[c] = i
            pair_j[c] = j
            c = c + 1


@wp.kernel
def sorted_order(
    grid: wp.uint64,
    # outputs
    new_to_old: wp.array[wp.int32],
    old_to_new: wp.array[wp.int32],
):
    """Permutation that lists particles in hash-grid cell order."""
    k = wp.tid()
    old = wp.hash_grid_point_id(grid, k)
    new_to_old[k] = old
    old_to_new[old] = k


@wp.kernel
def gather(src: wp.array(dtype=Any), new_to_old: wp.array[wp.int32],
           # outputs
           dst: wp.array(dtype=Any)):
    """dst[k] = src[new_to_old[k]]: one per-particle array in the new order."""
    k = wp.tid()
    dst[k] = src[new_to_old[k]]


_GATHER = {dtype: wp.overload(gather, [wp.array(dtype=dtype), wp.array(dtype=wp.int32), wp.array(dtype=dtype)])
           for dtype in (wp.vec3, wp.float32, wp.int32, wp.vec3d, wp.float64)}


@wp.kernel
def gather_rows_vec3(src: wp.array2d[wp.vec3], new_to_old: wp.array[wp.int32], dst: wp.array2d[wp.vec3]):
    k = wp.tid()
    for c in range(src.shape[1]):
        dst[k, c] = src[new_to_old[k], c]


@wp.kernel
def gather_contact_rows(
    src_partner: wp.array2d[wp.int32],
    src_count: wp.array[wp.int32],
    src_shear: wp.array2d[wp.vec3],
    new_to_old: wp.array[wp.int32],
    old_to_new: wp.array[wp.int32],
    # outputs
    dst_partner: wp.array2d[wp.int32],
    dst_count: wp.array[wp.int32],
    dst_shear: wp.array2d[wp.vec3],
):
    """Move contact rows to the new particle order and renumber partners, keeping rows sorted by id."""
    k = wp.tid()
    old = new_to_old[k]
    m = src_count[old]
    dst_count[k] = m
    capacity = dst_partner.shape[1]
    for c in range(m):
        j = old_to_new[src_partner[old, c]]
        s = src_shear[old, c]
        p = c
        while p > 0 and dst_partner[k, p - 1] > j:
            dst_partner[k, p] = dst_partner[k, p - 1]
            dst_shear[k, p] = dst_shear[k, p - 1]
            p = p - 1
        dst_partner[k, p] = j
        dst_shear[k, p] = s
    for c in range(m, capacity):
        dst_partner[k, c] = -1


@wp.kernel
def count_rebuild(counter: wp.array[wp.int32]):
    counter[0] = counter[0] + 1


# ---------------------------------------------------------------------------------------------
# launch wrappers


def launch_gather(src, new_to_old, dst) -> None:
    """``dst[k] = src[new_to_old[k]]`` for a per-particle vec3, float32, int32, vec3d or float64 array."""
    wp.launch(_GATHER[src.dtype], dim=src.shape[0], device=src.device, inputs=[src, new_to_old], outputs=[dst])


def launch_count_rebuild(counter) -> None:
    wp.launch(count_rebuild, dim=1, device=counter.device, inputs=[counter])


def launch_flag_rebuild(spheres: SphereArrays, x_at_build, half_skin: float, rebuild_flag) -> None:
    wp.launch(flag_rebuild, dim=spheres.x.shape[0], device=spheres.x.device,
              inputs=[spheres, x_at_build, half_skin], outputs=[rebuild_flag])


def launch_build_contact_list(grid, spheres: SphereArrays, max_radius: float, skin: float, old: ContactRows,
                              rows: ContactRows, x_at_build, overflow) -> None:
    """Rebuild ``rows`` from ``old`` (their previous contents; shear carried by partner id)."""
    wp.launch(build_contact_list, dim=spheres.x.shape[0], device=spheres.x.device,
              inputs=[grid.id, spheres, max_radius, skin, old], outputs=[rows, x_at_build, overflow])


def launch_contact_forces(spheres: SphereArrays, rows: ContactRows, params: ContactParams, dt: float,
                          force, torque) -> None:
    wp.launch(contact_forces, dim=spheres.x.shape[0], device=spheres.x.device,
              inputs=[spheres, params, dt], outputs=[rows, force, torque])

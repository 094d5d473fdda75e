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
- Contact onsets (:func:`record_onset`): each row entry carries a ``touching`` flag (overlap > 0 at the
  last force evaluation), carried through rebuilds and sorts by partner id like the shear. A contact
  whose flag was 0 and whose overlap is now > 0 is a new contact (an onset, i.e. one real collision): the
  owner thread (i < j) counts it per stream pair with an integer atomic and records its impact speed, the
  normal approach speed ``(v_i - v_j) . n`` at the velocities of that evaluation (velocity Verlet's half
  step: the pre-impact velocity, no contact force acted on the pair before). A contact that persists,
  across list rebuilds too, is not counted again; a pair that bounces apart and touches again is.
- Triply periodic box (:class:`PeriodicBox`, origin 0, lengths L): candidates and contacts use the
  minimum-image separation ``d - L round(d / L)`` (per axis; Allen & Tildesley, *Computer Simulation of
  Liquids*, 1987, sec. 1.5.2; unique while the cut-off is below L/2). The hash grid is built on positions
  wrapped into [0, L) and scaled to ``n_a / L_a`` cells per metre (cell width 1, ``n_a`` cells along
  axis a): ``wp.HashGrid`` hashes a cell (cx, cy, cz) modulo its dims (``warp/native/hashgrid.h``,
  ``hash_grid_index``), so with dims = n the grid is exactly periodic and a query near a face visits the
  cells at the opposite face. Needs ``n_a >= 3`` (each cell at least the search size 2 r_max + skin), so
  a query spans at most 3 cells per axis and never meets the same partner twice (checked on the host).
  Open space is the same kernels with ``periodic = 0``, unit scale (a uniform branch).
- A compact pair list (i < j, touching only) for collision-rate and statistics kernels.
- A spatial sort (gather by hash-grid cell order) that keeps neighbours close in memory.

Layout (:class:`ContactRows`): flat arrays of N * capacity entries, ``partner`` int32, ``shear`` vec3, m
(tangential spring displacement, Mindlin 1949), ``touching`` int32 (1 while the contact is closed: onset
bookkeeping); row i is the ``count[i]`` entries from ``start[i]``, sorted by partner. Two layouts of the same
arrays:

- *padded* (every device): ``start[i] = i * capacity``, -1 in the unused partner slots; the host reads the
  rows as (N, capacity) arrays (``hel_warp.collisions.dem.ContactList``);
- *packed* (``build_contact_list`` with ``packed = 1``; a device that runs threads in ``tid`` order, the
  CPU): row i follows row i - 1 (``start[i] = start[i-1] + count[i-1]``), so the entries in use are one
  contiguous stream. A sparse list (a falling bed: 0.4 entries per sphere in the half list) then costs
  one sequential read instead of three scattered cache lines per non-empty row (measured on the 1e5 falling
  bed: the rows' reads 46 -> 12 ns per sphere and step).
"""

from __future__ import annotations

from typing import Any

import warp as wp

from kernels.hertz import ContactParams, contact_force, rolling_torque
from kernels.integrate import SphereArrays, sphere_mass


@wp.struct
class ContactRows:
    """Per-particle contact rows (layout in the module docstring): entry k of row i is at ``start[i] + k``."""

    partner: wp.array(dtype=wp.int32)
    """(N * capacity,) partner index; row i sorted ascending (padded layout: -1 where empty)."""
    count: wp.array(dtype=wp.int32)
    """(N,) entries used in row i."""
    start: wp.array(dtype=wp.int32)
    """(N,) flat index of the first entry of row i (padded: i * capacity; packed: the rows back to back)."""
    shear: wp.array(dtype=wp.vec3)
    """(N * capacity,) Mindlin shear displacement of each contact, m."""
    touching: wp.array(dtype=wp.int32)
    """(N * capacity,) 1 where the contact had overlap > 0 at the last force evaluation, else 0."""
    capacity: int
    """Entries a row may hold."""


@wp.struct
class PeriodicBox:
    """Open space (``periodic = 0``) or a triply periodic box [0, L_x) x [0, L_y) x [0, L_z)."""

    periodic: int
    """1: minimum-image separations and a periodic hash grid; 0: open space (the other fields unused)."""
    length: wp.vec3
    """Box lengths L, m."""
    grid_scale: wp.vec3
    """Hash-grid coordinates per metre along each axis (n_a / L_a; (1, 1, 1) in open space)."""
    radius_scale: float
    """Query radius scale, max_a n_a / L_a (1 in open space), 1/m."""


@wp.struct
class ContactOnsets:
    """Onset counters of the contact-force kernel (see the module docstring); integer atomics only."""

    counting: int
    """1: count onsets; 0: only update the touching flags (the force evaluation before the first step)."""
    stream: wp.array(dtype=wp.int32)
    """(N,) stream tag per particle slot."""
    particle_id: wp.array(dtype=wp.int32)
    """(N,) particle id per slot (what the event list records)."""
    n_streams: int
    """Stream tags counted separately; tags outside [0, n_streams) count as the nearest end."""
    pair_onsets: wp.array(dtype=wp.int32)
    """(n_streams^2,) onsets per stream pair, row-major (min tag, max tag)."""
    speed_sum: wp.array(dtype=wp.float64)
    """(N,) sum of the impact speeds of the onsets owned by slot i (i < j), m/s; written by thread i only."""
    substep: wp.array(dtype=wp.int32)
    """(1,) index of the current sub-step (written into the events)."""
    event_capacity: int
    """Entries of the event arrays (0: no events recorded)."""
    event_count: wp.array(dtype=wp.int32)
    """(1,) onsets offered to the event list (may exceed event_capacity: the rest were not stored)."""
    event_a: wp.array(dtype=wp.int32)
    """(event_capacity,) smaller particle id of each onset."""
    event_b: wp.array(dtype=wp.int32)
    """(event_capacity,) larger particle id."""
    event_speed: wp.array(dtype=wp.float32)
    """(event_capacity,) impact speed (normal approach speed at onset), m/s."""
    event_substep: wp.array(dtype=wp.int32)
    """(event_capacity,) sub-step of the onset."""
    event_pair: wp.array(dtype=wp.int32)
    """(event_capacity,) stream-pair slot of the onset (row-major (min tag, max tag), as ``pair_onsets``)."""


@wp.func
def minimum_image(box: PeriodicBox, d: wp.vec3):
    """d - L round(d / L) per axis in a periodic box (the nearest image of the separation); d in open space."""
    if box.periodic == 0:
        return d
    length = box.length
    return wp.vec3(d[0] - length[0] * wp.round(d[0] / length[0]),
                   d[1] - length[1] * wp.round(d[1] / length[1]),
                   d[2] - length[2] * wp.round(d[2] / length[2]))


@wp.func
def stream_pair_slot(s_i: wp.int32, s_j: wp.int32, n_streams: wp.int32):
    """Row-major index of the unordered stream pair (min, max), tags clamped to [0, n_streams)."""
    a = wp.clamp(wp.min(s_i, s_j), 0, n_streams - 1)
    b = wp.clamp(wp.max(s_i, s_j), 0, n_streams - 1)
    return a * n_streams + b


@wp.func
def record_onset(onsets: ContactOnsets, i: int, j: int, impact_speed: float):
    """Count the new contact (i, j), i < j, under its stream pair; add its impact speed; store the event."""
    pair = stream_pair_slot(onsets.stream[i], onsets.stream[j], onsets.n_streams)
    wp.atomic_add(onsets.pair_onsets, pair, 1)
    onsets.speed_sum[i] = onsets.speed_sum[i] + wp.float64(impact_speed)
    if onsets.event_capacity > 0:
        slot = wp.atomic_add(onsets.event_count, 0, 1)
        if slot < onsets.event_capacity:
            a = onsets.particle_id[i]
            b = onsets.particle_id[j]
            onsets.event_a[slot] = wp.min(a, b)
            onsets.event_b[slot] = wp.max(a, b)
            onsets.event_speed[slot] = impact_speed
            onsets.event_substep[slot] = onsets.substep[0]
            onsets.event_pair[slot] = pair


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
def wrap_into_box(
    box: PeriodicBox,
    # outputs
    particle_x: wp.array[wp.vec3],
    particle_x_grid: wp.array[wp.vec3],
):
    """Periodic box: x <- x - L floor(x / L) in [0, L) (a result equal to L in float32 becomes 0), and the
    hash-grid coordinates ``x * grid_scale``."""
    i = wp.tid()
    x = particle_x[i]
    length = box.length
    w = wp.vec3(0.0)
    for a in range(3):
        c = x[a] - length[a] * wp.floor(x[a] / length[a])
        if c >= length[a] or c < 0.0:
            c = 0.0
        w[a] = c
    particle_x[i] = w
    particle_x_grid[i] = wp.cw_mul(w, box.grid_scale)


@wp.kernel
def build_contact_list(
    grid: wp.uint64,
    spheres: SphereArrays,
    max_radius: float,
    skin: float,
    box: PeriodicBox,
    old: ContactRows,
    half: int,
    packed: int,
    # outputs
    rows: ContactRows,
    particle_x_at_build: wp.array[wp.vec3],
    overflow: wp.array[wp.int32],
):
    """Row i: partners j with ``|x_i - x_j| < r_i + r_j + skin`` (minimum image in a periodic box), sorted by j;
    shear and touching flag carried by partner id. The grid holds ``x * box.grid_scale`` (x itself in open space).

    ``half = 1``: a half list, row i keeps only the partners j > i (``kernels/dem_step.py``); a pair's history
    not found in the old row i is looked up in the old row j (an owner changed by a spatial sort) with the
    shear's sign reversed (the owner's frame). ``overflow[0]`` receives the largest candidate count of a row
    that did not fit (integer atomic max); in a half list too it counts every candidate, j < i included, so a
    capacity that works on one device works on the other.

    ``packed = 1``: the packed layout (module docstring), row i written right after row i - 1: threads must run
    in ``tid`` order (the CPU device). Row i's start is at most ``i * capacity``, so its slots never reach
    past the padded row's end. ``old`` may be in either layout.
    """
    i = wp.tid()
    particle_x = spheres.x
    particle_radius = spheres.radius
    particle_alive = spheres.alive
    contact_partner = rows.partner
    old_partner = old.partner
    capacity = rows.capacity
    base = i * capacity
    if packed != 0 and i > 0:
        base = rows.start[i - 1] + rows.count[i - 1]
    rows.start[i] = base
    xi = particle_x[i]
    particle_x_at_build[i] = xi
    n = int(0)
    candidates = int(0)
    if particle_alive[i] != 0:
        ri = particle_radius[i]
        query = wp.hash_grid_query(grid, wp.cw_mul(xi, box.grid_scale), (ri + max_radius + skin) * box.radius_scale)
        for j in query:
            if j != i and particle_alive[j] != 0:
                cut = ri + particle_radius[j] + skin
                if wp.length_sq(minimum_image(box, particle_x[j] - xi)) < cut * cut:
                    candidates = candidates + 1
                    if half == 0 or j > i:
                        # sorted insert by partner id; when full keep the smallest ids (deterministic)
                        k = int(-1)
                        if n < capacity:
                            k = n
                        elif contact_partner[base + capacity - 1] > j:
                            k = capacity - 1
                        if k >= 0:
                            while k > 0 and contact_partner[base + k - 1] > j:
                                contact_partner[base + k] = contact_partner[base + k - 1]
                                k = k - 1
                            contact_partner[base + k] = j
                        n = n + 1
    if candidates > capacity:
        wp.atomic_max(overflow, 0, candidates)
    m = wp.min(n, capacity)
    rows.count[i] = m
    if packed == 0:
        for k in range(m, capacity):
            contact_partner[base + k] = -1
    # merge with the old row (both sorted by partner id) to carry the shear history and touching flag
    old_n = old.count[i]
    old_base = old.start[i]
    o = int(0)
    for k in range(m):
        j = contact_partner[base + k]
        s = wp.vec3(0.0)
        touching = int(0)
        while o < old_n and old_partner[old_base + o] < j:
            o = o + 1
        found = int(0)
        if o < old_n:
            if old_partner[old_base + o] == j:
                s = old.shear[old_base + o]
                touching = old.touching[old_base + o]
                found = 1
        if half != 0 and found == 0:
            j_base = old.start[j]
            for q in range(old.count[j]):
                if old_partner[j_base + q] == i:
                    s = -old.shear[j_base + q]
                    touching = old.touching[j_base + q]
        rows.shear[base + k] = s
        rows.touching[base + k] = touching


@wp.kernel
def contact_forces(
    spheres: SphereArrays,
    params: ContactParams,
    box: PeriodicBox,
    dt: float,
    # outputs (rows.shear and rows.touching are read and updated in place, row i by thread i only)
    onsets: ContactOnsets,
    rows: ContactRows,
    particle_f: wp.array[wp.vec3],
    particle_torque: wp.array[wp.vec3],
):
    """Sum of Hertz-Mindlin contact forces (N) and torques (N m) on particle i over its own row.

    ``params`` holds the material-pair constants (E*, G*, damping, friction); R* = r_i r_j/(r_i + r_j)
    and m* = m_i m_j/(m_i + m_j) are set per contact. Convention of ``kernels/hertz.py``: body 1 = i,
    normal ``n`` from i to j, contact point ``r_i n`` from the centre of i, relative contact velocity
    ``v_i - v_j + (r_i w_i + r_j w_j) x n``, separation ``x_j - x_i`` (minimum image in a periodic box). A
    contact with zero or negative overlap exerts no force and loses its shear history. A contact closing
    now (touching flag 0, overlap > 0) is an onset: thread i < j records it in ``onsets`` (module docstring).
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
    base = rows.start[i]
    for k in range(rows.count[i]):
        e = base + k
        j = contact_partner[e]
        d = minimum_image(box, particle_x[j] - xi)
        dist = wp.length(d)
        rj = particle_radius[j]
        overlap = ri + rj - dist
        if overlap > 0.0 and dist > 0.0:
            n = d / dist
            wj = particle_omega[j]
            vj = particle_v[j]
            if rows.touching[e] == 0:
                rows.touching[e] = 1
                if onsets.counting != 0 and i < j:
                    record_onset(onsets, i, j, wp.dot(vi - vj, n))
            v_rel = vi - vj + wp.cross(ri * wi + rj * wj, n)
            mj = sphere_mass(rj, particle_density[j])
            p = with_bodies(params, ri * rj / (ri + rj), mi * mj / (mi + mj))
            fc, shear_new, fn = contact_force(n, overlap, v_rel, contact_shear[e], p, dt)
            contact_shear[e] = shear_new
            f = f + fc
            t = t + wp.cross(ri * n, fc)
            if p.rolling_friction > 0.0:
                t = t + rolling_torque(p, n, wi - wj, fn)
        else:
            contact_shear[e] = wp.vec3(0.0)
            if rows.touching[e] != 0:
                rows.touching[e] = 0
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
    rows: ContactRows,
    # outputs
    pair_count: wp.array[wp.int32],
):
    """pair_count[i] = number of partners j > i with overlap > 0."""
    i = wp.tid()
    c = int(0)
    base = rows.start[i]
    for k in range(rows.count[i]):
        if is_touching_partner(particle_x, particle_radius, i, rows.partner[base + k]):
            c = c + 1
    pair_count[i] = c


@wp.kernel
def fill_touching_pairs(
    particle_x: wp.array[wp.vec3],
    particle_radius: wp.array[wp.float32],
    rows: ContactRows,
    pair_offset: wp.array[wp.int32],
    # outputs
    pair_i: wp.array[wp.int32],
    pair_j: wp.array[wp.int32],
):
    """Write the touching pairs (i < j) of row i at ``pair_offset[i]`` (exclusive scan of the counts)."""
    i = wp.tid()
    c = pair_offset[i]
    base = rows.start[i]
    for k in range(rows.count[i]):
        j = rows.partner[base + k]
        if is_touching_partner(particle_x, particle_radius, i, j):
            pair_i[c] = i
            pair_j[c] = j
            c = c + 1


@wp.kernel
def count_touching_stream_pairs(
    spheres: SphereArrays,
    box: PeriodicBox,
    rows: ContactRows,
    particle_stream: wp.array[wp.int32],
    n_streams: int,
    # outputs
    touching: wp.array[wp.int32],
):
    """Pairs i < j of the rows with ``|x_i - x_j| < r_i + r_j`` now (minimum image), per stream pair
    (row-major (min tag, max tag)); integer atomics."""
    i = wp.tid()
    if spheres.alive[i] == 0:
        return
    xi = spheres.x[i]
    ri = spheres.radius[i]
    base = rows.start[i]
    for k in range(rows.count[i]):
        j = rows.partner[base + k]
        if j > i:
            if wp.length(minimum_image(box, spheres.x[j] - xi)) < ri + spheres.radius[j]:
                wp.atomic_add(touching, stream_pair_slot(particle_stream[i], particle_stream[j], n_streams), 1)


@wp.kernel
def advance_substep(counter: wp.array[wp.int32]):
    counter[0] = counter[0] + 1


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
    src: ContactRows,
    new_to_old: wp.array[wp.int32],
    old_to_new: wp.array[wp.int32],
    # outputs
    dst: ContactRows,
):
    """Move contact rows (shear, touching flag) to the new particle order and renumber partners, keeping
    rows sorted by id. ``src`` in either layout; ``dst`` is written padded (``start[k] = k * capacity``)."""
    k = wp.tid()
    old = new_to_old[k]
    m = src.count[old]
    src_base = src.start[old]
    capacity = dst.capacity
    base = k * capacity
    dst.start[k] = base
    dst.count[k] = m
    for c in range(m):
        j = old_to_new[src.partner[src_base + c]]
        s = src.shear[src_base + c]
        touching = src.touching[src_base + c]
        p = c
        while p > 0 and dst.partner[base + p - 1] > j:
            dst.partner[base + p] = dst.partner[base + p - 1]
            dst.shear[base + p] = dst.shear[base + p - 1]
            dst.touching[base + p] = dst.touching[base + p - 1]
            p = p - 1
        dst.partner[base + p] = j
        dst.shear[base + p] = s
        dst.touching[base + p] = touching
    for c in range(m, capacity):
        dst.partner[base + c] = -1


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


def open_space() -> PeriodicBox:
    """The ``PeriodicBox`` of open space (no periodic faces, the grid built on the positions themselves)."""
    box = PeriodicBox()
    box.periodic = 0
    box.length = wp.vec3(1.0, 1.0, 1.0)
    box.grid_scale = wp.vec3(1.0, 1.0, 1.0)
    box.radius_scale = 1.0
    return box


def periodic_box(length, cells) -> PeriodicBox:
    """The ``PeriodicBox`` [0, L) with ``cells`` (n_x, n_y, n_z) hash-grid cells (grid cell width 1)."""
    box = PeriodicBox()
    box.periodic = 1
    box.length = wp.vec3(*[float(v) for v in length])
    scale = [float(n) / float(v) for n, v in zip(cells, length)]
    box.grid_scale = wp.vec3(*scale)
    box.radius_scale = max(scale)
    return box


def no_onsets() -> ContactOnsets:
    """A ``ContactOnsets`` that counts nothing (``counting = 0``; its arrays are never touched)."""
    onsets = ContactOnsets()
    onsets.counting = 0
    onsets.n_streams = 1
    onsets.event_capacity = 0
    return onsets


def launch_wrap_into_box(box: PeriodicBox, x, x_grid) -> None:
    """Periodic box: wrap ``x`` into [0, L) in place and write the hash-grid coordinates to ``x_grid``."""
    wp.launch(wrap_into_box, dim=x.shape[0], device=x.device, inputs=[box], outputs=[x, x_grid])


def launch_build_contact_list(grid, spheres: SphereArrays, max_radius: float, skin: float, old: ContactRows,
                              rows: ContactRows, x_at_build, overflow, box: PeriodicBox | None = None,
                              half: bool = False, packed: bool = False) -> None:
    """Rebuild ``rows`` from ``old`` (their previous contents; shear and touching flag carried by partner id).

    ``grid`` holds ``x * box.grid_scale`` (``launch_wrap_into_box`` first in a periodic box); ``box`` None
    is open space; ``half``: keep only partners j > i (``kernels/dem_step.py``); ``packed``: the packed
    layout (module docstring; CPU device only)."""
    if packed and spheres.x.device.is_cuda:
        raise ValueError("the packed contact layout is built by threads in tid order: CPU device only")
    wp.launch(build_contact_list, dim=spheres.x.shape[0], device=spheres.x.device,
              inputs=[grid.id, spheres, max_radius, skin, box if box is not None else open_space(), old, int(half),
                      int(packed)],
              outputs=[rows, x_at_build, overflow])


def launch_contact_forces(spheres: SphereArrays, rows: ContactRows, params: ContactParams, dt: float,
                          force, torque, *, box: PeriodicBox | None = None,
                          onsets: ContactOnsets | None = None) -> None:
    """Hertz-Mindlin contact forces and torques over the rows (``contact_forces``); onsets counted into
    ``onsets`` when given with ``counting = 1``."""
    wp.launch(contact_forces, dim=spheres.x.shape[0], device=spheres.x.device,
              inputs=[spheres, params, box if box is not None else open_space(), dt],
              outputs=[onsets if onsets is not None else no_onsets(), rows, force, torque])


def launch_gather_contact_rows(src: ContactRows, new_to_old, old_to_new, dst: ContactRows) -> None:
    """``dst`` = the rows of ``src`` in the new particle order (``gather_contact_rows``)."""
    wp.launch(gather_contact_rows, dim=src.count.shape[0], device=src.count.device,
              inputs=[src, new_to_old, old_to_new], outputs=[dst])


def launch_count_touching_stream_pairs(spheres: SphereArrays, rows: ContactRows, particle_stream, n_streams: int,
                                       touching, box: PeriodicBox | None = None) -> None:
    """Add the touching pairs of the rows (i < j) to ``touching`` (n_streams^2 int32, row-major)."""
    wp.launch(count_touching_stream_pairs, dim=spheres.x.shape[0], device=spheres.x.device,
              inputs=[spheres, box if box is not None else open_space(), rows, particle_stream, int(n_streams)],
              outputs=[touching])


def launch_advance_substep(counter) -> None:
    """``counter[0] += 1`` (the sub-step index written into onset events)."""
    wp.launch(advance_substep, dim=1, device=counter.device, inputs=[counter])

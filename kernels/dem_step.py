"""The N-body DEM step on one CPU thread: a half contact list, one fused pass per step.

Same equations as the general path (``kernels/contacts.py`` contact rows and forces, ``kernels/walls.py``
plane walls, ``kernels/integrate.py`` velocity Verlet; Hertz-Mindlin law of ``kernels/hertz.py``); what
differs is how the work is arranged, for a device that runs a kernel's threads one after the other in
``tid`` order (Warp's CPU device: one serial loop over the launch):

- **Half list** (``build_contact_list`` with ``half = 1``): row i holds only the partners j > i, so each
  pair is computed once (LAMMPS/LIGGGHTS ``newton on`` for pairs). Thread i adds the pair force to
  itself and subtracts it from j (plain stores: no other thread runs meanwhile). The law is odd under
  the exchange of the bodies to the last bit (``n``, ``v_rel`` and the shear change sign, the overlap
  does not; every operation of ``contact_force`` is sign-symmetric, FMA included), and thread j starts
  from the contributions of the partners j' < j in increasing j', then adds its own row in increasing
  j: the sums of the full list, in the full list's order. Forces and torques are bit-identical to the
  full-list kernels (tested in tests/test_dem.py).
- **One pass per step** instead of five launches: ``forces_kick`` (contacts, plane walls, second half
  kick, then the next step's half kick, drift, rebuild check against skin/2 and zeroed force
  accumulators: ``kick_drift_flag``, also a kernel of its own for the first step). Particle i's force
  is complete when thread i starts (every j < i has run) and its own row is done, so its kick follows
  at once; and no later thread reads x_i (their rows hold partners j' > j > i only), so i may move on
  to the next step before the others. The list check then runs between the passes.
- **Packed rows** (``build_contact_list`` with ``packed = 1``): row i starts where row i - 1 ends, so the
  pass reads the entries in use as one stream (a sparse list's rows are otherwise scattered cache lines).
- **Wall list**: at each list build ``mark_near_walls`` flags the walls within r + skin of a particle
  (LIGGGHTS keeps a neighbour list for its walls too); the others cannot be reached before the next
  build and are not tested.

The shear history of a pair lives in its owner's row (i < j) in the owner's frame; on a spatial sort
the owner can change, and the rebuild then finds the history in the partner's row with its sign
reversed (``build_contact_list``). On CUDA threads run concurrently: the solver keeps the full list and
the separate kernels there (``hel_warp/collisions/dem.py``).
"""

from __future__ import annotations

import warp as wp

from kernels.contacts import ContactOnsets, ContactRows, PeriodicBox, minimum_image, record_onset, with_bodies
from kernels.hertz import ContactParams, contact_force, rolling_torque
from kernels.integrate import SphereArrays, half_kick, sphere_mass
from kernels.walls import wall_contact


@wp.struct
class PlaneWalls:
    """The plane walls of the box (inward normals) and their per-particle shear history."""

    point: wp.array(dtype=wp.vec3)
    """(n_walls,) a point of each wall plane, m."""
    normal: wp.array(dtype=wp.vec3)
    """(n_walls,) unit normal pointing into the domain."""
    count: int
    """Walls in use (0: none; the arrays then hold one unused entry)."""
    params: ContactParams
    """Contact constants of the sphere-wall material pair (R*, m* set per contact)."""
    shear: wp.array2d(dtype=wp.vec3)
    """(N, n_walls) Mindlin shear displacement per particle and wall, m; updated in place."""
    near: wp.array(dtype=wp.int32)
    """(N,) bit w set when wall w was within r + skin of the particle at the last list build
    (``mark_near_walls``): only those walls are tested until the next build."""


@wp.func
def kick_drift_flag_one(
    i: int,
    gravity: wp.vec3,
    dt: float,
    particle_x_at_build: wp.array[wp.vec3],
    half_skin: float,
    spheres: SphereArrays,
    particle_f: wp.array[wp.vec3],
    particle_torque: wp.array[wp.vec3],
    rebuild_flag: wp.array[wp.int32],
):
    """Particle i of ``kick_drift_flag``."""
    f = particle_f[i]
    t = particle_torque[i]
    particle_f[i] = wp.vec3(0.0)
    particle_torque[i] = wp.vec3(0.0)
    if spheres.alive[i] != 0:
        v = half_kick(spheres, i, f, t, gravity, dt)
        x = spheres.x[i] + v * dt
        spheres.x[i] = x
        if wp.length(x - particle_x_at_build[i]) > half_skin:
            rebuild_flag[0] = 1


@wp.kernel
def kick_drift_flag(
    gravity: wp.vec3,
    dt: float,
    particle_x_at_build: wp.array[wp.vec3],
    half_skin: float,
    block: int,
    # outputs (x, v, omega updated in place; force and torque read, then zeroed for the next accumulation)
    spheres: SphereArrays,
    particle_f: wp.array[wp.vec3],
    particle_torque: wp.array[wp.vec3],
    rebuild_flag: wp.array[wp.int32],
):
    """Half kick with the forces of the current positions, full drift, then ``rebuild_flag[0] = 1`` if a
    particle moved more than skin/2 since the last list build (``kernels/contacts.flag_rebuild``).
    Thread b runs particles ``[b block, (b + 1) block)`` in order."""
    b = wp.tid()
    for i in range(b * block, wp.min(spheres.x.shape[0], (b + 1) * block)):
        kick_drift_flag_one(i, gravity, dt, particle_x_at_build, half_skin, spheres, particle_f, particle_torque,
                            rebuild_flag)


@wp.func
def forces_kick_one(
    i: int,
    spheres: SphereArrays,
    params: ContactParams,
    box: PeriodicBox,
    walls: PlaneWalls,
    gravity: wp.vec3,
    dt: float,
    kick: int,
    drift: int,
    particle_x_at_build: wp.array[wp.vec3],
    half_skin: float,
    onsets: ContactOnsets,
    rows: ContactRows,
    particle_f: wp.array[wp.vec3],
    particle_torque: wp.array[wp.vec3],
    rebuild_flag: wp.array[wp.int32],
):
    """Particle i of ``forces_kick``."""
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
    f = particle_f[i]  # the pairs (j', i), j' < i, whose threads ran before this one
    t = particle_torque[i]
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
                if onsets.counting != 0:
                    record_onset(onsets, i, j, wp.dot(vi - vj, n))
            v_rel = vi - vj + wp.cross(ri * wi + rj * wj, n)
            mj = sphere_mass(rj, particle_density[j])
            p = with_bodies(params, ri * rj / (ri + rj), mi * mj / (mi + mj))
            fc, shear_new, fn = contact_force(n, overlap, v_rel, contact_shear[e], p, dt)
            contact_shear[e] = shear_new
            f = f + fc
            t = t + wp.cross(ri * n, fc)
            particle_f[j] = particle_f[j] - fc
            particle_torque[j] = particle_torque[j] + wp.cross(rj * n, fc)
            if p.rolling_friction > 0.0:
                roll = rolling_torque(p, n, wi - wj, fn)
                t = t + roll
                particle_torque[j] = particle_torque[j] - roll
        else:
            contact_shear[e] = wp.vec3(0.0)
            if rows.touching[e] != 0:
                rows.touching[e] = 0
    near = walls.near[i]
    if spheres.alive[i] != 0 and near != 0:
        fw = wp.vec3(0.0)
        tw = wp.vec3(0.0)
        touching = int(0)
        for w in range(walls.count):
            if (near >> w) & 1 != 0:
                normal = walls.normal[w]
                gap = wp.dot(xi - walls.point[w], normal)
                if gap < ri:
                    result = wall_contact(normal, gap, ri, mi, vi, wi, walls.shear[i, w], walls.params, dt)
                    fw = fw + result[0]
                    walls.shear[i, w] = result[1]
                    tw = tw + result[2]
                    touching = 1
                else:
                    walls.shear[i, w] = wp.vec3(0.0)
        if touching != 0:
            f = f + fw
            t = t + tw
    if drift != 0:  # the next step's first pass for i (no later thread reads x_i: rows hold j > i only)
        particle_f[i] = wp.vec3(0.0)
        particle_torque[i] = wp.vec3(0.0)
        if spheres.alive[i] != 0:
            # half_kick twice from the same F and T (its arithmetic, from what thread i holds), then the drift
            half_dt = 0.5 * dt
            dv = (f / mi + gravity) * half_dt
            dw = t * (half_dt / (0.4 * mi * ri * ri))
            v = (vi + dv) + dv
            spheres.v[i] = v
            spheres.omega[i] = (wi + dw) + dw
            x = xi + v * dt
            spheres.x[i] = x
            if wp.length(x - particle_x_at_build[i]) > half_skin:
                rebuild_flag[0] = 1
    else:
        if kick != 0 and spheres.alive[i] != 0:
            half_kick(spheres, i, f, t, gravity, dt)
        particle_f[i] = f
        particle_torque[i] = t


@wp.kernel
def forces_kick(
    spheres: SphereArrays,
    params: ContactParams,
    box: PeriodicBox,
    walls: PlaneWalls,
    gravity: wp.vec3,
    dt: float,
    kick: int,
    drift: int,
    particle_x_at_build: wp.array[wp.vec3],
    half_skin: float,
    block: int,
    # outputs (rows.shear/touching, walls.shear updated in place; force and torque accumulated)
    onsets: ContactOnsets,
    rows: ContactRows,
    particle_f: wp.array[wp.vec3],
    particle_torque: wp.array[wp.vec3],
    rebuild_flag: wp.array[wp.int32],
):
    """Contact forces over the half row of i (added to i, subtracted from j > i), plane walls, then with
    ``kick = 1`` the second half kick of i. Needs zeroed accumulators and threads run in ``tid`` order; thread b runs particles
    ``[b block, (b + 1) block)`` in order (a block per task: Warp's CPU launch has a per-task cost of
    ~25 ns, measured, as much as the rest of a particle's work when it has no contacts).

    Convention of ``kernels/contacts.contact_forces``: body 1 = i, normal from i to j, relative contact
    velocity ``v_i - v_j + (r_i w_i + r_j w_j) x n``; j receives ``-F`` and the torque
    ``r_j n x F`` (its lever arm ``-r_j n`` times ``-F``), minus the rolling torque.
    """
    b = wp.tid()
    for i in range(b * block, wp.min(spheres.x.shape[0], (b + 1) * block)):
        forces_kick_one(i, spheres, params, box, walls, gravity, dt, kick, drift, particle_x_at_build, half_skin,
                        onsets, rows, particle_f, particle_torque, rebuild_flag)


@wp.kernel
def mark_near_walls(
    spheres: SphereArrays,
    margin: float,
    # outputs (walls.near written, walls.shear zeroed where a wall is out of reach)
    walls: PlaneWalls,
):
    """At a list build: bit w of ``walls.near[i]`` when the gap to wall w is below r + margin (margin = the
    skin). Until the next build a particle moves at most skin/2, so a wall out of the mask stays out of
    contact: its shear is zeroed here, as the next force evaluation would have done."""
    i = wp.tid()
    x = spheres.x[i]
    reach = spheres.radius[i] + margin
    mask = int(0)
    for w in range(walls.count):
        if wp.dot(x - walls.point[w], walls.normal[w]) < reach:
            mask = mask | (1 << w)
        else:
            walls.shear[i, w] = wp.vec3(0.0)
    walls.near[i] = mask


# ---------------------------------------------------------------------------------------------
# launch wrappers

CPU_BLOCK = 64
"""Particles per task of the fused passes (16-128 measured alike; 1 pays the per-task cost each particle)."""


def plane_walls(point, normal, count: int, params: ContactParams, shear, near) -> PlaneWalls:
    """The ``PlaneWalls`` view of the wall arrays (built once; the arrays are updated in place)."""
    walls = PlaneWalls()
    walls.point, walls.normal, walls.count, walls.params = point, normal, int(count), params
    walls.shear, walls.near = shear, near
    return walls


def launch_mark_near_walls(spheres: SphereArrays, walls: PlaneWalls, margin: float) -> None:
    wp.launch(mark_near_walls, dim=spheres.x.shape[0], device=spheres.x.device, inputs=[spheres, float(margin)],
              outputs=[walls])


def blocks(n: int, block: int) -> int:
    """Tasks of a launch that runs ``block`` particles per task."""
    return max(1, (int(n) + block - 1) // block)


def launch_kick_drift_flag(spheres: SphereArrays, force, torque, gravity, dt: float, x_at_build, half_skin: float,
                           rebuild_flag, block: int = CPU_BLOCK, record: bool = False):
    """``record``: return the launch as a ``wp.Launch`` (arguments packed once, run with ``.launch()``; valid
    while none of the arrays is reallocated) instead of launching."""
    n = spheres.x.shape[0]
    return wp.launch(kick_drift_flag, dim=blocks(n, block), device=spheres.x.device,
                     inputs=[gravity, dt, x_at_build, half_skin, int(block)],
                     outputs=[spheres, force, torque, rebuild_flag], record_cmd=record)


def launch_forces_kick(spheres: SphereArrays, rows: ContactRows, params: ContactParams, box: PeriodicBox,
                       walls: PlaneWalls, gravity, dt: float, onsets: ContactOnsets, force, torque, *,
                       kick: bool, x_at_build, half_skin: float, rebuild_flag, drift: bool = False,
                       block: int = CPU_BLOCK, record: bool = False):
    """Half-list contacts + plane walls (+ the second half kick with ``kick``; + the next step's
    ``kick_drift_flag`` with ``drift``, which needs ``kick``) on a serial device; the accumulators
    ``force``/``torque`` must be zero (``kick_drift_flag`` leaves them so). ``record``: as in
    ``launch_kick_drift_flag``."""
    if spheres.x.device.is_cuda:
        raise ValueError("forces_kick relies on threads running in tid order: CPU device only")
    if drift and not kick:
        raise ValueError("drift needs kick: the next step's first half kick follows this step's second")
    n = spheres.x.shape[0]
    return wp.launch(forces_kick, dim=blocks(n, block), device=spheres.x.device,
                     inputs=[spheres, params, box, walls, gravity, dt, int(kick), int(drift), x_at_build,
                             float(half_skin), int(block)],
                     outputs=[onsets, rows, force, torque, rebuild_flag], record_cmd=record)

"""Grid -> particle interpolation with trilinear (cloud-in-cell) weights at cell centres.

Uniform Cartesian grid: ``origin`` (m), spacing ``h`` (m), ``shape`` (nx, ny, nz); cell
(i, j, k) has its centre at origin + (i + 1/2, j + 1/2, k + 1/2) h and cell fields are
``wp.array3d`` indexed [i, j, k]. A parcel at x sits in the dual cell whose corners are the
eight surrounding cell centres; the weight of corner (a, b, c) in {0, 1}^3 is
prod (a ? f : 1 - f) over the axes, f the fractional position (Birdsall & Langdon,
*Plasma Physics via Computer Simulation*, 1991, ch. 8: "cloud in cell").

Along a periodic axis the stencil wraps around (cell -1 is cell n-1). Along a bounded axis,
within the outer half cell the coordinate is clamped to the last cell centre, so the field
is held constant there and the weights still sum to one (no momentum leaves the grid).
``kernels/deposit.py`` uses these same functions, so what a parcel reads and what it
deposits are weighted identically and the exchange is equal and opposite.
Weights are computed in float64.

``ParcelArrays`` is the per-parcel view (x, v, radius, density, weight, alive) that the parcel
kernels of ``kernels/push.py`` and ``kernels/deposit.py`` take as one argument; build it with
:func:`parcel_arrays`.

``ParcelStencil`` caches each parcel's trilinear stencil (eight flat cell indices and weights) for positions
that stay fixed over several parcel-grid passes (the step's deposit and interpolation, the implicit exchange's
eight passes): a pass that reads the cache instead of recomputing ``cic_corner`` per corner costs ~20-30 ns per
parcel instead of ~100 on the CPU. Cached and computed passes add the same terms in the same order,
so their results are bit for bit the same. A kernel that takes a ``ParcelStencil`` has two loops, the cached
one over eight constant corners (unrolled; one loop over ``8 K^3`` entries that picks a row's entry or computes
it per corner costs twice as much) and the computed one, and indexes the cell fields flat, (i ny + j) nz + k
(``flat_cells`` gives the view of a cell array).
"""

from __future__ import annotations

import math
import weakref

import warp as wp

from kernels.launches import LaunchCache, launch


@wp.struct
class CellGrid:
    """Uniform grid: origin (m, float64), spacing h (m), shape (nx, ny, nz), periodic flag per axis (0/1)."""

    origin: wp.vec3d
    spacing: wp.float64
    shape: wp.vec3i
    periodic: wp.vec3i
    spread: wp.int32
    """1: a parcel of w real particles couples through a tent of half-width K = round(sqrt(w^(2/3) / 2 + 1)) cells per axis
    (``parcel_stencil``; K = 1 is the trilinear stencil), 0: the trilinear stencil at any weight."""
    fluid: wp.array3d(dtype=wp.int32)
    """(nx, ny, nz) 1 for fluid cells, or empty (all fluid): a tent (K >= 2) keeps its weights on fluid cells,
    renormalised, so that a heavy parcel near a wall neither reads the solid cells' zero gas velocity nor deposits
    into them (the trilinear stencil, K = 1, is left as it is)."""
    cloud: wp.array(dtype=wp.float32)
    """Per parcel slot: the width b >= 0 (cells) of the parcel's cloud, from the real particles' number density
    around it (``kernels/deposit.py`` ``cloud_width_kernel``): the parcel couples through ``cloud_weight``, a
    uniform cloud of width b per axis read through the trilinear stencil at each of its points (b = 0: the
    trilinear stencil itself); empty, or a slot past its end (points that are not parcels): the weight rule's
    tents, ``spread_half_width``."""


@wp.struct
class ParcelArrays:
    """The per-parcel arrays the push and deposit kernels read (views of ``hel_warp.parcels.particles.Particles``)."""

    x: wp.array(dtype=wp.vec3)
    """Centre positions, m."""
    v: wp.array(dtype=wp.vec3)
    """Velocities, m/s."""
    radius: wp.array(dtype=float)
    """Radii, m."""
    density: wp.array(dtype=float)
    """Material densities, kg/m^3."""
    weight: wp.array(dtype=float)
    """Real particles per parcel."""
    alive: wp.array(dtype=wp.int32)
    """1 while the parcel takes part in the run."""


@wp.func
def cic_axis(x: wp.float64, origin: wp.float64, spacing: wp.float64, n: int, periodic: int):
    """Base cell index along one axis (-1 allowed when periodic) and the fractional weight of the upper one."""
    if periodic != 0:
        length = spacing * wp.float64(n)
        u = x - origin
        u = u - length * wp.floor(u / length)
        s = u / spacing - wp.float64(0.5)
        base = int(wp.floor(s))
        return base, s - wp.float64(base)
    s = (x - origin) / spacing - wp.float64(0.5)
    s = wp.clamp(s, wp.float64(0.0), wp.float64(n - 1))
    base = wp.max(wp.min(int(wp.floor(s)), n - 2), 0)
    return base, s - wp.float64(base)


@wp.func
def cic_stencil(grid: CellGrid, x: wp.vec3):
    """Base cell (i, j, k) of the 2x2x2 stencil around x, and the fractions (fx, fy, fz)."""
    i, fx = cic_axis(wp.float64(x[0]), grid.origin[0], grid.spacing, grid.shape[0], grid.periodic[0])
    j, fy = cic_axis(wp.float64(x[1]), grid.origin[1], grid.spacing, grid.shape[1], grid.periodic[1])
    k, fz = cic_axis(wp.float64(x[2]), grid.origin[2], grid.spacing, grid.shape[2], grid.periodic[2])
    return wp.vec3i(i, j, k), wp.vec3d(fx, fy, fz)


@wp.func
def cic_index(i: int, n: int, periodic: int):
    """Stencil index on the grid: wrapped when periodic, else clamped to n - 1."""
    if periodic != 0:
        return (i + n) % n
    return wp.min(i, n - 1)


@wp.func
def cic_corner(grid: CellGrid, base: wp.vec3i, frac: wp.vec3d, corner: int):
    """Cell index and weight of stencil corner ``corner`` in 0..7 (bit 0: +x, bit 1: +y, bit 2: +z)."""
    a = corner & 1
    b = (corner >> 1) & 1
    c = (corner >> 2) & 1
    one = wp.float64(1.0)
    wx = frac[0]
    if a == 0:
        wx = one - frac[0]
    wy = frac[1]
    if b == 0:
        wy = one - frac[1]
    wz = frac[2]
    if c == 0:
        wz = one - frac[2]
    idx = wp.vec3i(cic_index(base[0] + a, grid.shape[0], grid.periodic[0]),
                   cic_index(base[1] + b, grid.shape[1], grid.periodic[1]),
                   cic_index(base[2] + c, grid.shape[2], grid.periodic[2]))
    return idx, wx * wy * wz


@wp.func
def spread_half_width(grid: CellGrid, weight: float):
    """K = round(sqrt(w^(2/3) / 2 + 1)) >= 1 cells with ``grid.spread``, else 1: the tent whose second moment is that
    of the parcel's w real particles. They stand for a cube of w cells (one particle's trilinear share per cell,
    edge w^(1/3) h, per-axis variance w^(2/3) h^2 / 12) each read through its own trilinear stencil (variance
    h^2 / 6); a tent of half-width K has variance K^2 h^2 / 6 (coarse graining with the cloud's own filter width:
    Radl et al. 2011, Capecelatro & Desjardins 2013). So K = 2 at w = 8 and 3 at w = 64 (a w = 64 parcel of 315 um
    in a 1 mm cell would otherwise take its whole drag from the gas of 8 cells, ~1.8 times its drag impulse per step
    on the rig at 1e-3 s). The earlier rule K = round(w^(1/3)) matched the tent's support (2 K h)^3 to 8 w cells,
    twice the cloud's variance at large w; on the rig at w = 64 it crossed 0.01-0.04 more and spread 2-5 points less
    than this tent on the same seeds (``hel_warp.studies.rig_ensemble``)."""
    if grid.spread == 0 or weight < 3.9528:  # K < 1.5 below w = 2.5^1.5 (weight 1 skips the pow)
        return 1
    return int(wp.round(wp.sqrt(0.5 * wp.pow(weight, 2.0 / 3.0) + 1.0)))


@wp.func
def cloud_support(b: wp.float64):
    """K = ceil(b / 2 + 1): a cloud of width b read trilinearly reaches b / 2 + 1 cells from the parcel, within
    the 2K cells base - K + 1 .. base + K per axis (K = 1 at b = 0: the trilinear stencil)."""
    if b <= wp.float64(0.0):
        return 1
    return int(wp.ceil(wp.float64(0.5) * b + wp.float64(1.0) - wp.float64(1.0e-9)))


@wp.func
def parcel_shape(grid: CellGrid, weight: float, tid: int):
    """(K, b) of parcel slot ``tid``: its stencil spans 2K cells per axis (K = 1: trilinear); b >= 0 the width of
    its cloud (``grid.cloud``, ``cloud_weight``), b < 0 the weight rule's tent of half-width K."""
    if tid < grid.cloud.shape[0]:
        b = wp.float64(grid.cloud[tid])
        return cloud_support(b), b
    return spread_half_width(grid, weight), wp.float64(-1.0)


@wp.func
def parcel_support(grid: CellGrid, weight: float, tid: int):
    """K of parcel slot ``tid``'s stencil (1: trilinear)."""
    k, b = parcel_shape(grid, weight, tid)
    return k


@wp.func
def hat_integral(u: wp.float64):
    """int_{-inf}^{u} max(1 - |t|, 0) dt: the trilinear weight's antiderivative along one axis."""
    one = wp.float64(1.0)
    half = wp.float64(0.5)
    if u <= -one:
        return wp.float64(0.0)
    if u <= wp.float64(0.0):
        return half * (u + one) * (u + one)
    if u < one:
        return one - half * (one - u) * (one - u)
    return one


@wp.func
def cloud_weight(offset: int, k: int, b: wp.float64, f: wp.float64):
    """Weight of the cell ``offset`` in [0, 2K) (cell base - K + 1 + offset, the parcel at base + f) for a cloud
    of width b > 0: the trilinear weight averaged over the cloud's points, (H(u + b/2) - H(u - b/2)) / b with
    u = f - (offset - K + 1) and H ``hat_integral``. The 2K weights sum to 1 and their centroid is the parcel
    (the trilinear weights reproduce 1 and x at every point of the cloud); their variance about it, averaged over
    positions, is b^2 / 12 + 1 / 6: the cloud's own and one trilinear stencil's."""
    u = f - wp.float64(offset - k + 1)
    hb = wp.float64(0.5) * b
    return (hat_integral(u + hb) - hat_integral(u - hb)) / b


def cloud_width_host(weight: float) -> float:
    """The widest cloud a parcel of ``weight`` can get (``kernels/deposit.py`` ``cloud_width_kernel``, no other
    parcel around it): b = sqrt(w^(2/3) - 1) cells, w particles one cell apart."""
    return math.sqrt(max(float(weight) ** (2.0 / 3.0) - 1.0, 0.0))


def cloud_support_host(b: float) -> int:
    """``cloud_support`` on the host."""
    return 1 if b <= 0.0 else int(math.ceil(0.5 * b + 1.0 - 1.0e-9))


def spread_half_width_host(spread: bool, weight: float) -> int:
    """The largest K that :func:`spread_half_width` can return at ``weight``, on the host: what a launch needs to know
    ahead of the kernel, e.g. how many cells a parcel of the largest weight adds into (``kernels/deposit.py``). The
    kernel rounds a float32 sqrt(w^(2/3)/2 + 1), whose last bits depend on the device's pow; within 1e-5 of a half
    the larger K is returned, elsewhere exactly the kernel's."""
    if not spread or weight < 3.9527:
        return 1
    x = math.sqrt(0.5 * float(weight) ** (2.0 / 3.0) + 1.0) + 0.5
    return max(1, int(math.floor(x + 1e-5)))


@wp.kernel
def live_extremes(
    particle_v: wp.array(dtype=wp.vec3),
    particle_weight: wp.array(dtype=wp.float32),
    particle_radius: wp.array(dtype=wp.float32),
    particle_alive: wp.array(dtype=wp.int32),
    # outputs
    extremes: wp.array(dtype=wp.float64),
):
    """Over the live parcels (``extremes`` zeroed by the caller; ``Particles.live_extremes`` reads it back): [0] max |v| (float64 from the float32 components,
    (vx^2 + vy^2) + vz^2 then the root: numpy's ``linalg.norm(v.astype(float64), axis=1)``), [1] max weight, [2] max
    radius, [3] += 1 per live parcel, [4] += 1 per live parcel whose |v|, weight or radius is not finite (an atomic
    maximum passes a NaN over: the caller must look here). A maximum does not depend on the order of the atomics,
    and the counts are integers far below 2^53: the same values in every run (on the CPU numpy's; a GPU may fuse a
    product and a sum)."""
    p = wp.tid()
    if particle_alive[p] == 0:
        return
    v = particle_v[p]
    vx = wp.float64(v[0])
    vy = wp.float64(v[1])
    vz = wp.float64(v[2])
    sx = vx * vx
    sy = vy * vy
    sz = vz * vz
    sxy = sx + sy
    speed = wp.sqrt(sxy + sz)
    w = wp.float64(particle_weight[p])
    r = wp.float64(particle_radius[p])
    wp.atomic_max(extremes, 0, speed)
    wp.atomic_max(extremes, 1, w)
    wp.atomic_max(extremes, 2, r)
    wp.atomic_add(extremes, 3, wp.float64(1.0))
    if not (wp.isfinite(speed) and wp.isfinite(w) and wp.isfinite(r)):
        wp.atomic_add(extremes, 4, wp.float64(1.0))


@wp.func
def tent_index(i: int, n: int, periodic: int):
    """Tent cell index on the grid: wrapped when periodic, else clamped into [0, n - 1] (the share of a cell past
    the side goes to the last one: the sum is kept)."""
    if periodic != 0:
        return ((i % n) + n) % n
    return wp.clamp(i, 0, n - 1)


@wp.func
def tent_weight(offset: int, k: int, f: wp.float64):
    """Weight of the cell ``offset`` in [0, 2K) of the tent along one axis (cell base - K + 1 + offset, the parcel
    at base + f): (K - |offset - K + 1 - f|) / K^2 (the K^2 normalises: the 2K weights sum to 1 for any f)."""
    kd = wp.float64(k)
    d = wp.abs(wp.float64(offset - k + 1) - f)
    return wp.max(kd - d, wp.float64(0.0)) / (kd * kd)


@wp.func
def axis_weight(offset: int, k: int, b: wp.float64, f: wp.float64):
    """One axis's weight of a parcel's stencil: the cloud's (b >= 0, ``cloud_weight``) or the weight rule's tent
    (b < 0, ``tent_weight``)."""
    if b < wp.float64(0.0):
        return tent_weight(offset, k, f)
    return cloud_weight(offset, k, b, f)


@wp.func
def tent_cell(grid: CellGrid, base: wp.vec3i, frac: wp.vec3d, k: int, b: wp.float64, n: int):
    """Cell index and weight of entry n in [0, (2K)^3) (K >= 2) of a tent (b < 0) or a cloud of width b."""
    m = 2 * k
    i = n % m
    j = (n / m) % m
    l = n / (m * m)
    idx = wp.vec3i(tent_index(base[0] - k + 1 + i, grid.shape[0], grid.periodic[0]),
                   tent_index(base[1] - k + 1 + j, grid.shape[1], grid.periodic[1]),
                   tent_index(base[2] - k + 1 + l, grid.shape[2], grid.periodic[2]))
    return idx, axis_weight(i, k, b, frac[0]) * axis_weight(j, k, b, frac[1]) * axis_weight(l, k, b, frac[2])


@wp.func
def parcel_stencil(grid: CellGrid, x: wp.vec3, weight: float, tid: int):
    """The stencil of parcel slot ``tid`` of ``weight`` at x: its trilinear base cell and fractions, its support K
    and cloud width b (``parcel_shape``; ``parcel_cell`` walks the (2 K)^3 cells) and its weight on fluid cells
    (1 at K = 1, without a mask, or when the whole stencil lies in solid cells)."""
    base, frac = cic_stencil(grid, x)
    k, b = parcel_shape(grid, weight, tid)
    norm = wp.float64(1.0)
    if k > 1 and grid.fluid.shape[0] > 0:
        total = wp.float64(0.0)
        for n in range(8 * k * k * k):
            idx, w = tent_cell(grid, base, frac, k, b, n)
            if grid.fluid[idx[0], idx[1], idx[2]] != 0:
                total = total + w
        if total > wp.float64(0.0):
            norm = total
    return base, frac, k, b, norm


@wp.func
def parcel_cell(grid: CellGrid, base: wp.vec3i, frac: wp.vec3d, k: int, b: wp.float64, norm: wp.float64, n: int):
    """Cell index and weight of entry n in [0, (2K)^3) of a parcel's stencil (K = 1: ``cic_corner``, bitwise; a
    wider stencil's weight on a solid cell is 0 and the fluid cells' are divided by ``norm``, ``parcel_stencil``'s)."""
    if k == 1:
        return cic_corner(grid, base, frac, n)
    idx, w = tent_cell(grid, base, frac, k, b, n)
    if grid.fluid.shape[0] > 0 and norm != wp.float64(1.0):
        if grid.fluid[idx[0], idx[1], idx[2]] == 0:
            w = wp.float64(0.0)
        else:
            w = w / norm
    return idx, w


@wp.struct
class ParcelStencil:
    """Per-parcel cache of the trilinear stencil (K = 1): row n of parcel i is ``cic_corner``'s corner n at the
    position ``x[i]``. A kernel uses row i only when ``x[i]`` equals the position it is given for the parcel (it
    checks, per parcel, and computes the stencil otherwise), so a cache left over from moved parcels is never
    read; tents (K >= 2, ``spread_half_width``) are always computed. Empty arrays: no cache (every stencil
    computed)."""

    x: wp.array(dtype=wp.vec3)
    """(n,) the position row i was computed at, m."""
    cell: wp.array2d(dtype=wp.int32)
    """(n, 8) flat index (i ny + j) nz + k of corner n's cell."""
    weight: wp.array2d(dtype=wp.float64)
    """(n, 8) trilinear weight of corner n."""


@wp.func
def cell_offset(grid: CellGrid, idx: wp.vec3i):
    """Flat index (i ny + j) nz + k of cell idx in a contiguous (nx, ny, nz) array (``flat_cells``)."""
    return (idx[0] * grid.shape[1] + idx[1]) * grid.shape[2] + idx[2]


@wp.func
def stencil_holds(stencil: ParcelStencil, tid: int, x: wp.vec3, k: int):
    """True when the cached row ``tid`` is the trilinear stencil (k = 1) at x."""
    if k != 1 or stencil.x.shape[0] == 0:
        return False
    return stencil.x[tid] == x


@wp.func
def store_stencil(grid: CellGrid, stencil: ParcelStencil, tid: int, x: wp.vec3):
    """Compute x's trilinear stencil into row ``tid`` of the cache: corner n is ``cic_corner``'s (the same cell and
    the same product (w_x w_y) w_z, bit for bit), with the per-axis indices and the four w_x w_y products formed
    once instead of per corner (~30 instead of ~42 ns per parcel on the CPU)."""
    base, frac = cic_stencil(grid, x)
    one = wp.float64(1.0)
    ny = grid.shape[1]
    nz = grid.shape[2]
    i0 = cic_index(base[0], grid.shape[0], grid.periodic[0]) * ny
    i1 = cic_index(base[0] + 1, grid.shape[0], grid.periodic[0]) * ny
    j0 = cic_index(base[1], ny, grid.periodic[1])
    j1 = cic_index(base[1] + 1, ny, grid.periodic[1])
    k0 = cic_index(base[2], nz, grid.periodic[2])
    k1 = cic_index(base[2] + 1, nz, grid.periodic[2])
    stencil.cell[tid, 0] = (i0 + j0) * nz + k0
    stencil.cell[tid, 1] = (i1 + j0) * nz + k0
    stencil.cell[tid, 2] = (i0 + j1) * nz + k0
    stencil.cell[tid, 3] = (i1 + j1) * nz + k0
    stencil.cell[tid, 4] = (i0 + j0) * nz + k1
    stencil.cell[tid, 5] = (i1 + j0) * nz + k1
    stencil.cell[tid, 6] = (i0 + j1) * nz + k1
    stencil.cell[tid, 7] = (i1 + j1) * nz + k1
    w00 = (one - frac[0]) * (one - frac[1])
    w10 = frac[0] * (one - frac[1])
    w01 = (one - frac[0]) * frac[1]
    w11 = frac[0] * frac[1]
    wz0 = one - frac[2]
    stencil.weight[tid, 0] = w00 * wz0
    stencil.weight[tid, 1] = w10 * wz0
    stencil.weight[tid, 2] = w01 * wz0
    stencil.weight[tid, 3] = w11 * wz0
    stencil.weight[tid, 4] = w00 * frac[2]
    stencil.weight[tid, 5] = w10 * frac[2]
    stencil.weight[tid, 6] = w01 * frac[2]
    stencil.weight[tid, 7] = w11 * frac[2]
    stencil.x[tid] = x


@wp.kernel
def fill_stencil_kernel(
    grid: CellGrid,
    particle_x: wp.array(dtype=wp.vec3),
    particle_weight: wp.array(dtype=float),
    only_stale: int,
    # outputs
    stencil: ParcelStencil,
):
    """Row i of the cache at particle_x[i] for trilinear parcels (all of them, or with ``only_stale`` those whose
    row was computed elsewhere)."""
    tid = wp.tid()
    weight = float(1.0)
    if particle_weight.shape[0] > 0:
        weight = particle_weight[tid]
    if parcel_support(grid, weight, tid) != 1:
        return
    x = particle_x[tid]
    if only_stale != 0:
        if stencil.x[tid] == x:
            return
    store_stencil(grid, stencil, tid, x)


@wp.func
def vec3_to_64(f: wp.vec3):
    return wp.vec3d(wp.float64(f[0]), wp.float64(f[1]), wp.float64(f[2]))


@wp.func
def vec3_from_64(f: wp.vec3d):
    return wp.vec3(float(f[0]), float(f[1]), float(f[2]))


@wp.kernel
def interp_vec3_parcels_kernel(
    grid: CellGrid,
    stencil: ParcelStencil,
    particle_x: wp.array(dtype=wp.vec3),
    particle_weight: wp.array(dtype=float),
    cell_field: wp.array(dtype=wp.vec3),
    # outputs
    parcel_value: wp.array(dtype=wp.vec3),
):
    """``cell_field``: flat (``flat_cells``)."""
    tid = wp.tid()
    weight = float(1.0)
    if particle_weight.shape[0] > 0:  # no weights: trilinear
        weight = particle_weight[tid]
    x = particle_x[tid]
    acc = wp.vec3d(0.0, 0.0, 0.0)
    if stencil_holds(stencil, tid, x, parcel_support(grid, weight, tid)):
        for n in range(8):
            acc = acc + stencil.weight[tid, n] * vec3_to_64(cell_field[stencil.cell[tid, n]])
    else:
        base, frac, k, b, norm = parcel_stencil(grid, x, weight, tid)
        for n in range(8 * k * k * k):
            idx, w = parcel_cell(grid, base, frac, k, b, norm, n)
            acc = acc + w * vec3_to_64(cell_field[cell_offset(grid, idx)])
    parcel_value[tid] = vec3_from_64(acc)


@wp.kernel
def interp_scalar_parcels_kernel(
    grid: CellGrid,
    stencil: ParcelStencil,
    particle_x: wp.array(dtype=wp.vec3),
    particle_weight: wp.array(dtype=float),
    cell_field: wp.array(dtype=float),
    # outputs
    parcel_value: wp.array(dtype=float),
):
    """``cell_field``: flat (``flat_cells``)."""
    tid = wp.tid()
    weight = float(1.0)
    if particle_weight.shape[0] > 0:  # no weights: trilinear
        weight = particle_weight[tid]
    x = particle_x[tid]
    acc = wp.float64(0.0)
    if stencil_holds(stencil, tid, x, parcel_support(grid, weight, tid)):
        for n in range(8):
            acc = acc + stencil.weight[tid, n] * wp.float64(cell_field[stencil.cell[tid, n]])
    else:
        base, frac, k, b, norm = parcel_stencil(grid, x, weight, tid)
        for n in range(8 * k * k * k):
            idx, w = parcel_cell(grid, base, frac, k, b, norm, n)
            acc = acc + w * wp.float64(cell_field[cell_offset(grid, idx)])
    parcel_value[tid] = float(acc)


gas_record = wp.types.vector(length=8, dtype=wp.float32)
"""One cell's fields of the HEL step's interpolation side by side: gas velocity (3), grad p' (3), eps_s, unused."""


@wp.kernel
def gas_record_kernel(
    cell_velocity: wp.array(dtype=wp.vec3),
    cell_grad_p: wp.array(dtype=wp.vec3),
    cell_eps_s: wp.array(dtype=float),
    # outputs
    cell_gas: wp.array(dtype=gas_record),
):
    """The three cell fields into one record per cell (flat)."""
    c = wp.tid()
    u = cell_velocity[c]
    g = cell_grad_p[c]
    cell_gas[c] = gas_record(u[0], u[1], u[2], g[0], g[1], g[2], cell_eps_s[c], 0.0)


@wp.func
def add_gas_record(w: wp.float64, r: gas_record, u: wp.vec3d, g: wp.vec3d, e: wp.float64):
    """u, g, e plus w times the record's three fields (float64)."""
    u_new = u + w * wp.vec3d(wp.float64(r[0]), wp.float64(r[1]), wp.float64(r[2]))
    g_new = g + w * wp.vec3d(wp.float64(r[3]), wp.float64(r[4]), wp.float64(r[5]))
    return u_new, g_new, e + w * wp.float64(r[6])


@wp.kernel
def interp_gas_kernel(
    grid: CellGrid,
    stencil: ParcelStencil,
    particle_x: wp.array(dtype=wp.vec3),
    particle_weight: wp.array(dtype=float),
    cell_gas: wp.array(dtype=gas_record),
    # outputs
    parcel_u_f: wp.array(dtype=wp.vec3),
    parcel_grad_p: wp.array(dtype=wp.vec3),
    parcel_eps_s: wp.array(dtype=float),
):
    """The three fields of the HEL step's interpolation in one pass over the stencil, from the cells' records
    (``gas_record_kernel``; each field summed as ``interp_vec3_parcels_kernel`` / ``interp_scalar_parcels_kernel``
    sum it: the same bits); cell records flat."""
    tid = wp.tid()
    weight = float(1.0)
    if particle_weight.shape[0] > 0:  # no weights: trilinear
        weight = particle_weight[tid]
    x = particle_x[tid]
    u = wp.vec3d(0.0, 0.0, 0.0)
    g = wp.vec3d(0.0, 0.0, 0.0)
    e = wp.float64(0.0)
    if stencil_holds(stencil, tid, x, parcel_support(grid, weight, tid)):
        for n in range(8):
            u, g, e = add_gas_record(stencil.weight[tid, n], cell_gas[stencil.cell[tid, n]], u, g, e)
    else:
        base, frac, k, b, norm = parcel_stencil(grid, x, weight, tid)
        for n in range(8 * k * k * k):
            idx, w = parcel_cell(grid, base, frac, k, b, norm, n)
            u, g, e = add_gas_record(w, cell_gas[cell_offset(grid, idx)], u, g, e)
    parcel_u_f[tid] = vec3_from_64(u)
    parcel_grad_p[tid] = vec3_from_64(g)
    parcel_eps_s[tid] = float(e)


@wp.kernel
def stencil_weights_kernel(
    grid: CellGrid,
    particle_x: wp.array(dtype=wp.vec3),
    # outputs
    parcel_cells: wp.array2d(dtype=wp.vec3i),
    parcel_weights: wp.array2d(dtype=wp.float64),
):
    tid = wp.tid()
    base, frac = cic_stencil(grid, particle_x[tid])
    for corner in range(8):
        idx, w = cic_corner(grid, base, frac, corner)
        parcel_cells[tid, corner] = idx
        parcel_weights[tid, corner] = w


# ---------------------------------------------------------------- launch wrappers

@wp.kernel
def cell_sort_keys_kernel(
    grid: CellGrid,
    n_used: int,
    particle_x: wp.array(dtype=wp.vec3),
    particle_alive: wp.array(dtype=wp.int32),
    # outputs (length >= 2 * len(particle_x): the radix sort's scratch)
    keys: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.int32),
):
    """Key = linear index of the cell holding the parcel (live slots below ``n_used``), the cell count for
    dead or unused slots (sorted to the end, in slot order); value = the slot."""
    k = wp.tid()
    n_cells = grid.shape[0] * grid.shape[1] * grid.shape[2]
    key = n_cells
    if k < n_used and particle_alive[k] != 0:
        x = particle_x[k]
        c = wp.vec3i(0, 0, 0)
        for a in range(3):
            s = int(wp.floor((wp.float64(x[a]) - grid.origin[a]) / grid.spacing))
            c[a] = wp.clamp(s, 0, grid.shape[a] - 1)
        key = (c[0] * grid.shape[1] + c[1]) * grid.shape[2] + c[2]
    keys[k] = key
    values[k] = k


@wp.kernel
def inverse_permutation_kernel(new_to_old: wp.array(dtype=wp.int32), old_to_new: wp.array(dtype=wp.int32)):
    k = wp.tid()
    old_to_new[new_to_old[k]] = k


def cell_order(grid: CellGrid, n_used: int, particle_x, particle_alive, keys, values, old_to_new) -> None:
    """Stable radix sort of the slots by cell (dead and unused slots last): ``values[:n]`` = new_to_old,
    ``old_to_new`` its inverse; ``keys``/``values`` of length 2 n (n = len(particle_x))."""
    n = particle_x.shape[0]
    wp.launch(cell_sort_keys_kernel, dim=n, device=particle_x.device,
              inputs=[grid, int(n_used), particle_x, particle_alive], outputs=[keys, values])
    wp.utils.radix_sort_pairs(keys, values, n)
    wp.launch(inverse_permutation_kernel, dim=n, device=particle_x.device, inputs=[values], outputs=[old_to_new])


def parcel_arrays(particles, *, x=None, v=None) -> ParcelArrays:
    """The ``ParcelArrays`` view of a ``hel_warp.parcels.particles.Particles`` (no copy); ``x``/``v`` replace the
    particles' positions/velocities (e.g. the implicit exchange's start positions)."""
    p = ParcelArrays()
    p.x = particles.x if x is None else x
    p.v = particles.v if v is None else v
    p.radius, p.density, p.weight, p.alive = particles.radius, particles.density, particles.weight, particles.alive
    return p


def make_cell_grid(origin, spacing: float, shape, periodic=(False, False, False), spread: bool = False,
                   fluid=None, cloud=None) -> CellGrid:
    """A ``CellGrid`` from plain values (origin m, spacing m, shape and periodic flags of three entries; ``spread``:
    weighted parcels couple through tents that grow with their weight, ``spread_half_width``; ``fluid``: the
    int32 fluid mask the tents keep to, None: all fluid)."""
    grid = CellGrid()
    grid.spread = 1 if spread else 0
    grid.fluid = fluid if fluid is not None else _no_mask()
    grid.cloud = cloud if cloud is not None else _no_cloud()
    grid.origin = wp.vec3d(*[float(o) for o in origin])
    grid.spacing = wp.float64(spacing)
    grid.shape = wp.vec3i(*[int(n) for n in shape])
    grid.periodic = wp.vec3i(*[int(bool(p)) for p in periodic])
    return grid


def interpolate_vec3(grid: CellGrid, particle_x, cell_field, parcel_value):
    """Trilinear value of a vec3 cell field at each point, into ``parcel_value``."""
    interpolate_vec3_parcels(grid, particle_x, None, cell_field, parcel_value)


_NO_WEIGHTS = {}
_NO_MASK = {}
_NO_STENCIL = {}
_FLAT = weakref.WeakKeyDictionary()


def flat_cells(cell_field):
    """The flat (nx ny nz,) view of a contiguous cell array, index (i ny + j) nz + k (``cell_offset``), as the
    kernels that take a ``ParcelStencil`` read cell fields. Kept once per array (building a view costs ~6 us,
    ~20 of them per step); the view shares the array's memory and does not keep it alive."""
    view = _FLAT.get(cell_field)
    if view is None:
        if not cell_field.is_contiguous:
            raise ValueError("flat_cells needs a contiguous cell array")
        view = wp.array(ptr=cell_field.ptr, shape=(cell_field.size,), dtype=cell_field.dtype,
                        device=cell_field.device, copy=False)
        _FLAT[cell_field] = view
    return view


def make_parcel_stencil(capacity: int, device=None) -> ParcelStencil:
    """A ``ParcelStencil`` for ``capacity`` parcels (96 bytes per parcel plus the positions); its rows hold
    nothing until :func:`fill_stencil` (a position of NaN never equals a parcel's)."""
    stencil = ParcelStencil()
    stencil.x = wp.full(int(capacity), wp.vec3(float("nan")), dtype=wp.vec3, device=device)
    stencil.cell = wp.zeros((int(capacity), 8), dtype=wp.int32, device=device)
    stencil.weight = wp.zeros((int(capacity), 8), dtype=wp.float64, device=device)
    return stencil


def no_stencil(device) -> ParcelStencil:
    """The empty ``ParcelStencil`` (every stencil computed), kept once per device."""
    key = str(wp.get_device(device))
    if key not in _NO_STENCIL:
        stencil = ParcelStencil()
        stencil.x = wp.empty(0, dtype=wp.vec3, device=device)
        stencil.cell = wp.empty((0, 8), dtype=wp.int32, device=device)
        stencil.weight = wp.empty((0, 8), dtype=wp.float64, device=device)
        _NO_STENCIL[key] = stencil
    return _NO_STENCIL[key]


def stencil_or_empty(stencil, particle_x) -> ParcelStencil:
    """``stencil``, or the empty one on ``particle_x``'s device when None."""
    return stencil if stencil is not None else no_stencil(particle_x.device)


def fill_stencil(grid: CellGrid, particle_x, particle_weight, stencil: ParcelStencil, *,
                 only_stale: bool = False, launches: LaunchCache | None = None) -> None:
    """The cache's rows at ``particle_x`` for the trilinear parcels (``particle_weight`` None: all); with
    ``only_stale`` only the rows computed at another position (a read-only pass when nothing moved)."""
    launch(fill_stencil_kernel, dim=particle_x.shape[0], device=particle_x.device,
           inputs=[grid, particle_x, _weights_or_none(particle_weight, particle_x), int(bool(only_stale))],
           outputs=[stencil], cache=launches)


def _no_mask():
    """An empty int32 mask (all fluid) on the default device, kept once per device."""
    key = str(wp.get_device())
    if key not in _NO_MASK:
        _NO_MASK[key] = wp.empty((0, 0, 0), dtype=wp.int32)
    return _NO_MASK[key]


def _no_cloud():
    """An empty float32 array of cloud widths (the weight rule) on the default device, kept once per device."""
    key = "cloud:" + str(wp.get_device())
    if key not in _NO_MASK:
        _NO_MASK[key] = wp.empty(0, dtype=wp.float32)
    return _NO_MASK[key]


def _weights_or_none(particle_weight, particle_x):
    """``particle_weight``, or an empty array (trilinear for every point) kept once per device."""
    if particle_weight is not None:
        return particle_weight
    key = str(particle_x.device)
    if key not in _NO_WEIGHTS:
        _NO_WEIGHTS[key] = wp.empty(0, dtype=float, device=particle_x.device)
    return _NO_WEIGHTS[key]


def interpolate_vec3_parcels(grid: CellGrid, particle_x, particle_weight, cell_field, parcel_value, *,
                             stencil: ParcelStencil | None = None, launches: LaunchCache | None = None):
    """A vec3 cell field at each parcel with the parcel's stencil (``parcel_stencil``: trilinear at weight 1,
    without ``grid.spread`` or with ``particle_weight`` None), into ``parcel_value``; ``stencil``: the cache of
    the rows it holds at ``particle_x`` (None: all computed)."""
    launch(interp_vec3_parcels_kernel, dim=particle_x.shape[0], device=particle_x.device,
           inputs=[grid, stencil_or_empty(stencil, particle_x), particle_x,
                   _weights_or_none(particle_weight, particle_x), flat_cells(cell_field)],
           outputs=[parcel_value], cache=launches)


def interpolate_scalar_parcels(grid: CellGrid, particle_x, particle_weight, cell_field, parcel_value, *,
                               stencil: ParcelStencil | None = None):
    """A float32 cell field at each parcel with the parcel's stencil, into ``parcel_value`` (``stencil``: as
    :func:`interpolate_vec3_parcels`)."""
    wp.launch(interp_scalar_parcels_kernel, dim=particle_x.shape[0], device=particle_x.device,
              inputs=[grid, stencil_or_empty(stencil, particle_x), particle_x,
                      _weights_or_none(particle_weight, particle_x), flat_cells(cell_field)],
              outputs=[parcel_value])


def interpolate_gas_parcels(grid: CellGrid, particle_x, particle_weight, cell_velocity, cell_grad_p, cell_eps_s, *,
                            cell_gas, parcel_u_f, parcel_grad_p, parcel_eps_s, stencil: ParcelStencil | None = None,
                            launches: LaunchCache | None = None):
    """Gas velocity, grad p' and eps_s at each parcel in one pass (the values of three
    :func:`interpolate_vec3_parcels` / :func:`interpolate_scalar_parcels` calls, bit for bit). ``cell_gas``: an
    (nx, ny, nz) ``gas_record`` scratch array the three cell fields are first copied into, so that a corner is one
    32-byte read instead of three (~37 instead of ~51 ns per parcel on the CPU, the copy included)."""
    gas = flat_cells(cell_gas)
    launch(gas_record_kernel, dim=cell_gas.size, device=particle_x.device,
           inputs=[flat_cells(cell_velocity), flat_cells(cell_grad_p), flat_cells(cell_eps_s)], outputs=[gas],
           cache=launches)
    launch(interp_gas_kernel, dim=particle_x.shape[0], device=particle_x.device,
           inputs=[grid, stencil_or_empty(stencil, particle_x), particle_x,
                   _weights_or_none(particle_weight, particle_x), gas],
           outputs=[parcel_u_f, parcel_grad_p, parcel_eps_s], cache=launches)


def interpolate_scalar(grid: CellGrid, particle_x, cell_field, parcel_value):
    """Trilinear value of a float32 cell field at each point, into ``parcel_value``."""
    interpolate_scalar_parcels(grid, particle_x, None, cell_field, parcel_value)


def stencil_weights(grid: CellGrid, particle_x, parcel_cells, parcel_weights):
    """The eight (cell, weight) pairs of each parcel, shape (n, 8) (diagnostics and tests)."""
    wp.launch(stencil_weights_kernel, dim=particle_x.shape[0], device=particle_x.device,
              inputs=[grid, particle_x], outputs=[parcel_cells, parcel_weights])


def launch_live_extremes(particle_v, particle_weight, particle_radius, particle_alive, extremes) -> None:
    """``live_extremes`` into ``extremes`` (5 float64, zeroed here)."""
    extremes.zero_()
    wp.launch(live_extremes, dim=particle_v.shape[0], device=particle_v.device,
              inputs=[particle_v, particle_weight, particle_radius, particle_alive], outputs=[extremes])

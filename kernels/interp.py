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
"""

from __future__ import annotations

import warp as wp


@wp.struct
class CellGrid:
    """Uniform grid: origin (m, float64), spacing h (m), shape (nx, ny, nz), periodic flag per axis (0/1)."""

    origin: wp.vec3d
    spacing: wp.float64
    shape: wp.vec3i
    periodic: wp.vec3i
    spread: wp.int32
    """1: a parcel of w real particles couples through a tent of half-width K = round(w^(1/3)) cells per axis
    (``parcel_stencil``; K = 1 is the trilinear stencil), 0: the trilinear stencil at any weight."""
    fluid: wp.array3d(dtype=wp.int32)
    """(nx, ny, nz) 1 for fluid cells, or empty (all fluid): a tent (K >= 2) keeps its weights on fluid cells,
    renormalised, so that a heavy parcel near a wall neither reads the solid cells' zero gas velocity nor deposits
    into them (the trilinear stencil, K = 1, is left as it is)."""


@wp.struct
class ParcelArrays:
    """The per-parcel arrays the push and deposit kernels read (views of ``hel_warp.particles.Particles``)."""

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
    """K = round(w^(1/3)) >= 1 cells with ``grid.spread``, else 1: the tent's volume (2 K h)^3 grows as w, so a
    parcel's share per cell is that of one trilinear particle (coarse graining: the parcel's w particles spread
    over w times the volume; a w = 64 parcel of 315 um in a 1 mm cell would otherwise take its whole drag from
    the gas of 8 cells, ~1.8 times its drag impulse per step on the rig at 1e-3 s)."""
    if grid.spread == 0 or weight < 3.375:  # w^(1/3) < 1.5
        return 1
    return int(wp.round(wp.pow(weight, 1.0 / 3.0)))


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
def tent_cell(grid: CellGrid, base: wp.vec3i, frac: wp.vec3d, k: int, n: int):
    """Cell index and raw tent weight of entry n in [0, (2K)^3) (K >= 2)."""
    m = 2 * k
    a = n % m
    b = (n / m) % m
    c = n / (m * m)
    idx = wp.vec3i(tent_index(base[0] - k + 1 + a, grid.shape[0], grid.periodic[0]),
                   tent_index(base[1] - k + 1 + b, grid.shape[1], grid.periodic[1]),
                   tent_index(base[2] - k + 1 + c, grid.shape[2], grid.periodic[2]))
    return idx, tent_weight(a, k, frac[0]) * tent_weight(b, k, frac[1]) * tent_weight(c, k, frac[2])


@wp.func
def parcel_stencil(grid: CellGrid, x: wp.vec3, weight: float):
    """The stencil of a parcel of ``weight``: its trilinear base cell and fractions, the tent's half-width K
    (``parcel_cell`` walks its (2 K)^3 cells) and the tent's weight on fluid cells (1 at K = 1, without a mask,
    or when the whole tent lies in solid cells)."""
    base, frac = cic_stencil(grid, x)
    k = spread_half_width(grid, weight)
    norm = wp.float64(1.0)
    if k > 1 and grid.fluid.shape[0] > 0:
        total = wp.float64(0.0)
        for n in range(8 * k * k * k):
            idx, w = tent_cell(grid, base, frac, k, n)
            if grid.fluid[idx[0], idx[1], idx[2]] != 0:
                total = total + w
        if total > wp.float64(0.0):
            norm = total
    return base, frac, k, norm


@wp.func
def parcel_cell(grid: CellGrid, base: wp.vec3i, frac: wp.vec3d, k: int, norm: wp.float64, n: int):
    """Cell index and weight of entry n in [0, (2K)^3) of a parcel's stencil (K = 1: ``cic_corner``, bitwise; a
    tent's weight on a solid cell is 0 and the fluid cells' are divided by ``norm``, ``parcel_stencil``'s)."""
    if k == 1:
        return cic_corner(grid, base, frac, n)
    idx, w = tent_cell(grid, base, frac, k, n)
    if grid.fluid.shape[0] > 0 and norm != wp.float64(1.0):
        if grid.fluid[idx[0], idx[1], idx[2]] == 0:
            w = wp.float64(0.0)
        else:
            w = w / norm
    return idx, w


@wp.kernel
def interp_vec3_parcels_kernel(
    grid: CellGrid,
    particle_x: wp.array(dtype=wp.vec3),
    particle_weight: wp.array(dtype=float),
    cell_field: wp.array3d(dtype=wp.vec3),
    # outputs
    parcel_value: wp.array(dtype=wp.vec3),
):
    tid = wp.tid()
    weight = float(1.0)
    if particle_weight.shape[0] > 0:  # no weights: trilinear
        weight = particle_weight[tid]
    base, frac, k, norm = parcel_stencil(grid, particle_x[tid], weight)
    acc = wp.vec3d(0.0, 0.0, 0.0)
    for n in range(8 * k * k * k):
        idx, w = parcel_cell(grid, base, frac, k, norm, n)
        f = cell_field[idx[0], idx[1], idx[2]]
        acc = acc + w * wp.vec3d(wp.float64(f[0]), wp.float64(f[1]), wp.float64(f[2]))
    parcel_value[tid] = wp.vec3(float(acc[0]), float(acc[1]), float(acc[2]))


@wp.kernel
def interp_scalar_parcels_kernel(
    grid: CellGrid,
    particle_x: wp.array(dtype=wp.vec3),
    particle_weight: wp.array(dtype=float),
    cell_field: wp.array3d(dtype=float),
    # outputs
    parcel_value: wp.array(dtype=float),
):
    tid = wp.tid()
    weight = float(1.0)
    if particle_weight.shape[0] > 0:  # no weights: trilinear
        weight = particle_weight[tid]
    base, frac, k, norm = parcel_stencil(grid, particle_x[tid], weight)
    acc = wp.float64(0.0)
    for n in range(8 * k * k * k):
        idx, w = parcel_cell(grid, base, frac, k, norm, n)
        acc = acc + w * wp.float64(cell_field[idx[0], idx[1], idx[2]])
    parcel_value[tid] = float(acc)


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
    """The ``ParcelArrays`` view of a ``hel_warp.particles.Particles`` (no copy); ``x``/``v`` replace the
    particles' positions/velocities (e.g. the implicit exchange's start positions)."""
    p = ParcelArrays()
    p.x = particles.x if x is None else x
    p.v = particles.v if v is None else v
    p.radius, p.density, p.weight, p.alive = particles.radius, particles.density, particles.weight, particles.alive
    return p


def make_cell_grid(origin, spacing: float, shape, periodic=(False, False, False), spread: bool = False,
                   fluid=None) -> CellGrid:
    """A ``CellGrid`` from plain values (origin m, spacing m, shape and periodic flags of three entries; ``spread``:
    weighted parcels couple through tents that grow with their weight, ``spread_half_width``; ``fluid``: the
    int32 fluid mask the tents keep to, None: all fluid)."""
    grid = CellGrid()
    grid.spread = 1 if spread else 0
    grid.fluid = fluid if fluid is not None else _no_mask()
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


def _no_mask():
    """An empty int32 mask (all fluid) on the default device, kept once per device."""
    key = str(wp.get_device())
    if key not in _NO_MASK:
        _NO_MASK[key] = wp.empty((0, 0, 0), dtype=wp.int32)
    return _NO_MASK[key]


def _weights_or_none(particle_weight, particle_x):
    """``particle_weight``, or an empty array (trilinear for every point) kept once per device."""
    if particle_weight is not None:
        return particle_weight
    key = str(particle_x.device)
    if key not in _NO_WEIGHTS:
        _NO_WEIGHTS[key] = wp.empty(0, dtype=float, device=particle_x.device)
    return _NO_WEIGHTS[key]


def interpolate_vec3_parcels(grid: CellGrid, particle_x, particle_weight, cell_field, parcel_value):
    """A vec3 cell field at each parcel with the parcel's stencil (``parcel_stencil``: trilinear at weight 1,
    without ``grid.spread`` or with ``particle_weight`` None), into ``parcel_value``."""
    wp.launch(interp_vec3_parcels_kernel, dim=particle_x.shape[0], device=particle_x.device,
              inputs=[grid, particle_x, _weights_or_none(particle_weight, particle_x), cell_field],
              outputs=[parcel_value])


def interpolate_scalar_parcels(grid: CellGrid, particle_x, particle_weight, cell_field, parcel_value):
    """A float32 cell field at each parcel with the parcel's stencil, into ``parcel_value``."""
    wp.launch(interp_scalar_parcels_kernel, dim=particle_x.shape[0], device=particle_x.device,
              inputs=[grid, particle_x, _weights_or_none(particle_weight, particle_x), cell_field],
              outputs=[parcel_value])


def interpolate_scalar(grid: CellGrid, particle_x, cell_field, parcel_value):
    """Trilinear value of a float32 cell field at each point, into ``parcel_value``."""
    interpolate_scalar_parcels(grid, particle_x, None, cell_field, parcel_value)


def stencil_weights(grid: CellGrid, particle_x, parcel_cells, parcel_weights):
    """The eight (cell, weight) pairs of each parcel, shape (n, 8) (diagnostics and tests)."""
    wp.launch(stencil_weights_kernel, dim=particle_x.shape[0], device=particle_x.device,
              inputs=[grid, particle_x], outputs=[parcel_cells, parcel_weights])

"""Sorted cell list: the neighbour search structure of the swept detection (kernels/collide.py).

The points are binned into a box of cubic cells (no hashing: one cell per place, ``dims`` cells per axis from
``origin``; in a triply periodic box the cells tile the box exactly and a search wraps around its faces) and sorted
by cell, x fastest (a stable sort: within a cell by point index). The points of cell ``c`` are the slots
``cell_start[c] .. cell_start[c + 1] - 1``, so a row of cells along x is one contiguous range of slots: a search of
the box around a point walks (y, z) rows and reads each row's points in one run, without the per-cell hash, modulo
and bucket loads of a hash-grid query (``wp.hash_grid_query``), which dominated the swept searches on the CPU.
``slot_position`` holds each slot's point (sequential reads along a row). This is the cell list of molecular
dynamics (Allen & Tildesley, *Computer Simulation of Liquids*, sec. 5.3) with its cells in sorted order
(Green, *Particle Simulation using CUDA*, NVIDIA 2010).

A search for the points within ``radius`` of ``p``: ``lo, hi = search_box(cells, p, radius)``, then the slot ranges
``range_slots(cells, lo, hi, k, p, radius)`` for k < ``range_count(cells, lo, hi)``: one per (y, z) row in open space,
two in a periodic box (a row that crosses a face in x is two ranges; otherwise the second is empty); a row holds only
the cells of the ball's chord (a row beyond the radius none), so the search covers about the ball, not its box. One loop over k, not a
loop over rows and an unrolled one over the parts: the caller's loop body (often a large inlined test) is generated
once. Every point within the radius is visited exactly once (a search wider than the periodic box is clamped to its
cells once), the others of the box of cells too: callers test the distance.

Launch wrappers at the bottom; they never allocate (the host side, hel_warp/collisions/models.py, owns the arrays).
"""

from __future__ import annotations

import warp as wp

DEAD_CELL_KEY = wp.constant(2147483647)
"""Sort key of a point not in the list (dead parcel): after every cell."""


@wp.struct
class CellList:
    """Points sorted by cell (see the module docstring)."""

    origin: wp.vec3
    """Corner of cell (0, 0, 0), m."""
    inv_width: wp.float32
    """1 / cell width, 1/m."""
    dims: wp.vec3i
    """Cells per axis."""
    periodic: wp.int32
    """1: the cells tile a triply periodic box (searches wrap), 0: open space (searches clamp to the cells)."""
    cell_start: wp.array(dtype=wp.int32)
    """(cells + 1,) first slot of each cell; cell_start[cells] = points listed."""
    slot_key: wp.array(dtype=wp.int32)
    """(2 n,) cell of each slot after the sort (the radix sort's scratch beyond n)."""
    slot_point: wp.array(dtype=wp.int32)
    """(2 n,) point index of each slot (the radix sort's scratch beyond n)."""
    slot_position: wp.array(dtype=wp.vec3)
    """(n,) position of each slot's point, m."""


@wp.func
def cell_coord(cells: CellList, x: float, axis: int):
    """Cell coordinate of a position component, clamped into the cells."""
    c = int(wp.floor((x - cells.origin[axis]) * cells.inv_width))
    return wp.clamp(c, 0, cells.dims[axis] - 1)


@wp.func
def wrap(c: int, d: int):
    """c modulo d (non-negative)."""
    r = c % d
    if r < 0:
        r = r + d
    return r


@wp.func
def clamp_span(cells: CellList, lo: int, hi: int, axis: int):
    """A span of cell coordinates clamped into the cells in open space; in a periodic box kept (wrapped by the
    caller) unless it holds d cells or more: then the d cells once."""
    d = cells.dims[axis]
    if cells.periodic == 0:
        return wp.max(lo, 0), wp.min(hi, d - 1)
    if hi - lo + 1 >= d:
        return 0, d - 1
    return lo, hi


@wp.func
def axis_range(cells: CellList, x: float, radius: float, axis: int):
    """First and last cell coordinate of [x - radius, x + radius] on an axis (``clamp_span``)."""
    lo = int(wp.floor((x - radius - cells.origin[axis]) * cells.inv_width))
    hi = int(wp.floor((x + radius - cells.origin[axis]) * cells.inv_width))
    return clamp_span(cells, lo, hi, axis)


@wp.func
def search_box(cells: CellList, p: wp.vec3, radius: float):
    """The cells of the box [p - radius, p + radius] as a (lo, hi) vec3i pair."""
    x_lo, x_hi = axis_range(cells, p[0], radius, 0)
    y_lo, y_hi = axis_range(cells, p[1], radius, 1)
    z_lo, z_hi = axis_range(cells, p[2], radius, 2)
    return wp.vec3i(x_lo, y_lo, z_lo), wp.vec3i(x_hi, y_hi, z_hi)


@wp.func
def search_box_pair(cells: CellList, p: wp.vec3, radius_p: float, q: wp.vec3, radius_q: float):
    """The cells of the box around both balls (p, radius_p) and (q, radius_q); q within half a periodic box of p (the
    minimum image)."""
    lo_p, hi_p = search_box(cells, p, radius_p)
    lo_q, hi_q = search_box(cells, q, radius_q)
    x_lo, x_hi = clamp_span(cells, wp.min(lo_p[0], lo_q[0]), wp.max(hi_p[0], hi_q[0]), 0)
    y_lo, y_hi = clamp_span(cells, wp.min(lo_p[1], lo_q[1]), wp.max(hi_p[1], hi_q[1]), 1)
    z_lo, z_hi = clamp_span(cells, wp.min(lo_p[2], lo_q[2]), wp.max(hi_p[2], hi_q[2]), 2)
    return wp.vec3i(x_lo, y_lo, z_lo), wp.vec3i(x_hi, y_hi, z_hi)


@wp.func
def range_count(cells: CellList, lo: wp.vec3i, hi: wp.vec3i):
    """Slot ranges of a search box: its (y, z) rows (0 when it is empty), twice in a periodic box."""
    return wp.max(hi[1] - lo[1] + 1, 0) * wp.max(hi[2] - lo[2] + 1, 0) * (1 + cells.periodic)


@wp.func
def row_distance(cells: CellList, x: float, c: int, axis: int):
    """Distance from a position component to the cells of coordinate c on an axis (minimum image when periodic)."""
    width = 1.0 / cells.inv_width
    e = x - (cells.origin[axis] + (float(c) + 0.5) * width)
    if cells.periodic != 0:
        side = float(cells.dims[axis]) * width
        e = e - side * wp.round(e / side)
    return wp.max(wp.abs(e) - 0.5 * width, 0.0)


@wp.func
def chord(cells: CellList, p: wp.vec3, radius: float, cy: int, cz: int):
    """Cells along x of the chord of the ball (p, radius) in row (cy, cz), not clamped; first > last when the row is
    beyond the radius."""
    dy = row_distance(cells, p[1], cy, 1)
    dz = row_distance(cells, p[2], cz, 2)
    chord2 = radius * radius - dy * dy - dz * dz
    if chord2 < 0.0:
        return 1, 0
    half = wp.sqrt(chord2)
    return (int(wp.floor((p[0] - half - cells.origin[0]) * cells.inv_width)),
            int(wp.floor((p[0] + half - cells.origin[0]) * cells.inv_width)))


@wp.func
def row_of_range(lo: wp.vec3i, hi: wp.vec3i, k: int, parts: int):
    """Row (cy, cz) of slot range k of a search box (y fastest; ``parts`` ranges per row)."""
    row = k / parts
    ny = hi[1] - lo[1] + 1
    return lo[1] + row % ny, lo[2] + row / ny


@wp.func
def row_slots(cells: CellList, cy: int, cz: int, x_lo: int, x_hi: int, part: int):
    """Slot range [begin, end) of part 0 or 1 of the cells x_lo..x_hi of row (cy, cz): in a periodic box a span that
    crosses a face in x is two parts (the second empty otherwise), in open space one."""
    if x_lo > x_hi:
        return 0, 0
    x_lo, x_hi = clamp_span(cells, x_lo, x_hi, 0)
    dx = cells.dims[0]
    if cells.periodic != 0:
        cy = wrap(cy, cells.dims[1])
        cz = wrap(cz, cells.dims[2])
        if x_lo < 0:  # the row crosses the face x = 0: [x_lo + d, d) then [0, x_hi]
            if part == 0:
                x_lo = x_lo + dx
                x_hi = dx - 1
            else:
                x_lo = 0
        elif x_hi >= dx:  # the face x = L: [x_lo, d) then [0, x_hi - d]
            if part == 0:
                x_hi = dx - 1
            else:
                x_lo = 0
                x_hi = x_hi - dx
        elif part == 1:
            return 0, 0
    elif part == 1:
        return 0, 0
    first = (cz * cells.dims[1] + cy) * dx
    return cells.cell_start[first + x_lo], cells.cell_start[first + x_hi + 1]


@wp.func
def range_slots(cells: CellList, lo: wp.vec3i, hi: wp.vec3i, k: int, p: wp.vec3, radius: float):
    """Slot range [begin, end) number k of the search of the ball (p, radius) with the box (lo, hi) of
    ``search_box``: part k % 2 of row k / 2 in a periodic box, row k in open space (y fastest). A row farther from p
    than the radius is empty, the others hold only the cells of the ball's chord along x."""
    parts = 1 + cells.periodic
    cy, cz = row_of_range(lo, hi, k, parts)
    x_lo, x_hi = chord(cells, p, radius, cy, cz)
    return row_slots(cells, cy, cz, x_lo, x_hi, k % parts)


@wp.func
def range_slots_pair(cells: CellList, lo: wp.vec3i, hi: wp.vec3i, k: int, p: wp.vec3, radius_p: float, q: wp.vec3,
                     radius_q: float):
    """``range_slots`` of the search of both balls (box of ``search_box_pair``): per row the cells from the first to
    the last of the two chords, so a point in both balls is visited once."""
    parts = 1 + cells.periodic
    cy, cz = row_of_range(lo, hi, k, parts)
    x_lo, x_hi = chord(cells, p, radius_p, cy, cz)
    x_lo_q, x_hi_q = chord(cells, q, radius_q, cy, cz)
    if x_lo_q <= x_hi_q:
        if x_lo > x_hi:
            x_lo = x_lo_q
            x_hi = x_hi_q
        else:
            x_lo = wp.min(x_lo, x_lo_q)
            x_hi = wp.max(x_hi, x_hi_q)
    return row_slots(cells, cy, cz, x_lo, x_hi, k % parts)


@wp.kernel
def bin_points(
    cells: CellList,
    points: wp.array(dtype=wp.vec3),
    alive: wp.array(dtype=wp.int32),
    # outputs
    cell_count: wp.array(dtype=wp.int32),
):
    """Sort keys (cell, x fastest; dead points after every cell) and the points per cell."""
    i = wp.tid()
    key = DEAD_CELL_KEY
    if alive[i] != 0:
        p = points[i]
        key = (cell_coord(cells, p[2], 2) * cells.dims[1] + cell_coord(cells, p[1], 1)) * cells.dims[0] + cell_coord(
            cells, p[0], 0)
        wp.atomic_add(cell_count, key, 1)
    cells.slot_key[i] = key
    cells.slot_point[i] = i


@wp.kernel
def gather_positions(cells: CellList, points: wp.array(dtype=wp.vec3)):
    """slot_position[slot] = points[slot_point[slot]]."""
    slot = wp.tid()
    cells.slot_position[slot] = points[cells.slot_point[slot]]


def build_cell_list(cells: CellList, points, alive, cell_count) -> None:
    """Fill ``cells`` (origin, inv_width, dims, periodic set; arrays sized: cell_start and ``cell_count`` cells + 1,
    slot arrays 2 n) with the live ``points``."""
    n = points.shape[0]
    device = points.device
    cell_count.zero_()
    wp.launch(bin_points, dim=n, device=device, inputs=[cells, points, alive], outputs=[cell_count])
    wp.utils.radix_sort_pairs(cells.slot_key, cells.slot_point, n)
    wp.utils.array_scan(cell_count, cells.cell_start, inclusive=False)
    wp.launch(gather_positions, dim=n, device=device, inputs=[cells, points])

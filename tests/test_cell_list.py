"""The swept detection's sorted cell list (kernels/cell_list.py) against an O(N^2) brute force."""

import numpy as np
import pytest
import warp as wp

from kernels.cell_list import (CellList, build_cell_list, range_count, range_slots, range_slots_pair, search_box,
                               search_box_pair)


@wp.kernel
def neighbours_through_cells(cells: CellList, points: wp.array(dtype=wp.vec3), alive: wp.array(dtype=wp.int32),
                             radius: float, box: wp.vec3,
                             # outputs
                             count: wp.array(dtype=wp.int32), index_sum: wp.array(dtype=wp.int64),
                             visited: wp.array(dtype=wp.int32)):
    """Per live point: the live points within ``radius`` (minimum image when periodic) found by a cell-list search,
    their index sum, and every slot the search visits."""
    i = wp.tid()
    if alive[i] == 0:
        return
    p = points[i]
    c = int(0)
    s = wp.int64(0)
    seen = int(0)
    lo, hi = search_box(cells, p, radius)
    for k in range(range_count(cells, lo, hi)):
        begin, end = range_slots(cells, lo, hi, k, p, radius)
        for slot in range(begin, end):
            j = cells.slot_point[slot]
            d = cells.slot_position[slot] - p
            if cells.periodic != 0:
                d = wp.vec3(d[0] - box[0] * wp.round(d[0] / box[0]), d[1] - box[1] * wp.round(d[1] / box[1]),
                            d[2] - box[2] * wp.round(d[2] / box[2]))
            seen = seen + 1
            if wp.dot(d, d) < radius * radius:
                c = c + 1
                s = s + wp.int64(j)
    count[i] = c
    index_sum[i] = s
    visited[i] = seen


@wp.func
def image(d: wp.vec3, periodic: int, box: wp.vec3):
    if periodic == 0:
        return d
    return wp.vec3(d[0] - box[0] * wp.round(d[0] / box[0]), d[1] - box[1] * wp.round(d[1] / box[1]),
                   d[2] - box[2] * wp.round(d[2] / box[2]))


@wp.kernel
def pair_neighbours_through_cells(cells: CellList, points: wp.array(dtype=wp.vec3), alive: wp.array(dtype=wp.int32),
                                  radius: float, box: wp.vec3, offset: wp.vec3,
                                  # outputs
                                  count: wp.array(dtype=wp.int32), index_sum: wp.array(dtype=wp.int64),
                                  visited: wp.array(dtype=wp.int32)):
    """The same for the union of the balls (p, radius) and (p + offset, radius / 2)."""
    i = wp.tid()
    if alive[i] == 0:
        return
    p = points[i]
    q = p + offset
    c = int(0)
    s = wp.int64(0)
    seen = int(0)
    lo, hi = search_box_pair(cells, p, radius, q, 0.5 * radius)
    for k in range(range_count(cells, lo, hi)):
        begin, end = range_slots_pair(cells, lo, hi, k, p, radius, q, 0.5 * radius)
        for slot in range(begin, end):
            j = cells.slot_point[slot]
            d_p = image(cells.slot_position[slot] - p, cells.periodic, box)
            d_q = image(cells.slot_position[slot] - q, cells.periodic, box)
            seen = seen + 1
            if wp.dot(d_p, d_p) < radius * radius or wp.dot(d_q, d_q) < 0.25 * radius * radius:
                c = c + 1
                s = s + wp.int64(j)
    count[i] = c
    index_sum[i] = s
    visited[i] = seen


def search(points, alive, radius, width, periodic_side=None, offset=None):
    n = len(points)
    cells = CellList()
    if periodic_side is None:
        lo, hi = points[alive != 0].min(axis=0), points[alive != 0].max(axis=0)
        dims = tuple(int(np.floor((h - l) / width)) + 1 for l, h in zip(lo, hi))
        cells.origin, cells.periodic = tuple(float(c) for c in lo), 0
        box = (0.0, 0.0, 0.0)
    else:
        dims = (int(round(periodic_side / width)),) * 3
        width = periodic_side / dims[0]
        cells.origin, cells.periodic = (0.0, 0.0, 0.0), 1
        box = (periodic_side,) * 3
    cells.inv_width, cells.dims = 1.0 / width, dims
    total = int(np.prod(dims))
    cells.cell_start = wp.zeros(total + 1, dtype=wp.int32)
    cells.slot_key, cells.slot_point = wp.zeros(2 * n, dtype=wp.int32), wp.zeros(2 * n, dtype=wp.int32)
    cells.slot_position = wp.zeros(n, dtype=wp.vec3)
    p = wp.array(points, dtype=wp.vec3)
    a = wp.array(alive, dtype=wp.int32)
    build_cell_list(cells, p, a, wp.zeros(total + 1, dtype=wp.int32))
    count, index_sum, visited = wp.zeros(n, dtype=wp.int32), wp.zeros(n, dtype=wp.int64), wp.zeros(n, dtype=wp.int32)
    if offset is None:
        wp.launch(neighbours_through_cells, dim=n, inputs=[cells, p, a, float(radius), box],
                  outputs=[count, index_sum, visited])
    else:
        wp.launch(pair_neighbours_through_cells, dim=n, inputs=[cells, p, a, float(radius), box, tuple(offset)],
                  outputs=[count, index_sum, visited])
    return cells, count.numpy(), index_sum.numpy(), visited.numpy()


def brute_force(points, alive, radius, side=None, offset=None):
    def within_ball(centres, r):
        d = points[None, :, :] - centres[:, None, :]
        if side is not None:
            d = d - side * np.round(d / side)
        return np.sum(d.astype(np.float64) ** 2, axis=2) < r * r

    within = within_ball(points, radius)
    if offset is not None:
        within |= within_ball(points + np.asarray(offset, np.float32), 0.5 * radius)
    within &= alive[None, :] != 0
    within &= alive[:, None] != 0
    return within.sum(axis=1), (within * np.arange(len(points))[None, :]).sum(axis=1)


@pytest.mark.parametrize("periodic", [False, True])
def test_cell_list_search_finds_every_point_within_the_radius_once(periodic):
    # Reference: the O(N^2) set {j : |x_i - x_j| < R} (minimum image in the periodic box), its size and index sum; a
    # point visited twice by a search would raise both. A tenth of the points dead (never listed); in the periodic
    # box searches cross every face and one wider than the box is clamped to its cells once.
    rng = np.random.default_rng(4)
    n, side = 1500, 0.01
    points = rng.uniform(0.0, side, size=(n, 3)).astype(np.float32)
    if not periodic:
        points[:, 2] *= 0.2  # a flat cloud: the box of cells is not cubic
    alive = (rng.uniform(size=n) > 0.1).astype(np.int32)
    for radius, width in ((6e-4, 5e-4), (1.3e-3, 5e-4), (4e-4, 1e-3)) + (((0.006, 2.5e-3),) if periodic else ()):
        cells, count, index_sum, visited = search(points, alive, radius, width, side if periodic else None)
        ref_count, ref_sum = brute_force(points, alive, radius, side if periodic else None)
        live = alive != 0
        assert np.array_equal(count[live], ref_count[live]) and np.array_equal(index_sum[live], ref_sum[live])
        assert int(cells.cell_start.numpy()[-1]) == int(live.sum())
        assert visited[live].max() <= live.sum()  # no slot twice, even for the search wider than the box
        assert count[live].sum() > live.sum()  # neighbours besides itself


@pytest.mark.parametrize("periodic", [False, True])
def test_cell_list_search_of_two_balls_finds_every_point_of_their_union_once(periodic):
    # The causality check's search around both parcels of a pair: the union of the balls (p, R) and (p + offset, R/2)
    # against the O(N^2) union, offsets that overlap the balls, separate them, and cross periodic faces.
    rng = np.random.default_rng(5)
    n, side = 1500, 0.01
    points = rng.uniform(0.0, side, size=(n, 3)).astype(np.float32)
    alive = (rng.uniform(size=n) > 0.1).astype(np.int32)
    for radius, width, offset in ((8e-4, 5e-4, (3e-4, -2e-4, 1e-4)), (6e-4, 5e-4, (0.0, 1.2e-3, -1.1e-3)),
                                  (1.3e-3, 1e-3, (-1.9e-3, 0.0, 0.0))):
        cells, count, index_sum, visited = search(points, alive, radius, width, side if periodic else None, offset)
        ref_count, ref_sum = brute_force(points, alive, radius, side if periodic else None, offset)
        live = alive != 0
        assert np.array_equal(count[live], ref_count[live]) and np.array_equal(index_sum[live], ref_sum[live])
        assert visited[live].max() <= live.sum()

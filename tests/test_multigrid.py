"""Aggregation multigrid preconditioner (hel_warp/gas/multigrid.py) against linear algebra done in numpy.

References: the Galerkin coarse operator A_c = P^T A P with the piecewise-constant prolongation P of the
2 x 2 x 2 aggregates (dense numpy products); CG needs a symmetric positive definite preconditioner
(u.M^-1 v = v.M^-1 u, u.M^-1 u > 0); a multi-colour Gauss-Seidel sweep needs a proper colouring.
"""

import numpy as np
import pytest
import warp as wp

from hel_warp.gas.multigrid import AggregationMultigrid
from kernels.gas import make_stencil


def stencil_system(shape, periodic, fluid, rng, outlet_cells=4):
    """A random 7-point M-matrix on the fluid cells: symmetric couplings c > 0 between face neighbours
    (periodic wrap where set), diag = sum of couplings (+ a Dirichlet term on a few cells so that A is
    definite). Returns compact (diag, coef, neighbour) in the GasSolver format and the dense matrix."""
    rows = np.flatnonzero(fluid.ravel())
    index = -np.ones(fluid.size, dtype=np.int64)
    index[rows] = np.arange(rows.size)
    n = rows.size
    coef = np.zeros((n, 6))
    neighbour = np.tile(np.arange(n)[:, None], (1, 6))
    coords = np.stack(np.unravel_index(rows, shape), axis=1)
    dense = np.zeros((n, n))
    weights = {}
    for r in range(n):
        for axis in range(3):
            for side in range(2):
                c = coords[r].copy()
                c[axis] += 2 * side - 1
                if periodic[axis]:
                    c[axis] %= shape[axis]
                elif not 0 <= c[axis] < shape[axis]:
                    continue
                nb = index[np.ravel_multi_index(c, shape)]
                if nb < 0 or nb == r:
                    continue
                key = (min(r, nb), max(r, nb), axis)
                w = weights.setdefault(key, rng.uniform(0.3, 1.0))
                coef[r, 2 * axis + side] = w
                neighbour[r, 2 * axis + side] = nb
                dense[r, nb] -= w
    diag = -dense.sum(axis=1)
    diag[rng.choice(n, size=outlet_cells, replace=False)] += 2.0
    dense[np.arange(n), np.arange(n)] = diag
    return diag, coef, neighbour, dense, rows


def to_warp(diag, coef, neighbour):
    return make_stencil(wp.array(diag, dtype=wp.float64), wp.array(coef, dtype=wp.float64),
                        wp.array(neighbour.astype(np.int32), dtype=wp.int32))


def built(shape, periodic, seed, solid_fraction=0.3):
    """A random masked-box system (``stencil_system``) and its multigrid, set up: (mg, dense A, rows)."""
    rng = np.random.default_rng(seed)
    fluid = rng.uniform(size=shape) > solid_fraction
    diag, coef, neighbour, dense, rows = stencil_system(shape, periodic, fluid, rng)
    mg = AggregationMultigrid(rows, shape, periodic, None)  # the test run's device (conftest)
    mg.setup(to_warp(diag, coef, neighbour))
    return mg, dense, rows


CASES = [((8, 6, 4), (False, False, False)), ((7, 5, 3), (True, False, True)), ((6, 4, 5), (True, True, True)),
         ((4, 9, 4), (True, True, True))]


@pytest.mark.parametrize("shape,periodic", CASES)
def test_coarse_matrix_is_galerkin_product(shape, periodic):
    mg, dense, rows = built(shape, periodic, seed=3)
    assert len(mg.levels) >= 2
    fine_dense = dense
    for level, coarse in zip(mg.levels[:-1], mg.levels[1:]):
        parent = level.parent.numpy()
        P = np.zeros((level.n, coarse.n))
        P[np.arange(level.n), parent] = 1.0
        expected = P.T @ fine_dense @ P
        got = np.diag(coarse.A.diag.numpy()).astype(float)
        c_coef, c_nb = coarse.A.coef.numpy(), coarse.A.neighbour.numpy()
        for r in range(coarse.n):
            for m in range(6):
                if c_coef[r, m] != 0.0:
                    got[r, c_nb[r, m]] -= c_coef[r, m]
        np.testing.assert_allclose(got, expected, atol=1e-12)
        fine_dense = expected


@pytest.mark.parametrize("shape,periodic", CASES)
def test_colouring_separates_neighbours(shape, periodic):
    mg, dense, rows = built(shape, periodic, seed=4, solid_fraction=0.0)
    for level in mg.levels[:-1]:
        colour = level.colour.numpy()
        c_coef, c_nb = level.A.coef.numpy(), level.A.neighbour.numpy()
        for r in range(level.n):
            for m in range(6):
                if c_coef[r, m] != 0.0:
                    assert colour[c_nb[r, m]] != colour[r], (r, m)


@pytest.mark.parametrize("shape,periodic", CASES)
def test_vcycle_is_symmetric_positive_definite(shape, periodic):
    mg, dense, rows = built(shape, periodic, seed=5)
    n = rows.size
    M_inv = np.zeros((n, n))
    z = wp.zeros(n, dtype=wp.float64)
    for col in range(n):
        e = np.zeros(n)
        e[col] = 1.0
        mg.apply(wp.array(e, dtype=wp.float64), z)
        M_inv[:, col] = z.numpy()
    np.testing.assert_allclose(M_inv, M_inv.T, atol=1e-12 * np.abs(M_inv).max())
    eigenvalues = np.linalg.eigvalsh(0.5 * (M_inv + M_inv.T))
    assert eigenvalues.min() > 0.0
    # and it is a useful preconditioner: M^-1 A better conditioned than A (Jacobi-scaled)
    kappa_pre = np.linalg.cond(np.linalg.cholesky(M_inv).T @ dense @ np.linalg.cholesky(M_inv))
    d = 1.0 / np.sqrt(np.diag(dense))
    kappa_jacobi = np.linalg.cond(d[:, None] * dense * d[None, :])
    assert kappa_pre < 0.5 * kappa_jacobi, (kappa_pre, kappa_jacobi)


def test_a_periodic_axis_of_odd_count_is_halved_with_a_block_of_three_at_its_end():
    # the periodic riser's tile: 4 x 50 x 4 cells, periodic on every axis. 50 -> 25 -> 12 (blocks of two and one of
    # three, cells 22-24) -> 6 -> 3 -> 1: every axis halved at every level, so the coarse cells stay cubes (as wide
    # as they are tall) instead of plates 25 cells across a y of one
    shape, periodic = (16, 50, 16), (True, True, True)
    rows = np.arange(np.prod(shape))
    mg = AggregationMultigrid(rows, shape, periodic, None)
    assert [s[1] for s in mg.shapes] == [50, 25, 12, 6, 3, 1][:len(mg.shapes)]
    assert [s[0] for s in mg.shapes] == [16, 8, 4, 2, 1, 1][:len(mg.shapes)]
    level = mg.levels[1]
    parent = level.parent.numpy()
    coords = np.stack(np.unravel_index(np.arange(level.n), mg.shapes[1]), axis=1)
    block = coords[:, 1] // 2
    coarse_y = np.stack(np.unravel_index(parent, mg.shapes[2]), axis=1)[:, 1]
    np.testing.assert_array_equal(coarse_y, np.minimum(block, 11))
    assert np.count_nonzero(coarse_y[coords[:, 0] + coords[:, 2] == 0] == 11) == 3

"""The parcels' stencil cache (``kernels.interp.ParcelStencil``, ``HelConfig.stencil_cache``).

The cache must change nothing but the time: its rows are ``cic_corner``'s (cell, weight) pairs, and a pass that
reads them adds the same terms in the same order as a pass that computes them. References (docs/developer/conventions.md rule 9):
``stencil_weights`` (the computed corners) for the rows, and the same HelSolver run with the cache switched off
(``HelConfig(stencil_cache=False)``: every pass computes its stencils, the code path before the cache) for the
step, bit for bit, every particle, coupling and gas array.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from hel_warp.parcels.coupling import CouplingFields, GridSpec, interpolate_gas
from kernels.interp import fill_stencil, make_parcel_stencil, stencil_weights

H = 1e-3


def _flat(cells, shape):
    """(n, 8, 3) cell indices -> (n, 8) flat (i ny + j) nz + k."""
    return (cells[..., 0] * shape[1] + cells[..., 1]) * shape[2] + cells[..., 2]


@pytest.mark.parametrize("periodic", [(False, False, False), (True, False, True)])
def test_cache_rows_are_the_computed_corners(periodic, device):
    """Each trilinear parcel's row equals ``cic_corner``'s eight (cell, weight) pairs bit for bit, inside, in the
    outer half cells and past a periodic end; tents (weight 8 with spread) keep no row; ``only_stale`` refills
    exactly the rows of the parcels that moved."""
    rng = np.random.default_rng(3)
    shape = (6, 5, 7)
    grid = GridSpec(origin=(0.1, -0.2, 0.0), spacing=H, shape=shape, periodic=periodic)
    n = 400
    lo, hi = np.array(grid.origin), np.array(grid.origin) + H * np.array(shape)
    x = rng.uniform(lo - 0.8 * H, hi + 0.8 * H, size=(n, 3)).astype(np.float32)
    x[:5] = (lo + 0.5 * H).astype(np.float32)  # exactly on a cell centre (fraction 0)
    weight = np.where(np.arange(n) % 4 == 0, 8.0, 1.0).astype(np.float32)
    g = grid.cell_grid()
    xs = wp.array(x, dtype=wp.vec3, device=device)
    ws = wp.array(weight, dtype=float, device=device)
    stencil = make_parcel_stencil(n, device=device)
    fill_stencil(g, xs, ws, stencil)

    cells = wp.zeros((n, 8), dtype=wp.vec3i, device=device)
    weights = wp.zeros((n, 8), dtype=wp.float64, device=device)
    stencil_weights(g, xs, cells, weights)
    tri = weight == 1.0
    assert np.array_equal(stencil.cell.numpy()[tri], _flat(cells.numpy(), shape)[tri])
    assert np.array_equal(stencil.weight.numpy()[tri], weights.numpy()[tri])
    assert np.array_equal(stencil.x.numpy()[tri], x[tri])
    assert np.all(np.isnan(stencil.x.numpy()[~tri]))  # tents are computed, never cached

    moved = x.copy()
    moved[1::3] += np.float32(0.37 * H)
    before_cell, before_weight = stencil.cell.numpy(), stencil.weight.numpy()
    xs.assign(moved)
    fill_stencil(g, xs, ws, stencil, only_stale=True)
    stencil_weights(g, xs, cells, weights)
    assert np.array_equal(stencil.cell.numpy()[tri], _flat(cells.numpy(), shape)[tri])
    assert np.array_equal(stencil.weight.numpy()[tri], weights.numpy()[tri])
    still = np.ones(n, bool)
    still[1::3] = False
    assert np.array_equal(stencil.cell.numpy()[still], before_cell[still])
    assert np.array_equal(stencil.weight.numpy()[still], before_weight[still])


def test_interpolation_computes_the_rows_of_moved_parcels(device):
    """A cache filled before some parcels moved is read only where it holds: the interpolation equals the
    uncached one bit for bit (the rows of the moved parcels are stale and must not be used)."""
    rng = np.random.default_rng(5)
    shape = (7, 6, 5)
    grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=H, shape=shape, periodic=(False, True, False))
    n = 600
    x = rng.uniform(0.0, H * np.array(shape), size=(n, 3)).astype(np.float32)
    parts = _Parts(x, np.where(np.arange(n) % 5 == 0, 8.0, 1.0), device)
    stencil = make_parcel_stencil(n, device=device)
    fill_stencil(grid.cell_grid(), parts.x, parts.weight, stencil)
    x[::2] += np.float32(0.61 * H)
    parts.x.assign(x)
    velocity = wp.array(rng.normal(size=shape + (3,)).astype(np.float32), dtype=wp.vec3, device=device)
    grad_p = wp.array(rng.normal(size=shape + (3,)).astype(np.float32), dtype=wp.vec3, device=device)
    eps_s = rng.uniform(0.0, 0.3, shape).astype(np.float32)
    out = {}
    for key, s in (("cached", stencil), ("computed", None)):
        fields = CouplingFields.allocate(grid, n, device=device)
        fields.cell_eps_s.assign(eps_s)
        interpolate_gas(grid, parts, velocity, grad_p, fields, stencil=s)
        out[key] = {"u_f": fields.parcel_u_f.numpy(), "grad_p": fields.parcel_grad_p.numpy(),
                    "eps_s": fields.parcel_eps_s.numpy()}
    for name in ("u_f", "grad_p", "eps_s"):
        assert np.array_equal(out["cached"][name], out["computed"][name]), name


class _Parts:
    """The particle arrays ``interpolate_gas`` reads."""

    def __init__(self, x, weight, device):
        self.x = wp.array(x, dtype=wp.vec3, device=device)
        self.weight = wp.array(np.asarray(weight, np.float32), dtype=float, device=device)


class _Nudge:
    """A collision strategy that moves every third parcel between the interpolation and the push (as a
    collision's position change would): the exchange must compute those parcels' stencils again."""

    name = "none"

    def accelerate(self, solver) -> None:
        p = solver.pool.particles
        x = p.x.numpy()
        x[::3] += np.float32(0.29 * H)
        p.x.assign(x)


def _solver(*, cache: bool, mixed: bool, periodic: bool, nudge: bool, device, n=3000, shape=(10, 8, 9)):
    """The bench's box (``scripts/bench_hel.py`` ``make_solver``: random parcels and gas velocity), small;
    ``mixed``: every other parcel of weight 8 (a tent of 2^3 x 8 cells beside trilinear parcels); ``periodic``:
    x periodic (the box reaches past the grid's x ends, so no wall there)."""
    from hel_warp.parcels.coupling import PushConfig
    from hel_warp.gas.solver import GasConfig, GasField, GasSolver
    from hel_warp.gas.grid import Box, Geometry, Grid
    from hel_warp.hel import HelConfig, HelSolver
    from hel_warp.parcels.pool import ParcelPool

    hi = tuple(s * H for s in shape)
    grid = Grid(spacing=H, shape=shape, periodic=(periodic, False, False))
    lo_box = (-10 * H if periodic else 0.0, 0.0, 0.0)
    hi_box = (hi[0] + 10 * H if periodic else hi[0], hi[1], hi[2])
    domain = Geometry(shapes=(Box(lo=lo_box, hi=hi_box),)).build(grid, device=device)
    push = PushConfig()
    gas_solver = GasSolver(domain, GasConfig(density=push.fluid_density, viscosity=push.fluid_viscosity),
                           device=device)
    gas = GasField(domain, device=device)
    rng = np.random.default_rng(7)
    gas.cell_velocity.assign(rng.normal(0.0, 0.5, shape + (3,)).astype(np.float32))
    x = rng.uniform([0.5 * H] * 3, [s - 0.5 * H for s in hi], size=(n, 3)).astype(np.float32)
    if periodic:
        x[::7, 0] = rng.uniform(0.0, 0.5 * H, size=x[::7].shape[0])  # in the wrapped outer half cells
    pool = ParcelPool.empty(n + 16, device=device)  # a few unused slots
    p = pool.particles
    p.x.assign(np.concatenate([x, np.zeros((16, 3), np.float32)]))
    p.v.assign(np.concatenate([rng.normal(0.0, 0.1, size=(n, 3)), np.zeros((16, 3))]).astype(np.float32))
    weight = np.where(np.arange(n) % 2 == 1, 8.0, 1.0) if mixed else np.ones(n)
    p.weight.assign(np.concatenate([weight, np.ones(16)]).astype(np.float32))
    p.radius.assign(np.full(n + 16, 1e-4, np.float32))
    p.density.assign(np.full(n + 16, 1000.0, np.float32))
    alive = np.concatenate([np.ones(n), np.zeros(16)]).astype(np.int32)
    alive[::97] = 0  # some dead parcels among the live ones
    p.alive.assign(alive)
    p.particle_id.assign(np.arange(n + 16, dtype=np.int32))
    pool.used = n
    config = HelConfig(push=push, stencil_cache=cache, sort_every=2)
    return HelSolver(pool=pool, gas_solver=gas_solver, gas=gas, config=config,
                     collision=_Nudge() if nudge else None)


def _arrays(solver) -> dict:
    """Every per-parcel, coupling and gas array of the run, host copies."""
    out = {}
    p = solver.pool.particles
    for name in ("x", "v", "radius", "density", "weight", "alive", "particle_id"):
        out[f"particles.{name}"] = getattr(p, name).numpy()
    for f in dataclasses.fields(solver.fields):
        out[f"fields.{f.name}"] = getattr(solver.fields, f.name).numpy()
    for name in ("cell_velocity", "cell_grad_p", "cell_eps_s", "cell_momentum_source", "cell_drag_coeff"):
        out[f"gas.{name}"] = getattr(solver.gas, name).numpy()
    return out


@pytest.mark.parametrize("mixed, periodic, nudge", [(False, False, False), (True, True, False), (True, False, True)],
                         ids=["bench-box", "mixed-weights-periodic", "mixed-weights-moved-before-push"])
def test_steps_with_the_cache_are_bitwise_those_without(mixed, periodic, nudge, device):
    """Five HEL steps (deposit, gas step, interpolation, implicit exchange push, walls; a parcel sort every two)
    with and without the cache: every array equal bit for bit (NaN-aware: unused slots hold no NaN, but compare
    as such). Cases: the bench's box with trilinear parcels; weights 1 and 8 (tents beside trilinear parcels) on
    a grid periodic in x; a strategy that moves parcels after the interpolation (stale rows)."""
    runs = {}
    for cache in (True, False):
        solver = _solver(cache=cache, mixed=mixed, periodic=periodic, nudge=nudge, device=device)
        assert (solver.stencil is not None) == cache
        for _ in range(5):
            solver.step()
        runs[cache] = _arrays(solver)
    assert runs[True].keys() == runs[False].keys()
    for name, cached in runs[True].items():
        assert np.array_equal(cached, runs[False][name], equal_nan=cached.dtype.kind == "f"), name
    moved = np.abs(runs[True]["particles.v"]).max()
    assert moved > 0.0 and np.abs(runs[True]["fields.cell_gas_impulse"]).max() > 0.0  # the steps did something

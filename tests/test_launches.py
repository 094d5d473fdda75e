"""Recorded launches (``kernels.launches.LaunchCache``): a replayed launch must pass the kernel what a fresh
``wp.launch`` would. References (docs/developer/conventions.md rule 9): ``wp.launch`` itself for the values, and the same HelSolver
run with plain launches (``fields.launches = None``) for the step, bit for bit, every array.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from kernels.launches import LaunchCache
from test_stencil_cache import _arrays, _solver


@wp.struct
class _Scale:
    factor: float


@wp.kernel
def _affine(scale: _Scale, x: wp.array(dtype=float), offset: float, out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = scale.factor * x[i] + offset


def test_replayed_launch_follows_every_argument(device):
    """A launch is recorded once per argument set: replayed with the same arguments it adds no entry and gives
    wp.launch's values; a struct changed in place, another scalar or another array is recorded again (a stale
    replay would keep the old factor, offset or array)."""
    x = wp.array(np.arange(5, dtype=np.float32), dtype=float, device=device)
    y = wp.array(np.full(5, 10.0, np.float32), dtype=float, device=device)
    out = wp.zeros(5, dtype=float, device=device)
    scale = _Scale()
    scale.factor = 2.0
    cache = LaunchCache()

    def run(arr, offset):
        cache.launch(_affine, dim=5, inputs=[scale, arr, offset], outputs=[out], device=device)
        return out.numpy().copy()

    assert np.array_equal(run(x, 1.0), 2.0 * np.arange(5) + 1.0)
    assert np.array_equal(run(x, 1.0), 2.0 * np.arange(5) + 1.0) and len(cache) == 1
    scale.factor = 3.0
    assert np.array_equal(run(x, 1.0), 3.0 * np.arange(5) + 1.0) and len(cache) == 2
    assert np.array_equal(run(x, -1.0), 3.0 * np.arange(5) - 1.0) and len(cache) == 3
    assert np.array_equal(run(y, -1.0), np.full(5, 29.0)) and len(cache) == 4
    x.assign(np.ones(5, np.float32))  # new values in the same array: the recorded launch reads them
    assert np.array_equal(run(x, -1.0), np.full(5, 2.0)) and len(cache) == 4


def test_steps_with_recorded_launches_are_bitwise_those_without(device):
    """Five HEL steps (weights 1 and 8, x periodic, a sort every two) with the coupling's recorded launches and
    with plain ``wp.launch``: every particle, coupling and gas array equal bit for bit."""
    runs = {}
    for recorded in (True, False):
        solver = _solver(cache=True, mixed=True, periodic=True, nudge=False, device=device)
        if not recorded:
            solver.fields.launches = None
        for _ in range(5):
            solver.step()
        if recorded:
            assert len(solver.fields.launches) > 0
        runs[recorded] = _arrays(solver)
    for name, value in runs[True].items():
        assert np.array_equal(value, runs[False][name], equal_nan=value.dtype.kind == "f"), name

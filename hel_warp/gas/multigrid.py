"""Aggregation multigrid V-cycle: the preconditioner of the pressure CG (``GasConfig.pressure_preconditioner``).

The pressure system lives on the fluid cells of a box grid (``GasSolver``'s compact rows). Level l + 1
aggregates 2 x 2 x 2 blocks of level l (an axis down to one cell is not halved; a periodic axis of odd count
ends in a block of three, ``_halved``); the coarse matrices are Galerkin products with the piecewise-constant
prolongation, A_c = P^T A P, rebuilt every step from the fine matrix (eps_f changes) and again 7-point stencils. One
application z = M^-1 r is a V-cycle from z = 0: per level ``sweeps`` multi-colour Gauss-Seidel sweeps
before (colours ascending) and after (descending), the residual restricted by summation, the coarse
correction prolonged times ``scale`` (piecewise-constant prolongation under-corrects smooth errors;
Braess 1995 scales by ~1.8, Notay 2010 discusses why), symmetric Gauss-Seidel sweeps on the coarsest level.
The cycle is a fixed symmetric linear map, as CG needs. Coarse matrices and restricted residuals are gathered per coarse row from its fine rows in a fixed order
(no float atomics: the same numbers on any device). On the CPU the cycle's row loops are the native ones of
``kernels/gas_cpu.py`` (the same numbers). Colours: parity of i + j + k, or (with a periodic
axis of odd count, where parity does not separate neighbours across the wrap) the sum mod 3 of per-axis
colours {0, 1} with 2 on the last cell of such an axis — a proper colouring of the product graph.

References: Braess, *Towards algebraic multigrid for elliptic problems of second order*, Computing 55
(1995) 379-393; Notay, *An aggregation-based algebraic multigrid method*, ETNA 37 (2010) 123-146.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from kernels import gas as K
from kernels import gas_cpu

COARSEST_ROWS = 32
"""Stop coarsening below this many rows (the CPU's default)."""
COARSEST_ROWS_CUDA = 4
"""The same on a GPU, where the coarsest level's symmetric Gauss-Seidel sweeps run on one thread (20 sweeps of the
rig's 26 coarsest rows: 0.3 ms of every V-cycle on an H200): a level more, of a few rows."""
RECORDED_CYCLES = 8
"""V-cycles and set-ups kept recorded (``wp.launch(record_cmd=True)``), one per (r, z, fine matrix) memory seen
(set-up: per fine matrix memory); a replay skips the argument packing of ~40 launches (~25 us each on the CPU,
most of a coarse level's smoothing)."""


def _colours(coords: np.ndarray, shape: tuple, periodic: tuple) -> tuple[np.ndarray, int]:
    odd_wrap = [bool(periodic[a]) and shape[a] % 2 == 1 and shape[a] > 1 for a in range(3)]
    per_axis = coords % 2
    if not any(odd_wrap):
        return (per_axis.sum(axis=1) % 2).astype(np.int32), 2
    for a in range(3):
        if odd_wrap[a]:
            per_axis[coords[:, a] == shape[a] - 1, a] = 2
    return (per_axis.sum(axis=1) % 3).astype(np.int32), 3


def _halved(shape: tuple, periodic: tuple, coords: np.ndarray) -> tuple[tuple, np.ndarray]:
    """The next level's shape and each row's coarse coordinates: every axis of more than one cell halved into
    intervals of two cells. An odd count ends in a single cell, or, on a periodic axis (whose last cell borders the
    first), in one interval of three, so that the coarse cells stay a periodic lattice: a periodic axis of odd count
    left unhalved (a riser's 50 cells after one level) makes the coarse cells flat plates, strongly coupled across
    that axis, which the point smoother damps poorly: on the periodic riser the pressure CG took 8 / 9 / 12
    iterations at 896 / 14,336 / 229,376 parcels, halved like the other axes 5 at each."""
    coarse_shape, coarse = [], coords.copy()
    for a in range(3):
        n = shape[a]
        if n == 1:
            coarse_shape.append(1)
        elif periodic[a] and n % 2 == 1:
            coarse_shape.append(n // 2)
            coarse[:, a] = np.minimum(coords[:, a] // 2, n // 2 - 1)
        else:
            coarse_shape.append(-(-n // 2))
            coarse[:, a] = coords[:, a] // 2
    return tuple(coarse_shape), coarse


class _Level:
    def __init__(self, n: int, device, colour: np.ndarray, n_colours: int, fine: bool):
        self.n = n
        # the finest level takes the solver's matrix (``setup``) and its r, z (``apply``); coarse ones own theirs
        self.A = None if fine else K.make_stencil(wp.zeros(n, dtype=wp.float64, device=device),
                                                  wp.zeros((n, 6), dtype=wp.float64, device=device),
                                                  wp.zeros((n, 6), dtype=wp.int32, device=device))
        self.b = None if fine else wp.zeros(n, dtype=wp.float64, device=device)
        self.z = None if fine else wp.zeros(n, dtype=wp.float64, device=device)
        self.inverse_diag = wp.zeros(n, dtype=wp.float64, device=device)
        """1 / diag of A (0 where diag is 0), rebuilt by ``setup``."""
        self.colour = wp.array(colour, dtype=wp.int32, device=device)
        self.n_colours = n_colours
        self.colour_rows = [wp.array(np.flatnonzero(colour == c).astype(np.int32), dtype=wp.int32, device=device)
                            for c in range(n_colours)]
        self.schedules = {}  # colour sequence -> its wp.array (``AggregationMultigrid._smooth`` on the CPU)
        self.parent = None  # row of the next level, per row
        self.child_start = None  # rows of the previous level in this row's block: children[child_start[r]:...]
        self.children = None


class AggregationMultigrid:
    """Levels built once from the solved rows (box indices ``rows`` of ``shape``); ``setup`` takes the
    fine matrix of every step, ``apply`` is the preconditioner."""

    def __init__(self, rows: np.ndarray, shape: tuple, periodic: tuple, device, *, sweeps: int = 2,
                 scale: float = 1.8, coarsest_sweeps: int = 20, coarsest_rows: int = COARSEST_ROWS):
        self.device = wp.get_device(device)
        self.sweeps, self.scale, self.coarsest_sweeps = int(sweeps), float(scale), int(coarsest_sweeps)
        if self.sweeps < 1:
            raise ValueError(f"sweeps must be >= 1 (got {sweeps})")
        self._recorded: dict[tuple, list] = {}
        shape = tuple(int(v) for v in shape)
        coords = np.stack(np.unravel_index(np.asarray(rows, dtype=np.int64), shape), axis=1)
        self.levels: list[_Level] = []
        self.shapes = [shape]
        fine = None
        while True:
            colour, n_colours = _colours(coords, shape, periodic)
            level = _Level(coords.shape[0], self.device, colour, n_colours, fine=fine is None)
            if fine is not None:
                fine.parent = wp.array(parent, dtype=wp.int32, device=self.device)
                order = np.argsort(parent, kind="stable").astype(np.int32)  # fine rows by block, ascending
                start = np.concatenate([[0], np.cumsum(np.bincount(parent, minlength=level.n))]).astype(np.int32)
                level.children = wp.array(order, dtype=wp.int32, device=self.device)
                level.child_start = wp.array(start, dtype=wp.int32, device=self.device)
            self.levels.append(level)
            if level.n <= coarsest_rows or max(shape) == 1:
                break
            coarse_shape, coarse_coords = _halved(shape, periodic, coords)
            flat = np.ravel_multi_index(coarse_coords.T, coarse_shape)
            unique, parent = np.unique(flat, return_inverse=True)
            coords = np.stack(np.unravel_index(unique, coarse_shape), axis=1)
            shape, fine = coarse_shape, level
            self.shapes.append(shape)

    @property
    def rows_per_level(self) -> list[int]:
        return [level.n for level in self.levels]

    def setup(self, A: K.Stencil) -> None:
        """Take the fine matrix (compact arrays, n rows) and build the coarse ones (the launches recorded once per
        fine matrix memory, like ``apply``'s)."""
        fine = self.levels[0]
        fine.A = A
        key = ("setup", A.diag.ptr, A.coef.ptr, A.neighbour.ptr, A.diag.shape[0])
        launches = self._recorded.get(key)
        if launches is None:
            if len(self._recorded) >= RECORDED_CYCLES:
                self._recorded.pop(next(iter(self._recorded)))
            launches = self._recorded[key] = []
            for level, coarse in zip(self.levels[:-1], self.levels[1:]):
                self._record(launches, K.mg_coarsen_kernel, coarse.n,
                             [coarse.child_start, coarse.children, level.parent, level.A], [coarse.A])
            for level in self.levels:
                self._record(launches, K.mg_inverse_diagonal_kernel, level.n, [level.A], [level.inverse_diag])
        for launch in launches:
            launch.launch()

    def record(self, r, z) -> list:
        """The V-cycle's launches for (r, z) and the fine matrix of the last ``setup``, recorded on first use (no
        launch). Call it before a graph capture that holds ``apply(r, z)``: recording allocates the CPU smoother's
        colour schedules from host lists, and a capture on the CPU defers that copy to each replay of the graph,
        reading a host buffer that is freed by then (the device-side CG loop of the pressure then took ~20 times
        the host loop's iterations from its second solve on)."""
        fine = self.levels[0].A
        key = (r.ptr, z.ptr, fine.diag.ptr, fine.coef.ptr, fine.neighbour.ptr, r.shape[0])
        launches = self._recorded.get(key)
        if launches is None:
            if len(self._recorded) >= RECORDED_CYCLES:
                self._recorded.pop(next(iter(self._recorded)))
            launches = self._recorded[key] = []
            self._cycle(0, r, z, launches)
        return launches

    def apply(self, r, z) -> None:
        """z = M^-1 r (one V-cycle from z = 0)."""
        for launch in self.record(r, z):
            launch.launch()

    def _record(self, launches: list, kernel, dim: int, inputs: list, outputs: list) -> None:
        if dim:  # the native row loops on the CPU (kernels/gas_cpu.py)
            kernel, dim = gas_cpu.for_device(kernel, dim, self.device, inputs + outputs)
            launches.append(wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=self.device,
                                      record_cmd=True))

    def _smooth(self, level: _Level, b, z, colours, launches: list) -> None:
        """Gauss-Seidel updates of the rows of each colour in ``colours``, in order: one launch per colour, or on the
        CPU one launch for the whole sequence (``gas_cpu.mg_smooth_schedule_kernel``: the same updates in the same
        order)."""
        colours = list(colours)
        if not colours:
            return
        if gas_cpu.for_device(K.mg_smooth_kernel, 1, self.device, [])[0] is not K.mg_smooth_kernel:  # the CPU
            schedule = level.schedules.get(tuple(colours))
            if schedule is None:
                schedule = level.schedules[tuple(colours)] = wp.array(colours, dtype=wp.int32, device=self.device)
            rows = [level.colour_rows[min(c, level.n_colours - 1)] for c in range(3)]
            self._record(launches, gas_cpu.mg_smooth_schedule_kernel, 1,
                         [level.A, level.inverse_diag, *rows, schedule, b], [z])
            return
        for c in colours:
            rows = level.colour_rows[c]
            self._record(launches, K.mg_smooth_kernel, rows.shape[0], [level.A, level.inverse_diag, rows, b], [z])

    def _cycle(self, index: int, b, z, launches: list) -> None:
        """Record the launches of the V-cycle from level ``index`` down (``apply`` replays them)."""
        level = self.levels[index]
        if index == len(self.levels) - 1:
            self._record(launches, K.mg_coarsest_kernel, 1,
                         [level.A, level.inverse_diag, b, level.n, self.coarsest_sweeps], [z])
            return
        ascending = list(range(level.n_colours))
        # pre-smoothing from z = 0: the first colour's first update fused with the zeroing
        self._record(launches, K.mg_smooth_from_zero_kernel, level.n, [level.inverse_diag, level.colour, b], [z])
        self._smooth(level, b, z, ascending[1:] + ascending * (self.sweeps - 1), launches)
        coarse = self.levels[index + 1]
        self._record(launches, K.mg_residual_restrict_kernel, coarse.n,
                     [coarse.child_start, coarse.children, level.parent, level.A, b, z, level.colour, ascending[-1]], [coarse.b])
        self._cycle(index + 1, coarse.b, coarse.z, launches)
        self._record(launches, K.mg_prolong_kernel, level.n, [level.parent, coarse.z, wp.float64(self.scale)], [z])
        self._smooth(level, b, z, ascending[::-1] * self.sweeps, launches)

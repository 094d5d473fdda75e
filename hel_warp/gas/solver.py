"""Gas phase of the HEL / MP-PIC step: state (``GasField``) and the step (``GasSolver``).

Paper eqs. (1)-(3) with constant gas density, on the MAC grid of ``kernels/gas.py``:
semi-Lagrangian advection, particle momentum source, backward-Euler viscous step with
molecular + Smagorinsky viscosity, and a pressure projection onto
``d(eps_f)/dt + div(eps_f u) = 0``; both linear systems (7-point stencils assembled once per step) are solved
with a native CG on every device (``GasConfig.linear_solver``; ``warp.optim.linear.cg`` on request):
the pressure preconditioned with an aggregation V-cycle, the viscous systems reduced to their black rows (red-black
elimination) and preconditioned with the diagonal (``GasConfig.viscous_preconditioner``); each iteration a
captured graph, its dot products in fixed chunks (``device_tuning``: the CPU's and a GPU's shapes). On the CPU the step's hot loops (the linear solvers, the advection, the cell and
face passes) run as native C++ loops over raw pointers (``kernels/gas_cpu.py``: the same numbers, ~2x faster on the
colliding-streams rig).

Interface with the particle side (``kernels/deposit.py``, ``kernels/interp.py``):
before ``GasSolver.step`` fill ``cell_eps_s``, ``cell_momentum_source`` (N s per cell over
the step, = minus the drag impulses the particles received) and ``cell_drag_coeff``; after
it read ``cell_velocity`` and ``cell_grad_p`` (gradient of the modified pressure
``p' = p - rho_f g.x``, including any imposed mean gradient).

The momentum source is applied explicitly: each cell's impulse is split evenly over its two
faces per axis, so the gas gets exactly the impulse the particles lost, except the half of a
wall cell's wall-normal impulse that goes straight to that wall (where the gas pressure would
carry it anyway). ``cell_drag_coeff`` is accepted but not used by this step.

Known simplifications: the transposed-gradient and bulk parts of the stress, eq. (3), are
dropped (exact for constant eps_f mu_eff and a solenoidal u); the viscous wall condition puts
no-slip walls on cell faces (staircase for inclined channels); advection takes a zero-gradient
tangential velocity just outside an inlet (the viscous step uses the inlet vector there); the
projection is first order in time; explicit drag on the gas can
overshoot in dense cells at large dt.
"""

from __future__ import annotations

import sys
import time
import weakref
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import warp as wp
import warp.optim.linear as wpl

from hel_warp.errors import ConfigError, HelWarpError, require_finite, require_positive
from hel_warp.gas.grid import FlowDomain
from hel_warp.gas.multigrid import COARSEST_ROWS, COARSEST_ROWS_CUDA, AggregationMultigrid
from kernels import gas as K
from kernels import gas_cpu

FLOAT32_FLOOR = 1e-7
"""Continuity residual below which the float32 face velocities cannot resolve it, relative to the
gross face flux through the cells (floor of the pressure solver's absolute tolerance)."""

FLOAT32_UNIT_ROUNDOFF = 2.0**-24
"""Unit round-off of float32 (5.96e-8): the relative error of rounding a value to the stored float32."""


class _FloorOf(NamedTuple):
    """A CG's absolute floor scale * sqrt(sums[index]) from a device array: the device-side loop takes it there
    (``kernels/gas.py`` ``pcg_params_floor_kernel``), the other paths read it back (``GasSolver._host_floor``)."""

    sums: object
    index: int
    scale: float


def _check_solve(what: str, iterations, residual: float, atol: float, since: str = "") -> None:
    """HelWarpError for a CG solve of ``what`` ('pressure', 'viscous (x)') that produced NaN/inf or stopped above
    its bound; ``since``: how many failed since the last check (deferred checks)."""
    kind = "pressure" if what == "pressure" else "viscous"
    if not np.isfinite(residual):
        raise HelWarpError(f"{what} solve produced NaN/inf (residual {residual}){since}; the gas state blew up: "
                           "reduce dt or check the inputs (eps_s, momentum source) for NaN")
    if residual > atol:
        raise HelWarpError(f"{what} solve did not converge: residual {residual:.3e} > {atol:.3e} after {iterations} "
                           f"CG iterations{since}; raise {kind}_max_iterations, loosen {kind}_tolerance, or reduce dt")


@dataclass(frozen=True, kw_only=True)
class GasConfig:
    """Gas properties and solver controls (SI units)."""

    density: float = 1.205
    """Gas density rho_f, kg/m^3 (air at 20 C)."""
    viscosity: float = 1.81e-5
    """Molecular dynamic viscosity mu_f, Pa s (air at 20 C)."""
    smagorinsky_constant: float = 0.17
    """C_s of the Smagorinsky sub-grid viscosity; 0 switches it off (laminar)."""
    eps_f_min: float = 0.37
    """Lower clip of eps_f = 1 - eps_s (1 - packing limit 0.63)."""
    mean_pressure_gradient: tuple = (0.0, 0.0, 0.0)
    """Imposed mean gradient of p' (Pa/m), e.g. to drive a periodic duct; reported in cell_grad_p."""
    inlet_superficial: bool = False
    """eps_f = 1 on the inlet faces: the inlet velocity is the superficial velocity of the gas entering (a
    distributor under a bed: CFDEMcoupling's inlets hold voidfraction 1). False: the face takes the mean eps_f of
    its cells, so solids beside an inlet cut its flux (the dilute rig's inlets, whose figures were measured so)."""
    pressure_tolerance: float = 1e-7
    """Relative residual of the pressure (continuity) system."""
    pressure_max_iterations: int = 5000
    pressure_preconditioner: str = "multigrid"
    """Preconditioner of the pressure CG: 'multigrid' (an aggregation V-cycle, hel_warp/gas/multigrid.py; both
    linear solvers) or 'ic' (incomplete Cholesky, see the relaxation below, on the 'native' solver; Jacobi
    on 'warp')."""
    pressure_multigrid_scale: float = 2.0
    """Factor on the prolonged coarse correction of the 'multigrid' preconditioner (``AggregationMultigrid``'s
    ``scale``): piecewise-constant prolongation under-corrects smooth errors (Braess 1995: ~1.8; Notay 2010). The
    V-cycle stays a symmetric positive definite preconditioner up to 2 (the scaled coarse correction I - s P A_c^-1
    P^T A has A-norm max(1, |1 - s|) <= 1 there, and the smoothing sweeps around it contract). 2.0 takes 8-9 CG
    iterations on the colliding-streams rig where 1.8 takes 10, and 5 where 1.8 takes 6 on 16^3-32^3 cubes, at the
    same tolerance."""
    pressure_preconditioner_relaxation: float = 0.97
    """tau of the modified incomplete Cholesky of the 'ic' preconditioner: 0 is plain IC(0); 0.97
    (Bridson 2015) takes 120 iterations on the rig where IC(0) takes 180."""
    viscous_tolerance: float = FLOAT32_UNIT_ROUNDOFF
    """Relative residual of each viscous system (||b - A u|| <= tol ||b||). The default is float32's unit
    round-off, 2^-24 = 5.96e-8: the solution is stored as float32 face velocities, and rounding even the exact
    solution to float32 leaves a relative residual of 3.6-5.7e-8 on the colliding-streams rig (the three
    components, measured; A is dominated by its diagonal there, so the residual of a rounding is about the
    rounding itself), so a tighter tolerance (1e-8 before) buys digits the stored field cannot keep. On the rig it
    takes 6 / 6 / 6 IC(0)-PCG iterations where 1e-8 took 6 / 7 / 7."""
    viscous_max_iterations: int = 1000
    viscous_preconditioner: str = "red_black"
    """Preconditioner of the viscous CG on the 'native' solver: 'red_black' (Jacobi-PCG on the red-black reduced
    system, kernels/gas.py "red-black reduced system": the red rows eliminated, half the unknowns, about half
    Jacobi's iterations, no factorisation; a system with a coupling between rows of one colour, a periodic axis
    with an odd count, takes 'ic0'), 'ic0' (incomplete Cholesky, factored every step, two sequential substitutions
    per iteration) or 'jacobi' (the diagonal, one streaming pass per iteration). Every one stops at the same
    ``viscous_tolerance``. On the colliding-streams rig (off-diagonal sums 0.44 of the diagonal, median; 0.79 at
    most) the three components take 8 / 8 / 8 iterations with 'red_black', 6 / 6 / 6 with 'ic0', 15 / 16 / 16
    with 'jacobi', and the viscous step costs 0.75 of its 'ic0' time (0.92 with 'jacobi'; ``scripts/bench_hel.py --profile-gas``). The 'warp' solver always takes Jacobi."""
    linear_solver: str = "auto"
    """'warp' (warp.optim.linear.cg, Jacobi preconditioner), 'native' (PCG with the preconditioners above,
    deterministic atomic reductions and one captured graph per iteration, kernels/gas.py; a GPU's chunks and coarsest
    level from ``device_tuning``), or 'auto': native on every device. On the CPU warp's tile-based dot products cost
    ~0.1 s each at 1e5 unknowns; on an H200 the rig's step took 116 ms with 'warp' (1,280 launches and copies, the
    device busy 23 % of it) against 67 ms with 'native' (30 ms with the GPU's dot chunks and coarsest level;
    ``scripts/profile_step.py rig --device cuda``)."""
    pcg_device_loop: bool = False
    """The native CG as one captured graph per system whose iterations loop on the device (``wp.capture_while``,
    the stop test in a kernel): one read-back per solve instead of one per iteration (~33 per rig step, each a sync
    on a GPU). The same bits as the host loop (tests/test_gas.py), NaN cases included, and as fast on the CPU
    (21.8 against 22.1 ms of gas per rig step). Off here by default; ``HelSolver`` turns it on with
    ``HelConfig.read_back`` 'output' (the CUDA default). A driver without graph conditional nodes falls back to
    the host loop with a warning."""
    check_finite: bool = True
    """Raise HelWarpError when a NaN/inf appears (one int read back per step; with ``deferred_checks`` at
    ``GasSolver.check``)."""
    deferred_checks: bool = False
    """Steps without a device-to-host read (with ``pcg_device_loop`` on the native solver): the CG solves log their
    iterations and failures (not converged, NaN) on the device, the NaN cells accumulate there, the pressure's
    float32 floor is taken on the device, and ``GasSolver.check()`` reads them, raising the error a step would
    have raised, at the caller's pace (``HelSolver`` does at each output: ``HelConfig.read_back``). On a GPU
    every read is a sync that stalls the queue of launches; the numbers are the same bits either way."""

    def __post_init__(self) -> None:
        require_positive("gas density", self.density, "kg/m^3")
        require_positive("gas viscosity", self.viscosity, "Pa s")
        require_finite("smagorinsky_constant", self.smagorinsky_constant)
        if self.smagorinsky_constant < 0.0:
            raise ConfigError(f"smagorinsky_constant must be >= 0 (got {self.smagorinsky_constant})")
        if not 0.0 < self.eps_f_min <= 1.0:
            raise ConfigError(f"eps_f_min must lie in (0, 1] (got {self.eps_f_min})")
        object.__setattr__(self, "mean_pressure_gradient",
                           tuple(float(v) for v in np.asarray(self.mean_pressure_gradient, dtype=float)))
        require_finite("mean_pressure_gradient", self.mean_pressure_gradient)
        for name in ("pressure_tolerance", "viscous_tolerance"):
            value = getattr(self, name)
            if not 0.0 < value < 1.0:
                raise ConfigError(f"{name} must lie in (0, 1) (got {value})")
        if not 0.0 < self.pressure_multigrid_scale <= 2.0:
            raise ConfigError("pressure_multigrid_scale must lie in (0, 2] (beyond 2 the V-cycle can stop being positive "
                              f"definite and CG can fail; got {self.pressure_multigrid_scale})")
        if not 0.0 <= self.pressure_preconditioner_relaxation <= 1.0:
            raise ConfigError("pressure_preconditioner_relaxation must lie in [0, 1] "
                              f"(got {self.pressure_preconditioner_relaxation})")
        if self.pressure_preconditioner not in ("multigrid", "ic"):
            raise ConfigError(f"pressure_preconditioner must be 'multigrid' or 'ic' (got {self.pressure_preconditioner!r})")
        if self.viscous_preconditioner not in ("ic0", "jacobi", "red_black"):
            raise ConfigError("viscous_preconditioner must be 'ic0', 'jacobi' or 'red_black' "
                              f"(got {self.viscous_preconditioner!r})")
        if self.linear_solver not in ("auto", "warp", "native"):
            raise ConfigError(f"linear_solver must be 'auto', 'warp' or 'native' (got {self.linear_solver!r})")
        for name in ("pressure_max_iterations", "viscous_max_iterations"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"{name} must be >= 1 (got {getattr(self, name)})")


@dataclass(frozen=True)
class RedBlackSplit:
    """A viscous system's rows by colour (kernels/gas.py "red-black reduced system"), fixed at set-up."""

    black_rows: wp.array
    """Compact rows of colour 0 (parity of the face's i + j + k), ascending; int32, (n_b,)."""
    red_rows: wp.array
    """Compact rows of colour 1, ascending; int32, (n_r,)."""
    black_other: wp.array
    """Per black row and slot, the index among ``red_rows`` of the slot's neighbour (0 where the slot is unused);
    int32, (n_b, 6)."""
    red_other: wp.array
    """Per red row and slot, the index among ``black_rows`` of the slot's neighbour; int32, (n_r, 6)."""


class GasField:
    """Changing gas state on a ``FlowDomain`` (updated in place by ``GasSolver.step``).

    Cell arrays are ``wp.array3d`` indexed [i, j, k]; face arrays follow ``kernels/gas.py``.
    """

    def __init__(self, domain: FlowDomain, device=None):
        grid = domain.grid
        shape = grid.shape
        self.domain = domain
        self.face_velocity = self._faces(grid, device)
        """MAC face velocity components, m/s (float32, shape + e_axis)."""
        self.face_eps = self._faces(grid, device, fill=1.0)
        """eps_f on faces (used by the last projection)."""
        self.face_kappa = self._faces(grid, device)
        """eps_f (mu + rho nu_t) on faces, Pa s."""
        self.face_kappa_flat = tuple(a.flatten() for a in (self.face_kappa.x, self.face_kappa.y, self.face_kappa.z))
        """``face_kappa`` per axis as flat views of the same memory (indexed by flat face index)."""
        self.cell_velocity = wp.zeros(shape, dtype=wp.vec3, device=device)
        """Cell-centred gas velocity, m/s."""
        self.cell_pressure = wp.zeros(shape, dtype=float, device=device)
        """Modified pressure p' less the imposed mean-gradient part, Pa."""
        self.cell_grad_p = wp.zeros(shape, dtype=wp.vec3, device=device)
        """grad p' at cell centres (imposed mean gradient included), Pa/m."""
        self.cell_eps_s = wp.zeros(shape, dtype=float, device=device)
        """Solid volume fraction (input from deposit)."""
        self.cell_eps_f = wp.ones(shape, dtype=float, device=device)
        """Gas volume fraction of the last step, clip(1 - eps_s, eps_f_min, 1)."""
        self.cell_eps_f_prev = wp.ones(shape, dtype=float, device=device)
        """Gas volume fraction of the step before (for d eps_f/dt)."""
        self.cell_momentum_source = wp.zeros(shape, dtype=wp.vec3, device=device)
        """Momentum given to the gas over the step, N s per cell (input from deposit)."""
        self.cell_drag_coeff = wp.zeros(shape, dtype=float, device=device)
        """Sum of beta V per cell, kg/s (input; unused by the explicit source treatment)."""
        self.cell_nu_t = wp.zeros(shape, dtype=float, device=device)
        """Smagorinsky sub-grid kinematic viscosity, m^2/s."""
        self.pressure_solution = wp.zeros(int(np.prod(shape)), dtype=wp.float64, device=device)
        """Pressure p^n (float64, flat, Pa) of the incremental projection."""
        self._started = False
        self.set_face_velocity(self.face_arrays())  # inlet faces start at their velocity

    @staticmethod
    def _faces(grid, device, fill: float = 0.0) -> K.FaceFloat:
        faces = K.FaceFloat()
        arrays = []
        for axis in range(3):
            shape = list(grid.shape)
            shape[axis] += 1
            arrays.append(wp.full(tuple(shape), fill, dtype=float, device=device))
        faces.x, faces.y, faces.z = arrays
        return faces

    def face_arrays(self, faces: K.FaceFloat | None = None) -> tuple:
        """Host copies (numpy) of a face struct's three arrays (default: the velocity)."""
        faces = self.face_velocity if faces is None else faces
        return faces.x.numpy(), faces.y.numpy(), faces.z.numpy()

    def set_face_velocity(self, components) -> None:
        """Set the face velocities from three numpy arrays (fixed faces are reset to their BC)."""
        for axis, arr in enumerate(components):
            target = (self.face_velocity.x, self.face_velocity.y, self.face_velocity.z)[axis]
            types = (self.domain.face_type.x, self.domain.face_type.y, self.domain.face_type.z)[axis].numpy()
            bc = (self.domain.face_bc.velocity_x, self.domain.face_bc.velocity_y,
                  self.domain.face_bc.velocity_z)[axis].numpy()[..., axis]
            values = np.asarray(arr, dtype=np.float32).copy()
            if values.shape != tuple(target.shape):
                raise ConfigError(f"face velocity {axis} must have shape {tuple(target.shape)} (got {values.shape})")
            fixed = (types == int(K.FACE_WALL)) | (types == int(K.FACE_INLET))
            values[fixed] = bc[fixed]
            alias = types == int(K.FACE_ALIAS)
            if alias.any():
                first = [slice(None)] * 3
                first[axis] = 0
                last = [slice(None)] * 3
                last[axis] = -1
                values[tuple(last)] = values[tuple(first)]
            target.assign(values)


RECORDED_LAUNCHES = 256
"""Cell and face launches ``GasSolver._launch`` keeps recorded (~40 per step and GasField; the oldest go first)."""

LAUNCH_OVER = ("fluid", "box")
"""What ``GasSolver`` launches its cell and face kernels over (``launch_over``)."""


def _index_list(mask: np.ndarray, device) -> wp.array:
    """The (i, j, k) of the true entries of ``mask``, in ascending flat order, as a ``wp.vec3i`` array."""
    return wp.array(np.argwhere(mask).astype(np.int32).reshape(-1, 3), dtype=wp.vec3i, device=device)


def _touches_fluid(fluid: np.ndarray, axis: int, periodic: bool) -> np.ndarray:
    """Faces of ``axis`` with a fluid cell on either side (the periodic wrap as ``wrap_cell``): the faces whose
    eps_f and kappa are means over cells (kernels/gas.py ``face_coefficients_one``)."""
    n = fluid.shape[axis]
    index = np.arange(n + 1)
    out = np.zeros(tuple(s + (a == axis) for a, s in enumerate(fluid.shape)), dtype=bool)
    for cell in (index - 1, index):
        valid = (cell >= 0) & (cell < n)
        if periodic:
            cell, valid = cell % n, np.ones_like(valid)
        side = np.take(fluid, np.clip(cell, 0, n - 1), axis=axis)
        shape = [1, 1, 1]
        shape[axis] = n + 1
        out |= side & valid.reshape(shape)
    return out



def device_tuning(device) -> dict:
    """The native solvers' shapes for ``device`` (a ``wp.Device``): rows per thread of the PCG's dot-product passes
    (``dot_chunk``: kernels/gas.py DOT_CHUNK, DOT_CHUNK_CUDA) and the multigrid's coarsest level (``coarsest_rows``:
    hel_warp/gas/multigrid.py COARSEST_ROWS, COARSEST_ROWS_CUDA). A CPU thread runs its rows fast and the threads one
    after another; a GPU thread runs its rows slowly and the threads side by side. The same CG either way, its sums
    in another order (tests/test_gas.py runs the GPU's shapes on the CPU)."""
    if device.is_cpu:
        return {"dot_chunk": K.DOT_CHUNK, "coarsest_rows": COARSEST_ROWS}
    return {"dot_chunk": K.DOT_CHUNK_CUDA, "coarsest_rows": COARSEST_ROWS_CUDA}


class GasSolver:
    """One gas step per call; fixed data (domain, config, index lists) here, changing data in ``GasField``.

    ``launch_over``: ``'fluid'`` (default) launches the cell kernels over the fluid cells and the face kernels
    over the faces they update (solved faces; faces next to a fluid cell for eps_f and kappa; alias faces for the
    periodic copy); the solid cells and the faces away from the fluid hold constants (eps_f 1, velocity 0, nu_t 0,
    pressure 0, grad p' the imposed mean gradient; face eps_f 1, kappa 0), written once per ``GasField``. ``'box'``
    launches the same kernels over every cell and face of the box, every step (the reference the fluid launches
    are tested against: the same fields)."""

    def __init__(self, domain: FlowDomain, config: GasConfig | None = None, device=None, *,
                 launch_over: str = "fluid"):
        if launch_over not in LAUNCH_OVER:
            raise ConfigError(f"launch_over must be one of {LAUNCH_OVER} (got {launch_over!r})")
        self.domain = domain
        self.config = config or GasConfig()
        self.device = wp.get_device(device)
        self.launch_over = launch_over
        self._recorded_launches = {}  # _launch's recorded cell and face launches, by kernel and arguments
        self._params_cache = {}  # dt -> FlowParams (_params)
        self.time_phases = False
        """True: :meth:`step` times its four phases into :attr:`timings` (s), synchronising the device after each
        (CUDA launches are asynchronous); what ``scripts/bench_rig.py`` reports per gas phase."""
        self.timings: dict = {}
        """The last step's wall clock per phase (``update_cell_state``, ``advect``, ``add_forces_and_diffuse``,
        ``project``), when :attr:`time_phases`."""
        grid = domain.grid
        self.grid_info = grid.info()
        self._n_cells = int(np.prod(grid.shape))
        dev = self.device
        fluid = domain.cell_fluid.numpy() != 0
        box = launch_over == "box"
        # index lists (kernels/gas.py "Launches"), built once from the mask and the face types
        self._fluid_cells = _index_list(np.ones_like(fluid) if box else fluid, dev)
        """Cells the cell kernels run over every step."""
        self._solid_cells = _index_list(~fluid, dev)
        """Cells that hold the solid constants (written once per GasField)."""
        self._solved_faces, self._coefficient_faces, self._alias_faces, self._far_faces = [], [], [], []
        self._inlet_faces = []
        """Per axis the inlet faces: eps_f = 1 on them (``K.inlet_face_eps_kernel``: the patch velocity is the
        superficial velocity of the gas entering, whatever solids lie beside the inlet)."""
        solved_masks = []
        for axis, types in enumerate((domain.face_type.x, domain.face_type.y, domain.face_type.z)):
            t = types.numpy()
            solved = (t == int(K.FACE_FLUID)) | (t == int(K.FACE_OUTLET))
            near = _touches_fluid(fluid, axis, bool(grid.periodic[axis]))
            every = np.ones_like(solved)
            solved_masks.append(solved.ravel())
            self._solved_faces.append(_index_list(every if box else solved, dev))
            self._coefficient_faces.append(_index_list(every if box else near, dev))
            self._alias_faces.append(_index_list(every if box else t == int(K.FACE_ALIAS), dev))
            self._far_faces.append(_index_list(~near, dev))
            self._inlet_faces.append(_index_list(t == int(K.FACE_INLET), dev))
        self._fluid_sum = wp.zeros(3, dtype=wp.float64, device=dev)
        # solved rows only (kernels/gas.py "compacted systems"): fluid cells, solved faces per axis
        self._systems = {"pressure": self._row_map(fluid.ravel())}
        for axis in range(3):
            self._systems[axis] = self._row_map(solved_masks[axis])
        # one stencil per system; its neighbour rows are fixed by the mask and face types, written here once
        self._stencils = {system: self._new_stencil(max(1, rows.shape[0]))
                          for system, (rows, _) in self._systems.items()}
        """The compact matrix of each system (kernels/gas.py ``Stencil``): coefficients by the assembly kernels every
        step, neighbour rows once at set-up."""
        self._viscous_topology = [self._viscous_stencil_topology(axis) for axis in range(3)]
        self._red_black = [self._red_black_split(axis) for axis in range(3)]
        """Per viscous system its ``RedBlackSplit`` (kernels/gas.py "red-black reduced system"), or None where a
        coupling joins two rows of one colour."""
        self._launch(K.pressure_neighbours_kernel, self._fluid_cells,
                     [self.grid_info, self._fluid_cells, self._systems["pressure"][1], domain.cell_fluid,
                      domain.face_type, self._stencils["pressure"]])
        self._pressure_mg = None
        if self.config.pressure_preconditioner == "multigrid":
            self._pressure_mg = AggregationMultigrid(self._systems["pressure"][0].numpy(), grid.shape,
                                                     tuple(bool(p) for p in grid.periodic), dev,
                                                     scale=self.config.pressure_multigrid_scale,
                                                     coarsest_rows=device_tuning(self.device)["coarsest_rows"])
        n_rows = max(1, max(rows.shape[0] for rows, _ in self._systems.values()))
        self._c_rhs, self._c_x = (wp.zeros(n_rows, dtype=wp.float64, device=dev) for _ in range(2))
        self._c_active = wp.zeros(n_rows, dtype=wp.int32, device=dev)
        self._pcg = [wp.zeros(n_rows, dtype=wp.float64, device=dev) for _ in range(4)]  # r, z, p, Ap
        self._scalars = wp.zeros(6, dtype=wp.float64, device=dev)  # kernels/gas.py "native Jacobi-PCG"
        self._coefficients = wp.zeros(6, dtype=wp.float64, device=dev)  # alpha, beta as read beside the dot sums
        self._rb = [wp.zeros(n_rows, dtype=wp.float64, device=dev) for _ in range(5)]  # x_b, t, b_r, D_r^-1, D_b^-1
        self._pivot = wp.zeros(n_rows, dtype=wp.float64, device=dev)
        self._pivot_inverse = wp.zeros(n_rows, dtype=wp.float64, device=dev)
        self._pressure_increment = wp.zeros(self._n_cells, dtype=wp.float64, device=dev)
        """dp of the last projection (flat, box-sized; 0 in solid cells)."""
        solver = self.config.linear_solver
        # 'warp' (warp.optim.linear.cg, our V-cycle as M) on request, tested on the CPU: tests/test_device_paths.py
        self.linear_solver = "native" if solver == "auto" else solver
        """The linear solver actually used ('warp' or 'native')."""
        self.dot_chunk = device_tuning(self.device)["dot_chunk"]
        """Rows one thread of the native PCG's dot-product passes sums (``kernels/gas.py`` DOT_CHUNK on the CPU,
        DOT_CHUNK_CUDA on a GPU)."""
        self._bad = wp.zeros(1, dtype=wp.int32, device=dev)
        self._velocity_tmp = GasField._faces(grid, dev)
        self._face_grad_p = GasField._faces(grid, dev)
        """d p / d x_axis of the new pressure at the solved faces (kernels/gas.py ``pressure_correct_one``), Pa/m."""
        self._cell_kappa = wp.zeros(grid.shape, dtype=float, device=dev)
        self._pcg_recorded = {}  # system -> the native PCG's recorded launches (_pcg_launches)
        self._pcg_graphs = {}  # (system, rows, preconditioner) -> one captured PCG iteration (_pcg_iteration_graph)
        self._pcg_solve_graphs = {}  # (system, rows, kind) -> a whole CG (_device_loop_pcg)
        self._pcg_stop = wp.zeros(3, dtype=wp.float64, device=dev)  # bound, ||r||, iterations
        self._pcg_params = wp.zeros(3, dtype=wp.float64, device=dev)  # tol, atol_floor, maxiter
        self._device_loop_warned = False
        self._pcg_more = wp.zeros(1, dtype=wp.int32, device=dev)  # the while loop's condition
        self._solve_log = wp.full((4, 7), -1.0, dtype=wp.float64, device=dev)  # kernels/gas.py pcg_log_kernel
        self._log_unread = False
        self.device_loop = bool(self.config.pcg_device_loop)
        """``GasConfig.pcg_device_loop`` (may be changed between steps)."""
        self.deferred_checks = bool(self.config.deferred_checks)
        """``GasConfig.deferred_checks`` (may be changed between steps; ``check`` first)."""
        self._ordered_slots = int(not any(bool(v) for v in grid.periodic))
        """1 when every compact system couples a row to lower rows only through slots -x, -y, -z (no axis
        periodic: no coupling wraps around), which ``ic0_step_apply_kernel`` then takes without index tests."""
        self._primed = weakref.WeakSet()  # GasFields whose solid cells and far faces hold the constants
        self._last_iterations = {"pressure": 0, "viscous": [0, 0, 0]}

    @staticmethod
    def _host_floor(atol_floor) -> float:
        """A CG's absolute floor on the host: a float, or ``_FloorOf`` read back."""
        if isinstance(atol_floor, _FloorOf):
            return atol_floor.scale * float(np.sqrt(atol_floor.sums.numpy()[atol_floor.index]))
        return float(atol_floor)

    @property
    def last_iterations(self) -> dict:
        """CG iterations of the last step (diagnostic): {'pressure': n, 'viscous': [nx, ny, nz]}. With deferred
        checks the solves log them on the device, and asking reads the log (a sync on a GPU)."""
        if self._log_unread:
            self._read_log()
        return self._last_iterations

    def _read_log(self) -> np.ndarray:
        log = self._solve_log.numpy().copy()
        self._log_unread = False
        for slot, row in enumerate(log):
            if row[0] < 0.0:  # no solve of this system since the last read
                continue
            if slot == 3:
                self._last_iterations["pressure"] = int(row[0])
            else:
                self._last_iterations["viscous"][slot] = int(row[0])
        return log

    def _deferring(self) -> bool:
        """Checks deferred to ``check`` this step: asked for, and the native CG looping on the device."""
        return self.deferred_checks and self.device_loop and self.linear_solver == "native"

    def check(self) -> None:
        """With deferred checks: read what the steps since the last call logged on the device (two reads) and
        raise the HelWarpError a step would have raised at once: NaN/inf in the gas field, a CG solve that produced
        NaN or did not converge. Without deferred checks nothing is pending (the steps checked themselves)."""
        if not (self.deferred_checks or self._log_unread):
            return
        log = self._read_log()
        bad = int(self._bad.numpy()[0]) if self.config.check_finite else 0
        self._solve_log.fill_(-1.0)  # column 0 < 0: no solve since this read; column 3 <= 0: no failure
        self._bad.zero_()
        for slot, row in enumerate(log):
            if row[3] > 0.0:
                what = "pressure" if slot == 3 else f"viscous ({'xyz'[slot]})"
                _check_solve(what, int(row[4]), float(row[5]), float(row[6]),
                             f" ({int(row[3])} failed solves since the last check)")
        if bad > 0:
            raise HelWarpError(f"gas field held NaN/inf in {bad} cell-steps since the last check; "
                               "reduce dt or check eps_s and the momentum source for NaN")

    # ------------------------------------------------------------------ private building blocks
    def _params(self, dt: float) -> K.FlowParams:
        """The ``FlowParams`` of a step of ``dt``: one struct per dt, kept (``_launch`` records launches by the
        identity of their arguments)."""
        params = self._params_cache.get(dt)
        if params is None:
            if len(self._params_cache) >= RECORDED_LAUNCHES:
                self._params_cache.pop(next(iter(self._params_cache)))
            params = self._params_cache[dt] = self._new_params(dt)
        return params

    def _new_params(self, dt: float) -> K.FlowParams:
        c = self.config
        params = K.FlowParams()
        params.rho = float(c.density)
        params.mu = float(c.viscosity)
        params.smagorinsky = float(c.smagorinsky_constant)
        params.eps_min = float(c.eps_f_min)
        params.body_accel = wp.vec3(*(-g / c.density for g in c.mean_pressure_gradient))
        params.dt = float(dt)
        return params

    def _launch(self, kernel, items, inputs):
        """The kernel over the index list ``items`` (the list is the kernel's input named in ``inputs``), ``block``
        entries per thread (kernels/gas.py "Launches": ``CPU_BLOCK`` on the CPU, one on CUDA)."""
        n = items.shape[0]
        if not n:
            return
        # recorded once per kernel and arguments (the same objects: arrays, structs; scalars by value), replayed
        # after: packing a launch's struct arguments costs ~70 us of host time on the CPU (~35 launches per step)
        key = (kernel.key, *(v if isinstance(v, (int, float)) else id(v) for v in (items, *inputs)))
        entry = self._recorded_launches.get(key)
        if entry is None:
            if len(self._recorded_launches) >= RECORDED_LAUNCHES:
                self._recorded_launches.pop(next(iter(self._recorded_launches)))
            block = 1 if self.device.is_cuda else K.CPU_BLOCK
            dim = (n + block - 1) // block
            kernel, dim = gas_cpu.for_device(kernel, dim, self.device, inputs)  # native loops on the CPU
            launch = wp.launch(kernel, dim=dim, inputs=[block, *inputs], device=self.device, record_cmd=True)
            # the arguments are kept with the launch: an id is not reused while its object lives
            entry = self._recorded_launches[key] = (launch, (items, *inputs))
        entry[0].launch()

    def _row_map(self, solved: np.ndarray) -> tuple:
        """(rows, box_to_row) of a system whose solved box rows are ``solved`` (see ``_solve``)."""
        rows = np.flatnonzero(solved).astype(np.int32)
        box_to_row = np.full(solved.shape[0], -1, dtype=np.int32)
        box_to_row[rows] = np.arange(rows.shape[0], dtype=np.int32)
        return (wp.array(rows, dtype=wp.int32, device=self.device),
                wp.array(box_to_row, dtype=wp.int32, device=self.device))

    def _viscous_stencil_topology(self, axis: int) -> K.ViscousTopology:
        """The fixed neighbour classification of the viscous system of ``axis`` (kernels/gas.py
        ``ViscousTopology``), one row per solved face."""
        dev, dom = self.device, self.domain
        n = max(1, self._systems[axis][0].shape[0])
        topology = K.ViscousTopology()
        topology.neighbour_flat = wp.full((n, 6), -1, dtype=wp.int32, device=dev)
        topology.factor = wp.zeros((n, 6), dtype=float, device=dev)
        topology.value = wp.zeros((n, 6), dtype=float, device=dev)
        faces = self._solved_faces[axis]
        self._launch(K.viscous_topology_kernel, faces, [self.grid_info, axis, faces, self._systems[axis][1],
                                                        dom.face_type, dom.face_bc, topology, self._stencils[axis]])
        return topology

    def _red_black_split(self, axis: int):
        """The red-black split of the viscous system of ``axis`` (colour: parity of the face's i + j + k), or None
        if a coupled slot (its neighbour row not the row itself) joins two rows of one colour."""
        rows = self._systems[axis][0].numpy()
        n = rows.shape[0]
        shape = list(self.domain.grid.shape)
        shape[axis] += 1
        colour = np.sum(np.unravel_index(rows, shape), axis=0) % 2
        neighbour = self._stencils[axis].neighbour.numpy()[:n]
        coupled = neighbour != np.arange(n)[:, None]
        black, red = np.flatnonzero(colour == 0), np.flatnonzero(colour == 1)
        if not black.size or not red.size or np.any(colour[neighbour][coupled] == np.broadcast_to(
                colour[:, None], neighbour.shape)[coupled]):
            return None
        index = np.zeros(n, dtype=np.int32)
        index[black], index[red] = np.arange(black.size), np.arange(red.size)
        other = np.where(coupled, index[neighbour], 0).astype(np.int32)  # unused slot: coef 0, any index
        as_array = lambda a: wp.array(np.ascontiguousarray(a), dtype=wp.int32, device=self.device)  # noqa: E731
        return RedBlackSplit(black_rows=as_array(black), red_rows=as_array(red), black_other=as_array(other[black]),
                             red_other=as_array(other[red]))

    def _new_stencil(self, n: int) -> K.Stencil:
        """An empty compact matrix of ``n`` rows (every slot unused: coefficient 0, pointing at its own row)."""
        neighbour = np.repeat(np.arange(n, dtype=np.int32)[:, None], 6, axis=1)
        return K.make_stencil(wp.zeros(n, dtype=wp.float64, device=self.device),
                              wp.zeros((n, 6), dtype=wp.float64, device=self.device),
                              wp.array(neighbour, dtype=wp.int32, device=self.device))

    def _prime(self, gas: GasField) -> None:
        """Once per GasField: the constants of the solid cells and of the faces away from the fluid, which the
        fluid launches never write (the cell kernels' and ``face_coefficients_one``'s solid branches)."""
        if gas in self._primed:
            return
        g, dom, params, solid = self.grid_info, self.domain, self._params(1.0), self._solid_cells
        for target in (gas.cell_eps_f, gas.cell_eps_f_prev):
            self._launch(K.eps_f_kernel, solid, [solid, gas.cell_eps_s, dom.cell_fluid, params.eps_min, target])
        self._launch(K.cell_velocity_kernel, solid, [g, solid, dom.cell_fluid, gas.face_velocity, gas.cell_velocity])
        self._launch(K.smagorinsky_kernel, solid, [g, params, solid, dom.cell_fluid, gas.cell_velocity,
                                                   gas.cell_eps_f, gas.cell_nu_t, self._cell_kappa])
        self._launch(K.cell_pressure_kernel, solid, [g, params, solid, dom.cell_fluid, dom.face_type, self._face_grad_p,
                                                     gas.pressure_solution, gas.cell_pressure, gas.cell_grad_p])
        for axis in range(3):
            far = self._far_faces[axis]
            self._launch(K.FACE_COEFFICIENTS_KERNELS[axis], far, [g, far, dom.cell_fluid, gas.cell_eps_f,
                                                                  self._cell_kappa, gas.face_eps, gas.face_kappa])
        self._primed.add(gas)

    def _solve(self, system, what: str, tol: float, maxiter: int, atol_floor: float = 0.0,
               relaxation: float = 0.0, multigrid: AggregationMultigrid | None = None,
               preconditioner: str = "ic0") -> int:
        """CG (see ``GasConfig.linear_solver``) of the compact system the assembly kernels wrote (``_c_rhs``,
        ``_c_x`` as the first guess, ``_stencils[system]``; ``system``: a key of ``_systems``); the solution is
        left in ``_c_x``. Preconditioner: ``multigrid`` if given, else on the native solver ``preconditioner``
        (``GasConfig.viscous_preconditioner``; 'ic0' modified by ``relaxation`` > 0); Jacobi on warp's."""
        rows, _ = self._systems[system]
        n = rows.shape[0]
        if n == 0:
            return 0
        A = self._stencils[system]
        rhs, x, diag = self._c_rhs[:n], self._c_x[:n], A.diag
        if multigrid is not None:
            multigrid.setup(A)
        if self.linear_solver == "native":
            iterations, residual, atol = self._native_pcg(system, n, A, tol, maxiter, atol_floor, relaxation,
                                                          multigrid, preconditioner)
            if iterations is None:  # deferred: logged on the device, read by ``check``
                return None
        else:
            atol_floor = self._host_floor(atol_floor)
            def matvec(xv, yv, zv, alpha, beta):
                wp.launch(K.stencil_matvec_kernel, dim=n, inputs=[A, xv, yv, wp.float64(alpha), wp.float64(beta)],
                          outputs=[zv], device=self.device)

            operator = wpl.LinearOperator(shape=(n, n), dtype=wp.float64, device=self.device, matvec=matvec)

            def jacobi(xv, yv, zv, alpha, beta):
                wp.launch(K.jacobi_kernel, dim=n, inputs=[diag, xv, yv, wp.float64(alpha), wp.float64(beta)],
                          outputs=[zv], device=self.device)

            def vcycle(xv, yv, zv, alpha, beta):  # warp's cg calls M with alpha = 1, beta = 0
                assert alpha == 1.0 and beta == 0.0
                multigrid.apply(xv, zv)

            M = wpl.LinearOperator(shape=(n, n), dtype=wp.float64, device=self.device,
                                   matvec=jacobi if multigrid is None else vcycle)
            iterations, residual, atol = wpl.cg(operator, rhs, x, tol=tol, atol=atol_floor, maxiter=maxiter, M=M, check_every=10,
                                                use_cuda_graph=False)
        _check_solve(what, iterations, residual, atol)
        return int(iterations)

    def _pcg_launches(self, system, n: int, A: K.Stencil, relaxation: float) -> dict:
        """The launches of the native PCG of ``system`` on its compact arrays (fixed memory, fixed n), recorded
        once (``wp.launch(record_cmd=True)``) and replayed every solve: ~200 launches per step whose argument
        packing cost ~25 us each on the CPU."""
        launches = self._pcg_recorded.get(system)
        if launches is not None:
            return launches
        rhs, x, pivot, pivot_inverse = self._c_rhs[:n], self._c_x[:n], self._pivot[:n], self._pivot_inverse[:n]
        r, z, p, ap = (v[:n] for v in self._pcg)
        s, c, dev = self._scalars, self._coefficients, self.device
        chunk = self.dot_chunk
        dot_dim = (n + chunk - 1) // chunk

        def record(kernel, dim, inputs, outputs):  # the native row loops on the CPU (kernels/gas_cpu.py)
            kernel, dim = gas_cpu.for_device(kernel, dim, dev, inputs + outputs)
            return wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=dev, record_cmd=True)

        def dot(a, b, slot):
            return record(K.pcg_dot_kernel, dot_dim, [a, b, slot, chunk], [s])

        launches = {
            "r = b - A x, b.b, r.r": record(K.pcg_residual_start_kernel, dot_dim, [A, x, rhs, chunk], [r, s]),
            "r.z new": dot(r, z, 2),
            "r.z new, r.r": record(K.pcg_dot_pair_kernel, dot_dim, [r, z, 2, 3, chunk], [s]),
            "ap, p.ap": record(K.pcg_matvec_dot_kernel, dot_dim, [A, p, 1, chunk], [ap, s]),
            "alpha": record(K.pcg_ratio_kernel, 1, [0, 1, 4], [s, c]),
            "step": record(K.pcg_step_kernel, n, [p, ap, s], [x, r]),
            "step, ic0 apply": record(K.ic0_step_apply_kernel, 1, [pivot_inverse, A, p, ap, s, n, self._ordered_slots],
                                      [x, r, z]),
            "beta": record(K.pcg_ratio_kernel, 1, [2, 0, 5], [s, c]),
            "direction": record(K.pcg_direction_kernel, n, [z, s], [p]),
            "shift": record(K.pcg_shift_kernel, 1, [], [s]),
            "ic0 factor": record(K.ic0_factor_kernel, 1, [A, n, wp.float64(relaxation)], [pivot, pivot_inverse]),
            "ic0 apply": record(K.ic0_apply_kernel, 1, [pivot_inverse, A, r, n], [z]),
            "jacobi start": record(K.jacobi_start_kernel, n, [A.diag, r], [pivot_inverse, z]),
            "step, jacobi, r.z new, r.r": record(K.jacobi_step_dot_kernel, dot_dim, [pivot_inverse, p, ap, c, chunk],
                                                 [x, r, z, s]),
        }
        split = self._red_black[system] if system in (0, 1, 2) else None
        if split is not None:  # the reduced system's CG on the black rows (``_red_black_pcg``)
            n_b, n_r = split.black_rows.shape[0], split.red_rows.shape[0]
            x_b, inverse_b = self._rb[0][:n_b], self._rb[4][:n_b]
            t, b_r, inverse_r = (v[:n_r] for v in self._rb[1:4])
            r_b, z_b, p_b, ap_b = (v[:n_b] for v in self._pcg)
            black_dim = (n_b + chunk - 1) // chunk
            red = [A, split.red_rows, split.red_other, inverse_r, b_r]
            launches.update({
                "b.b": dot(rhs, rhs, 1),
                "rb gather black": record(K.rb_gather_kernel, n_b, [split.black_rows, A.diag, x], [inverse_b, x_b]),
                "rb gather red": record(K.rb_gather_kernel, n_r, [split.red_rows, A.diag, rhs], [inverse_r, b_r]),
                "rb x_r": record(K.rb_red_kernel, n_r, [*red, wp.float64(1.0), x_b], [t]),
                "rb residual, r.r": record(K.rb_black_residual_kernel, black_dim,
                                           [A, split.black_rows, split.black_other, rhs, x_b, t, chunk], [r_b, s]),
                "rb N p": record(K.rb_red_kernel, n_r, [*red, wp.float64(0.0), p_b], [t]),
                "rb ap, p.ap": record(K.rb_black_matvec_dot_kernel, black_dim,
                                      [A, split.black_rows, split.black_other, p_b, t, chunk], [ap_b, s]),
                "rb step, jacobi, r.z new, r.r": record(K.jacobi_step_dot_kernel, black_dim,
                                                        [inverse_b, p_b, ap_b, c, chunk], [x_b, r_b, z_b, s]),
                "rb direction": record(K.pcg_direction_kernel, n_b, [z_b, s], [p_b]),
                "rb scatter black": record(K.rb_scatter_kernel, n_b, [split.black_rows, x_b], [x]),
                "rb scatter red": record(K.rb_scatter_kernel, n_r, [split.red_rows, t], [x]),
            })
        self._pcg_recorded[system] = launches
        return launches

    def _native_pcg(self, system, n: int, A: K.Stencil, tol: float, maxiter: int, atol_floor: float = 0.0,
                    relaxation: float = 0.0, multigrid: AggregationMultigrid | None = None,
                    preconditioner: str = "ic0") -> tuple:
        """CG on the compact system, preconditioned with ``multigrid`` (set up), else the diagonal ('jacobi') or
        (modified, ``relaxation`` > 0) IC(0) of the stencil ('ic0') (kernels/gas.py ``pcg_*``, ``jacobi_*``,
        ``ic0_*``), or on its red-black reduced system ('red_black', ``_red_black_pcg``); stops at ||r|| <= max(tol
        ||b||, atol_floor) like warp's cg. Returns (iterations, ||r||, that bound)."""
        run = {name: launch.launch for name, launch in self._pcg_launches(system, n, A, relaxation).items()}
        if multigrid is None and preconditioner == "red_black" and system in (0, 1, 2) and self._red_black[system]:
            return self._red_black_pcg(system, n, run, tol, maxiter, atol_floor)
        jacobi = multigrid is None and preconditioner == "jacobi"
        r, z, p = (v[:n] for v in self._pcg[:3])
        s = self._scalars
        if multigrid is not None:
            def precondition():
                multigrid.apply(r, z)
        elif jacobi:
            precondition = "jacobi"
        else:
            precondition = None

        def start():
            s.zero_()
            run["r = b - A x, b.b, r.r"]()

        def prepare():
            if precondition is None:
                run["ic0 factor"]()
                run["ic0 apply"]()
            elif precondition == "jacobi":
                run["jacobi start"]()  # D^-1 kept for the iterations
            else:
                precondition()
            wp.copy(p, z)
            s.zero_()
            run["r.z new"]()  # the first iteration's shift moves it to (r.z)_old

        if self.device_loop:
            if multigrid is not None:
                multigrid.record(r, z)  # outside the capture (``AggregationMultigrid.record`` says why)
            kind = precondition if precondition in (None, "jacobi") else "multigrid"
            done = self._device_loop_pcg((system, n, kind), start, prepare, self._pcg_iteration(run, precondition),
                                         None, tol, maxiter, atol_floor)
            if done is not None:
                return done
        return self._host_loop_pcg(system, n, run, precondition, start, prepare, None, tol, maxiter, atol_floor)

    def _host_loop_pcg(self, system, n: int, run: dict, precondition, start, prepare, after, tol: float,
                       maxiter: int, atol_floor: float) -> tuple:
        """The PCG's loop on the host: ``start`` (residual and ||b||), the stop bound max(tol ||b||, atol_floor), then
        unless the residual is within it (a NaN residual takes one iteration; the caller reports it) ``prepare``,
        the captured iteration (``_pcg_iteration_graph``) until the bound or ``maxiter``, and ``after`` (None:
        nothing). One read-back per iteration. Returns (iterations, ||r||, bound)."""
        s = self._scalars
        atol_floor = self._host_floor(atol_floor)
        start()
        host = s.numpy()
        atol = max(tol * float(np.sqrt(host[1])), atol_floor)
        residual = float(np.sqrt(host[3]))
        iterations = 0
        if not residual <= atol:
            prepare()
            # captured, not run, the first time; IC(0) takes the step inside its forward substitution
            iteration = self._pcg_iteration_graph(system, n, run, precondition)
            while iterations < maxiter:
                wp.capture_launch(iteration)
                iterations += 1
                residual = float(np.sqrt(s.numpy()[3]))
                if not residual > atol:  # converged, or NaN (reported by the caller)
                    break
            if after is not None:
                after()
        return iterations, residual, atol

    def _red_black_pcg(self, system, n: int, run: dict, tol: float, maxiter: int, atol_floor: float) -> tuple:
        """Jacobi-PCG on the red-black reduced system of ``system`` (kernels/gas.py "red-black reduced system"):
        from the black rows of the guess, x_r = D_r^-1 (b_r + N_rb x_b) and the reduced residual, which is the
        full residual (0 on the red rows), so the stop ||r|| <= max(tol ||b||, atol_floor) is ``_native_pcg``'s;
        at the end x_r from the solved x_b, both scattered into ``_c_x``. Returns (iterations, ||r||, bound)."""
        n_b = self._red_black[system].black_rows.shape[0]
        z, p = self._pcg[1][:n_b], self._pcg[2][:n_b]
        s = self._scalars
        def start():
            s.zero_()
            for name in ("rb gather black", "rb gather red", "rb x_r", "rb residual, r.r", "b.b"):
                run[name]()

        def prepare():
            p.zero_()
            s.zero_()  # alpha = 0 (read from the copy): the pass only takes z = D_b^-1 r and r.z (x and r stay)
            self._coefficients.zero_()
            run["rb step, jacobi, r.z new, r.r"]()
            wp.copy(p, z)

        def scatter():
            run["rb scatter black"]()
            run["rb scatter red"]()

        if self.device_loop:
            def finish():
                run["rb x_r"]()  # also after 0 iterations: t again from the same x_b
                scatter()

            done = self._device_loop_pcg((system, n, "red_black"), start, prepare,
                                         self._pcg_iteration(run, "red_black"), finish, tol, maxiter, atol_floor)
            if done is not None:
                return done
        done = self._host_loop_pcg(system, n, run, "red_black", start, prepare, run["rb x_r"], tol, maxiter,
                                   atol_floor)
        scatter()
        return done

    def _pcg_iteration_graph(self, system, n: int, run: dict, precondition):
        """One PCG iteration of ``system`` as a captured graph (``wp.ScopedCapture``: a CUDA graph, or Warp's CPU
        replay), captured once and launched every iteration: its ~7 launches (~50 with the V-cycle) without the
        host's per-launch cost (~6 us each on the CPU). Scalars as ``kernels/gas.py`` "native PCG": the shift
        of (r.z)_new into (r.z)_old first, then the iteration, which ends with the residual check's r.r in
        scalars[3]. ``precondition`` None: IC(0), whose forward substitution takes the step x += alpha p,
        r -= alpha Ap (``ic0_step_apply_kernel``); "jacobi": the step, z = D^-1 r and both dot products in one pass
        (``jacobi_step_dot_kernel``); else the V-cycle, a callable. The matrix product and p.Ap in one pass."""
        kind = precondition if precondition in (None, "jacobi", "red_black") else "multigrid"
        key = (system, n, kind)
        graph = self._pcg_graphs.get(key)
        if graph is None:
            with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                self._pcg_iteration(run, precondition)()
            graph = self._pcg_graphs[key] = capture.graph
        return graph

    @staticmethod
    def _pcg_iteration(run: dict, precondition):
        """One PCG iteration's launches as a callable (``_pcg_iteration_graph`` says what they do)."""
        if precondition == "red_black":  # the reduced system's CG (``_red_black_pcg``)
            def iteration():
                for name in ("shift", "rb N p", "rb ap, p.ap", "alpha", "rb step, jacobi, r.z new, r.r", "beta",
                             "rb direction"):
                    run[name]()
            return iteration

        def iteration():
            run["shift"]()
            run["ap, p.ap"]()
            run["alpha"]()
            if precondition == "jacobi":
                run["step, jacobi, r.z new, r.r"]()
            else:
                if precondition is None:
                    run["step, ic0 apply"]()
                else:
                    run["step"]()
                    precondition()
                run["r.z new, r.r"]()  # the residual check's r.r in the same pass, every iteration
            run["beta"]()
            run["direction"]()
        return iteration

    def _device_loop_pcg(self, key: tuple, start, prepare, iteration, finish, tol: float, maxiter: int,
                         atol_floor: float) -> tuple:
        """The whole CG of one system as one captured graph (``GasSolver.device_loop``): ``start`` (r = b - A x, b.b,
        r.r), the stop test's start (``pcg_stop_start_kernel``), ``prepare`` (the preconditioner's set-up, p = z,
        r.z; run also when the guess already meets the bound: it leaves x alone), then the iterations in a
        ``wp.capture_while`` loop (a CUDA graph's while node; Warp's CPU replay loops natively), each followed by
        ``pcg_stop_kernel``, then ``finish`` (None or the red-black scatter). The same launches in the same order
        as the host loop, so the same bits (NaN cases too); one read-back per solve (bound, ||r||, iterations) where
        the host loop reads ||r|| after every iteration (a sync each on a GPU). Captured once per (system, rows,
        kind); tol, atol_floor and maxiter are written to the device before each solve. Returns (iterations, ||r||,
        bound), or None where the driver cannot loop in a graph (then ``device_loop`` is switched off with a
        warning and the caller takes the host loop)."""
        dev, s, stop, more, params = self.device, self._scalars, self._pcg_stop, self._pcg_more, self._pcg_params
        if dev.is_cuda and not wp.is_conditional_graph_supported():
            if not self._device_loop_warned:
                self._device_loop_warned = True
                print("hel-warp: warning: GasConfig.pcg_device_loop needs CUDA graph conditional nodes (CUDA 12.4+), "
                      "which this driver lacks: the CG loops on the host", file=sys.stderr)
            self.device_loop = False
            return None
        # the stop test's parameters on the device, so that one graph serves every step (the pressure's atol_floor
        # changes with the step's gross divergence)
        if isinstance(atol_floor, _FloorOf):
            wp.launch(K.pcg_params_floor_kernel, dim=1,
                      inputs=[wp.float64(tol), wp.float64(atol_floor.scale), atol_floor.sums, atol_floor.index,
                              wp.float64(maxiter)], outputs=[params], device=dev)
        else:
            wp.launch(K.pcg_params_kernel, dim=1, inputs=[wp.float64(tol), wp.float64(atol_floor),
                                                          wp.float64(maxiter)], outputs=[params], device=dev)
        graph = self._pcg_solve_graphs.get(key)
        if graph is None:
            slot = 3 if key[0] == "pressure" else int(key[0])
            log = wp.launch(K.pcg_log_kernel, dim=1, inputs=[stop, slot], outputs=[self._solve_log], device=dev,
                            record_cmd=True)
            stop_start = wp.launch(K.pcg_stop_start_kernel, dim=1, inputs=[s, params], outputs=[stop, more],
                                   device=dev, record_cmd=True)
            check = wp.launch(K.pcg_stop_kernel, dim=1, inputs=[s, params], outputs=[stop, more], device=dev,
                              record_cmd=True)

            def body():
                iteration()
                check.launch()

            with wp.ScopedCapture(device=dev, force_module_load=False) as capture:
                start()
                stop_start.launch()
                prepare()
                wp.capture_while(more, body)
                if finish is not None:
                    finish()
                log.launch()
            graph = self._pcg_solve_graphs[key] = capture.graph
        wp.capture_launch(graph)
        if self.deferred_checks:
            self._log_unread = True
            return None, None, None
        atol, residual, iterations = (float(v) for v in self._pcg_stop.numpy())
        return int(iterations), residual, atol

    # ------------------------------------------------------------------ sub-steps
    def update_cell_state(self, gas: GasField) -> None:
        """eps_f from eps_s, cell velocity, Smagorinsky viscosity and face coefficients."""
        self._prime(gas)
        g, dom, params, cells = self.grid_info, self.domain, self._params(1.0), self._fluid_cells
        self._launch(K.cell_state_kernel, cells, [g, cells, gas.cell_eps_s, dom.cell_fluid, params.eps_min,
                                                  gas.face_velocity, gas.cell_eps_f, gas.cell_velocity])
        self._launch(K.smagorinsky_kernel, cells, [g, params, cells, dom.cell_fluid, gas.cell_velocity,
                                                   gas.cell_eps_f, gas.cell_nu_t, self._cell_kappa])
        for axis in range(3):
            faces = self._coefficient_faces[axis]
            self._launch(K.FACE_COEFFICIENTS_KERNELS[axis], faces, [g, faces, dom.cell_fluid, gas.cell_eps_f,
                                                                    self._cell_kappa, gas.face_eps, gas.face_kappa])
            inlets = self._inlet_faces[axis]
            if inlets.shape[0] and self.config.inlet_superficial:
                wp.launch(K.inlet_face_eps_kernel, dim=inlets.shape[0], inputs=[axis, inlets, gas.face_eps],
                          device=self.device)

    def advect(self, gas: GasField, dt: float) -> None:
        """Semi-Lagrangian advection of the face velocities into the scratch faces (``add_forces_and_diffuse`` takes
        them from there)."""
        g, dom = self.grid_info, self.domain
        for axis in range(3):
            faces = self._solved_faces[axis]
            self._launch(K.ADVECT_KERNELS[axis], faces, [g, faces, dom.face_type, gas.face_velocity, float(dt),
                                                         self._velocity_tmp])

    def add_forces_and_diffuse(self, gas: GasField, dt: float) -> None:
        """u* = advected velocity + particle momentum source + imposed mean pressure gradient, less the old pressure
        gradient (predictor u -= (dt/rho) grad p^n of the incremental projection, Goda 1979, so that a steady
        balance of force and pressure, e.g. a fluidised bed, is a fixed point of the step), then the
        backward-Euler viscous step from u*, one CG solve per component, into the face velocity. u* is formed by
        the assembly of each system (kernels/gas.py ``forced_velocity``), not stored by a pass of its own."""
        g, dom, params, c = self.grid_info, self.domain, self._params(dt), self.config
        for axis in range(3):
            faces, face_row = self._solved_faces[axis], self._systems[axis][1]
            self._launch(K.VISCOUS_RHS_KERNELS[axis], faces,
                         [g, params, faces, face_row, self._viscous_topology[axis], dom.face_type, dom.face_bc,
                          dom.cell_fluid, gas.face_eps, gas.face_kappa_flat[axis], gas.cell_momentum_source,
                          gas.pressure_solution, self._velocity_tmp, self._c_rhs, self._c_x, self._stencils[axis]])
            iterations = self._solve(
                axis, f"viscous ({'xyz'[axis]})", c.viscous_tolerance, c.viscous_max_iterations,
                preconditioner=c.viscous_preconditioner)
            if iterations is not None:
                self._last_iterations["viscous"][axis] = iterations
            self._launch(K.STORE_COMPONENT_KERNELS[axis], faces, [g, faces, face_row, self._c_x, gas.face_velocity])

    def project(self, gas: GasField, dt: float) -> None:
        """Projection onto d(eps_f)/dt + div(eps_f u) = 0 with a pressure increment dp (outlet dp = 0);
        p^{n+1} = p^n + dp; sets the cell pressure and its gradient."""
        self._prime(gas)
        g, dom, params, c, cells = self.grid_info, self.domain, self._params(dt), self.config, self._fluid_cells
        cell_row = self._systems["pressure"][1]
        n = self._systems["pressure"][0].shape[0]
        self._fluid_sum.zero_()
        self._launch(K.pressure_rhs_kernel, cells,
                     [g, params, cells, cell_row, dom.cell_fluid, dom.face_type, dom.face_bc, gas.face_eps,
                      gas.face_velocity, gas.cell_eps_f, gas.cell_eps_f_prev, 0.0, self._c_rhs,
                      self._stencils["pressure"], self._c_active, self._fluid_sum])
        if not dom.has_outlet and n:
            wp.launch(K.remove_mean_kernel, dim=n, inputs=[self._c_active[:n], self._fluid_sum, self._c_rhs[:n]],
                      device=self.device)
        self._c_x.zero_()
        # floor: float32 round-off of the stored face velocities, relative to the gross flux (read back unless
        # the device-side loop takes it there)
        floor = _FloorOf(self._fluid_sum, 2, FLOAT32_FLOOR)
        iterations = self._solve("pressure", "pressure", c.pressure_tolerance, c.pressure_max_iterations,
                                 atol_floor=floor if self._deferring() else self._host_floor(floor),
                                 relaxation=c.pressure_preconditioner_relaxation, multigrid=self._pressure_mg)
        if iterations is not None:
            self._last_iterations["pressure"] = iterations
        dp = self._pressure_increment
        self._launch(K.pressure_increment_kernel, cells, [g, cells, cell_row, self._c_x, dp, gas.pressure_solution])
        for axis in range(3):
            faces = self._solved_faces[axis]
            self._launch(K.PRESSURE_CORRECT_KERNELS[axis], faces,
                         [g, params, faces, dom.face_type, dom.face_bc, dp, 0.0, gas.pressure_solution,
                          gas.face_velocity, self._face_grad_p])
            alias = self._alias_faces[axis]
            self._launch(K.periodic_sync_kernel, alias, [g, axis, alias, gas.face_velocity])
        if not self._deferring():  # deferred: the count accumulates until ``check``
            self._bad.zero_()
        self._launch(K.cell_projected_kernel, cells,
                     [g, params, cells, dom.cell_fluid, dom.face_type, self._face_grad_p, gas.pressure_solution,
                      gas.face_velocity, gas.cell_pressure, gas.cell_grad_p, gas.cell_velocity, self._bad])

    # ------------------------------------------------------------------ the step
    def step(self, gas: GasField, dt: float) -> None:
        """Advance ``gas`` by ``dt`` in place (docs/developer/architecture.md, step 2)."""
        if not dt > 0.0:
            raise ConfigError(f"gas time step dt must be > 0 (got {dt!r})")
        self._prime(gas)
        cells = self._fluid_cells
        if not gas._started:
            # first step: no history of eps_f, take d(eps_f)/dt = 0
            self._launch(K.eps_f_kernel, cells, [cells, gas.cell_eps_s, self.domain.cell_fluid,
                                                 float(self.config.eps_f_min), gas.cell_eps_f_prev])
            gas._started = True
        else:
            wp.copy(gas.cell_eps_f_prev, gas.cell_eps_f)
        for phase, args in ((self.update_cell_state, (gas,)), (self.advect, (gas, dt)),
                            (self.add_forces_and_diffuse, (gas, dt)), (self.project, (gas, dt))):
            if self.time_phases:
                start = time.perf_counter()
                phase(*args)
                wp.synchronize_device(self.device)
                self.timings[phase.__name__] = time.perf_counter() - start
            else:
                phase(*args)
        if self.config.check_finite and not self._deferring():
            # counted by the projection's cell pass over the fluid cells (the solid cells hold constants)
            if int(self._bad.numpy()[0]) > 0:
                raise HelWarpError(f"gas field holds NaN/inf in {int(self._bad.numpy()[0])} cells after the step; "
                                   "reduce dt or check eps_s and the momentum source for NaN")

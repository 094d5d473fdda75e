"""Two-way gas-parcel coupling on a uniform Cartesian grid (host wrappers of the HEL step).

The order inside one HEL step (docs/developer/architecture.md, "The step"):

1. :func:`deposit_parcels`  - solid volume, -drag impulse (the gas momentum source), sum beta V,
   solids mass and momentum to the cells (``kernels/deposit.py``);
2. gas step                 - ``hel_warp.gas.solver.GasSolver`` (reads ``cell_eps_s``, ``cell_momentum_source``,
   ``cell_drag_coeff``), not here;
3. :func:`interpolate_gas`  - gas velocity, modified-pressure gradient and eps_s at the parcels,
   with the same cloud-in-cell weights (``kernels/interp.py``);
4. collision acceleration   - :func:`ktgf_collision` (or zero);
5. :func:`push_parcels`     - eq. (4) with semi-implicit drag; records each parcel's drag impulse,
   which the next :func:`deposit_parcels` hands to the gas with the opposite sign.

Stencil cache: given a ``kernels.interp.ParcelStencil`` (``stencil=``, as ``HelSolver`` does), the deposit
computes each trilinear parcel's stencil once into it and the interpolation and the implicit exchange's passes
read it (computed in every kernel, a parcel's stencil costs ~12 evaluations per step); every kernel checks per parcel that the
cached row is at the position it is given and computes it otherwise, so the results are those of the computed
stencils, bit for bit. None: every stencil computed.

Momentum bookkeeping: the impulse a parcel receives from drag over a step is
``weight m F_D dt (u_f - v_new)``; the cells receive exactly minus that, spread with weights
that sum to one, so sum(cell_momentum_source) + sum(parcel drag impulses) = 0 to float64
round-off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hel_warp.errors import ConfigError, require_finite, require_positive


@dataclass(frozen=True, kw_only=True)
class GridSpec:
    """Uniform Cartesian grid: cell (i,j,k) centre = origin + (i+1/2, j+1/2, k+1/2) spacing."""

    origin: tuple[float, float, float]
    """Lower corner of the grid, m."""
    spacing: float
    """Cell size h, m."""
    shape: tuple[int, int, int]
    """Cells per axis (nx, ny, nz)."""
    periodic: tuple[bool, bool, bool] = (False, False, False)
    """Periodic flag per axis (the stencil wraps around)."""
    spread: bool = True
    """Weighted parcels couple (deposit, interpolation, drag exchange) through tents with the second moment of
    their w real particles instead of the trilinear stencil; False: trilinear at any weight. Weight 1 is trilinear
    either way."""
    cloud_density: bool = True
    """With ``spread``: a parcel's w particles stand at the number density of the real particles around it, so
    its cloud is narrower where they are dense: a cube of w particles at their spacing, uniform of width
    b = sqrt(w^(2/3) - 1) min(1, (n h^3)^(-1/3)) cells per axis, each point read trilinearly (``kernels/deposit.py``
    ``cloud_width_kernel``, ``kernels/interp.py`` ``cloud_weight``); False: the weight rule, a tent of whole
    half-width round(sqrt(w^(2/3) / 2 + 1)) cells (the cloud at one particle per cell) anywhere
    (``kernels/interp.py`` ``spread_half_width``)."""

    def __post_init__(self):
        if len(self.origin) != 3 or len(self.shape) != 3:
            raise ConfigError("grid origin and shape must each have three entries")
        require_finite("grid origin", np.asarray(self.origin, float))
        require_positive("grid spacing", self.spacing, "m")
        if any(int(n) != n or n < 1 for n in self.shape):
            raise ConfigError(f"grid shape must be three positive integers (got {self.shape!r})")
        if len(self.periodic) != 3:
            raise ConfigError(f"grid periodic must have three flags (got {self.periodic!r})")

    @property
    def cell_volume(self) -> float:
        return self.spacing**3

    def cell_grid(self, fluid=None, cloud=None):
        """The kernel-side ``CellGrid`` struct (``fluid``: the int32 fluid mask the tents keep to, None: all fluid;
        ``cloud``: the parcels' float32 tent half-widths, ``CouplingFields.parcel_cloud``, None: the weight rule),
        built once per (mask, widths) and kept (building one costs ~20 us, three per HEL step); callers must not
        modify it."""
        from kernels.interp import make_cell_grid

        cache = self.__dict__.get("_cell_grids")
        if cache is None:
            cache = {}
            object.__setattr__(self, "_cell_grids", cache)  # frozen: not a field (no part of eq, hash or repr)
        key = (id(fluid), id(cloud))
        entry = cache.get(key)
        if entry is None or entry[0] is not fluid or entry[1] is not cloud:  # held, so the ids are not reused
            entry = (fluid, cloud, make_cell_grid(self.origin, self.spacing, self.shape, self.periodic,
                                                  spread=self.spread, fluid=fluid, cloud=cloud))
            cache[key] = entry
        return entry[2]

    @classmethod
    def of(cls, grid) -> "GridSpec":
        """From any grid object with ``origin``, ``spacing`` (or ``h``) and ``shape`` attributes."""
        spacing = getattr(grid, "spacing", None)
        if spacing is None:
            spacing = grid.h
        periodic = tuple(bool(p) for p in getattr(grid, "periodic", (False, False, False)))
        return cls(origin=tuple(float(o) for o in grid.origin), spacing=float(spacing),
                   shape=tuple(int(n) for n in grid.shape), periodic=periodic)


@dataclass(frozen=True, kw_only=True)
class PushConfig:
    """Gas properties and drag law seen by the parcels (SI units)."""

    drag: str = "gidaspow"
    """Drag law: ``schiller-naumann``, ``wen-yu``, ``gidaspow`` (Table 1) or ``ergun``."""
    fluid_density: float = 1.205
    """Gas density rho_f, kg/m^3 (air at 20 C)."""
    fluid_viscosity: float = 1.81e-5
    """Gas dynamic viscosity mu_f, Pa s (air at 20 C)."""
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.80665)
    """Gravitational acceleration, m/s^2."""
    gidaspow_switch: float = 0.8
    """Gas fraction at which Gidaspow switches from Ergun (below) to Wen-Yu (above)."""
    packing: float = 0.63
    """eps_s seen by the drag law is clipped to this packing limit."""

    def __post_init__(self):
        from kernels.push import DRAG_LAWS

        if self.drag not in DRAG_LAWS:
            raise ConfigError(f"unknown drag law {self.drag!r}; choose one of {', '.join(DRAG_LAWS)}")
        require_positive("fluid_density", self.fluid_density, "kg/m^3")
        require_positive("fluid_viscosity", self.fluid_viscosity, "Pa s")
        if len(self.gravity) != 3:
            raise ConfigError("gravity must have three components (m/s^2)")
        require_finite("gravity", np.asarray(self.gravity, float))
        if not 0.0 < self.gidaspow_switch < 1.0:
            raise ConfigError(f"gidaspow_switch must lie in (0, 1) (got {self.gidaspow_switch})")
        if not 0.0 < self.packing < 1.0:
            raise ConfigError(f"packing must lie in (0, 1) (got {self.packing})")

    def params(self, dt: float):
        """The kernel-side ``PushParams`` for time step ``dt`` (s)."""
        import warp as wp

        from kernels.push import DRAG_LAWS, PushParams

        require_positive("dt", dt, "s")
        p = PushParams()
        p.gravity = wp.vec3(*[float(g) for g in self.gravity])
        p.fluid_density = float(self.fluid_density)
        p.fluid_viscosity = float(self.fluid_viscosity)
        p.drag_law = int(DRAG_LAWS[self.drag])
        p.gidaspow_switch = float(self.gidaspow_switch)
        p.eps_s_max = float(self.packing)
        p.dt = float(dt)
        return p


@dataclass
class CouplingFields:
    """Cell and parcel arrays of the coupling, allocated once (Warp arrays on one device).

    Cell fields (shape = grid shape):
        solid_volume: sum weight V_p w, m^3, float64.
        momentum_source: N s over the step given to the gas (= -sum drag impulse w), vec3d.
        drag_coeff: sum beta V = sum weight m_p F_D w, kg/s, float64.
        solid_mass: kg, float64.  solid_momentum: kg m/s, vec3d.
        eps_s: solid volume fraction, float32.  solid_velocity: mass-averaged, m/s, vec3.
        p_s: granular pressure, Pa; theta: granular temperature m^2/s^2; g0; mu_s, mu_fric Pa s;
        grad_p_s: Pa/m, vec3 (KTGF collision model only).
        exchange_coeff A (kg), exchange_momentum B (kg m/s), u_eq (m/s, vec3), gas_impulse G (N s, the
        momentum owed to the gas by the last implicit push), mismatch (N s): the implicit drag exchange
        (:func:`exchange_push`, ``kernels/deposit.py``).
    Parcel fields (shape = capacity):
        u_f: gas velocity at the parcel, m/s; grad_p: modified-pressure gradient, Pa/m;
        eps_s: solid fraction at the parcel; a_coll: collision acceleration, m/s^2;
        drag_impulse: impulse of drag on the parcel over the last push, N s, vec3d;
        drag_coeff: weight m_p F_D, kg/s, float64.
        rate: F_D (1/s); exchange: D = weight m_p dt F_D / (1 + dt F_D) (kg); u_eq: the implicit
        exchange velocity at the parcel; x_start: position before the push (the exchange's stencils).
    Scratch of one push, not in checkpoints (``checkpoint=False`` in the field's metadata):
        exchange_divisor: A_c where the exchange's correction takes the mismatch back, +inf elsewhere (kg);
        exchange_sums: (A_c, B_c) as the exchange's deposit accumulates them, vec4d (kg, kg m/s);
        deposit_sums: the five sums above as the deposit accumulates them (``kernels.deposit.vec9d``);
        gas_record: the gas velocity, grad p' and eps_s the interpolation reads, side by side
        (``kernels.interp.gas_record``);
        parcel_voidage: the drag law's slip-free factor for the exchange's passes (``kernels.push.drag_voidage``).
    Not a field: ``launches``, the coupling kernels' recorded launches (``kernels.launches.LaunchCache``: a launch
    replayed costs ~7 instead of ~25 us; it holds the arrays it was given, as these fields do).
    """

    cell_solid_volume: object
    cell_momentum_source: object
    cell_drag_coeff: object
    cell_solid_mass: object
    cell_solid_momentum: object
    cell_eps_s: object
    cell_solid_velocity: object
    cell_p_s: object
    cell_theta: object
    cell_g0: object
    cell_mu_s: object
    cell_mu_fric: object
    cell_grad_p_s: object
    parcel_u_f: object
    parcel_grad_p: object
    parcel_eps_s: object
    parcel_a_coll: object
    parcel_drag_impulse: object
    parcel_drag_coeff: object
    cell_exchange_coeff: object
    cell_exchange_momentum: object
    cell_u_eq: object
    cell_gas_impulse: object
    cell_mismatch: object
    parcel_rate: object
    parcel_exchange: object
    parcel_u_eq: object
    parcel_x_start: object
    cell_exchange_divisor: object = field(default=None, metadata={"checkpoint": False})
    cell_exchange_sums: object = field(default=None, metadata={"checkpoint": False})
    cell_deposit_sums: object = field(default=None, metadata={"checkpoint": False})
    cell_gas_record: object = field(default=None, metadata={"checkpoint": False})
    parcel_voidage: object = field(default=None, metadata={"checkpoint": False})
    parcel_cloud: object = field(default=None, metadata={"checkpoint": False})
    """Per parcel the cloud width (cells) of this step (``GridSpec.cloud_density``), computed by the deposit."""
    cell_packing_stress: object = field(default=None, metadata={"checkpoint": False})
    """The enduring-contact stress tau of this step (``packing_acceleration``), Pa."""

    @classmethod
    def allocate(cls, grid: GridSpec, capacity: int, *, device=None) -> "CouplingFields":
        import warp as wp

        from kernels.deposit import vec9d
        from kernels.launches import LaunchCache
        from kernels.interp import gas_record

        shape = tuple(int(n) for n in grid.shape)

        def cells(dtype):
            return wp.zeros(shape, dtype=dtype, device=device)

        def parcels(dtype):
            return wp.zeros(int(capacity), dtype=dtype, device=device)

        fields = cls(
            cell_solid_volume=cells(wp.float64), cell_momentum_source=cells(wp.vec3d),
            cell_drag_coeff=cells(wp.float64), cell_solid_mass=cells(wp.float64),
            cell_solid_momentum=cells(wp.vec3d), cell_eps_s=cells(wp.float32),
            cell_solid_velocity=cells(wp.vec3), cell_p_s=cells(wp.float32), cell_theta=cells(wp.float32),
            cell_g0=cells(wp.float32), cell_mu_s=cells(wp.float32), cell_mu_fric=cells(wp.float32),
            cell_grad_p_s=cells(wp.vec3),
            parcel_u_f=parcels(wp.vec3), parcel_grad_p=parcels(wp.vec3), parcel_eps_s=parcels(wp.float32),
            parcel_a_coll=parcels(wp.vec3), parcel_drag_impulse=parcels(wp.vec3d),
            parcel_drag_coeff=parcels(wp.float64), cell_exchange_coeff=cells(wp.float64),
            cell_exchange_momentum=cells(wp.vec3d), cell_u_eq=cells(wp.vec3), cell_gas_impulse=cells(wp.vec3d),
            cell_mismatch=cells(wp.vec3d), parcel_rate=parcels(wp.float32), parcel_exchange=parcels(wp.float64),
            parcel_u_eq=parcels(wp.vec3), parcel_x_start=parcels(wp.vec3), cell_exchange_divisor=cells(wp.float64),
            cell_exchange_sums=cells(wp.vec4d), cell_deposit_sums=cells(vec9d), cell_gas_record=cells(gas_record),
            parcel_voidage=parcels(wp.float32), parcel_cloud=parcels(wp.float32),
            cell_packing_stress=cells(wp.float32))
        fields.launches = LaunchCache()
        return fields


def reserve_tent_records(grid: GridSpec, particles, max_weight: float | None = None) -> int:
    """Before the tent deposits of a coupling call on CUDA: Warp's deterministic atomics of ``kernels/deposit.py``
    sized for the largest live parcel's tent (``kernels.deposit.reserve_records``; a tent of half-width K adds into
    (2K)^3 cells); ``max_weight``: an upper bound of the live weights, None: read it (``live_extremes``). Nothing to
    do on the CPU, without tents or without parcels. Returns the bound in force."""
    from kernels import deposit as D

    if not (D.DETERMINISTIC and particles.device.is_cuda and grid.spread and particles.count > 0):
        return D.reserve_records(0)
    if max_weight is None:
        max_weight = particles.live_extremes()[1]  # the largest live weight
    k = tent_support_host(grid, max_weight)
    return D.reserve_records(8 * k**3)


def tent_support_host(grid: GridSpec, weight: float) -> int:
    """The most cells per axis / 2 a parcel of ``weight`` couples through on ``grid``: the weight rule's K, or with
    ``cloud_density`` the larger of it (the deposit that reads the clouds' surroundings) and the widest cloud's."""
    from kernels.interp import cloud_support_host, cloud_width_host, spread_half_width_host

    k = spread_half_width_host(grid.spread, weight)
    if grid.spread and grid.cloud_density:
        k = max(k, cloud_support_host(cloud_width_host(weight)))
    return k


def parcel_grid(grid: GridSpec, fields: "CouplingFields", cell_fluid=None):
    """The ``CellGrid`` the step's coupling kernels use: with the cloud widths of the step's deposit when it
    computed them (``fields.cloud_on``), else the weight rule's."""
    cloud = fields.parcel_cloud if getattr(fields, "cloud_on", False) else None
    return grid.cell_grid(cell_fluid, cloud)


def deposit_parcels(grid: GridSpec, particles, fields: CouplingFields, cell_fluid=None, *, stencil=None,
                    max_weight: float | None = None) -> None:
    """Step 1: parcels -> cells (volume, momentum source from the last push, sum beta V, solids momentum);
    ``cell_fluid``: the int32 fluid mask heavy parcels' tents keep to; ``stencil``: a ``ParcelStencil`` the
    deposit fills at the parcels' positions (every trilinear row: the parcels moved since the last step);
    ``max_weight``: an upper bound of the live parcels' weights (None: read the largest, one sync). The bound
    may exceed it: the cloud widths of parcels of weight <= 1 are 0, whose stencil is the trilinear one that the
    weight rule gives them (``kernels/interp.py`` ``parcel_cell``, K = 1), so computing them changes no bit."""
    from kernels.deposit import cloud_widths, deposit, finish_cells
    from kernels.interp import parcel_arrays

    reserve_tent_records(grid, particles, max_weight)
    arrays = parcel_arrays(particles)
    fields.cloud_on = False  # not a field: True from a deposit that computed parcel_cloud to the next deposit
    if grid.spread and grid.cloud_density and particles.count > 0 and \
            (particles.live_extremes()[1] if max_weight is None else max_weight) > 1.0:
        cloud_widths(grid.cell_grid(cell_fluid), arrays, cell_solid_volume=fields.cell_solid_volume,
                     parcel_cloud=fields.parcel_cloud, launches=fields.launches)
        fields.cloud_on = True
    deposit(parcel_grid(grid, fields, cell_fluid), arrays, fields.parcel_drag_impulse, fields.parcel_drag_coeff,
            cell_sums=fields.cell_deposit_sums, stencil=stencil, launches=fields.launches)
    finish_cells(grid.cell_volume, fields.cell_deposit_sums, cell_solid_volume=fields.cell_solid_volume,
                 cell_momentum_source=fields.cell_momentum_source, cell_drag_coeff=fields.cell_drag_coeff,
                 cell_solid_mass=fields.cell_solid_mass, cell_solid_momentum=fields.cell_solid_momentum,
                 cell_eps_s=fields.cell_eps_s, cell_solid_velocity=fields.cell_solid_velocity,
                 launches=fields.launches)


def interpolate_gas(grid: GridSpec, particles, cell_velocity, cell_grad_p, fields: CouplingFields,
                    cell_fluid=None, *, stencil=None) -> None:
    """Step 3: gas velocity, grad p' and eps_s at the parcels (same weights as the deposit), in one pass;
    ``stencil``: the deposit's cache (its rows are read where the parcels have not moved since)."""
    from kernels.interp import interpolate_gas_parcels

    interpolate_gas_parcels(parcel_grid(grid, fields, cell_fluid), particles.x, particles.weight, cell_velocity, cell_grad_p,
                            fields.cell_eps_s, cell_gas=fields.cell_gas_record, parcel_u_f=fields.parcel_u_f,
                            parcel_grad_p=fields.parcel_grad_p, parcel_eps_s=fields.parcel_eps_s, stencil=stencil,
                            launches=fields.launches)


def ktgf_collision(grid: GridSpec, particles, fields: CouplingFields, params, *, dt: float | None = None) -> None:
    """Step 4 (KTGF): cell Theta, p_s from the deposited solids; a_coll = -grad p_s / (eps_s rho_p) at parcels.

    Theta is the algebraic root of eq. (8) including the gas-solid exchange 3 K_sg Theta, with
    K_sg = sum(beta V) / V_cell from the deposited ``fields.cell_drag_coeff`` (the drag coefficients of
    the last push). ``params``: a ``kernels.ktgf.KtgfParams`` (see ``make_ktgf_params``). Needs
    :func:`deposit_parcels` first. ``dt`` (s, the HEL step): given, |a_coll| is limited to h / dt^2 (one step's
    collision velocity moves a parcel at most one cell; ``kernels/ktgf.py``, "Stability"); None: unlimited.
    """
    from kernels.ktgf import cell_gradient, collision_acceleration, ktgf_cells

    ktgf_cells(params, grid.spacing, fields.cell_eps_s, fields.cell_solid_velocity, cell_g0=fields.cell_g0,
               cell_theta=fields.cell_theta, cell_p_s=fields.cell_p_s, cell_mu_s=fields.cell_mu_s,
               cell_mu_fric=fields.cell_mu_fric, periodic=grid.periodic, cell_drag_coeff=fields.cell_drag_coeff)
    cell_gradient(grid.spacing, fields.cell_p_s, fields.cell_grad_p_s, periodic=grid.periodic)
    collision_acceleration(grid.cell_grid(), params.eps_s_min, particles.x, particles.density,
                           fields.cell_grad_p_s, fields.cell_eps_s, fields.parcel_a_coll, dt=dt)


def packing_acceleration(grid: GridSpec, particles, fields: CouplingFields, *, pressure: float, beta: float,
                         packed: float, eps: float, dt: float | None, onset: float = 0.0, knee: float = 1.0,
                         knee_stress: float = 0.0, stiffness: float = 0.0) -> None:
    """Step 4, added to any collision model's: the enduring-contact stress of the packed parcels (MP-PIC,
    Harris & Crighton 1994; Snider 2001), tau(eps_s) of the deposited ``fields.cell_eps_s``
    (``kernels/ktgf.py`` ``packing_stress``), as a_coll += -grad tau / (eps_s rho_p) with the gradient on the cell
    faces (``face_stress_acceleration_kernel``), limited to h / dt^2 on its own. Needs :func:`deposit_parcels` first; ``hel_warp.hel.PackingStress`` holds the
    parameters and the reasons."""
    from kernels.ktgf import face_stress_acceleration, packing_pressure

    packing_pressure(fields.cell_eps_s, fields.cell_packing_stress, p_solid=pressure, beta=beta, packed=packed,
                     eps=eps, onset=onset, knee=knee, knee_stress=knee_stress, stiffness=stiffness)
    face_stress_acceleration(grid.cell_grid(), 1.0e-6, particles, fields.cell_packing_stress, fields.cell_eps_s,
                             fields.parcel_a_coll, dt=dt)


def push_parcels(particles, fields: CouplingFields, push_params, *, particle_x_out=None,
                 particle_v_out=None) -> None:
    """Step 5: eq. (4) on ``particles.x``/``particles.v`` (in place unless ``particle_*_out`` are given);
    records drag impulses for the next deposit (the explicit exchange)."""
    from kernels.interp import parcel_arrays
    from kernels.push import push

    push(push_params, parcel_arrays(particles), fields.parcel_u_f, fields.parcel_grad_p, fields.parcel_eps_s,
         fields.parcel_a_coll, fields.parcel_drag_impulse, fields.parcel_drag_coeff, particle_x_out=particle_x_out,
         particle_v_out=particle_v_out)


EXCHANGE_PASSES = 3
"""Picard passes of the implicit exchange: the first evaluates F_D at the slip against the interpolated gas
velocity, the next ones at the slip against the previous pass's exchange velocity u_eq (the velocity the drag
acts towards). In the hindered-settling test (eps_s = 0.1, dt = 1e-3 s) the settled slip is 0.6 % from the
drag law's balance with three passes, 3.7 % with two (the iteration alternates about the answer)."""


def exchange_push(grid: GridSpec, particles, fields: CouplingFields, push_params, *, cell_velocity, cell_fluid,
                  gas_density: float, eps_f_min: float, particle_x_out=None, particle_v_out=None,
                  stencil=None, cell_grad_p=None, max_weight: float | None = None) -> None:
    """Step 5 with the implicit drag exchange (``kernels/deposit.py``): eq. (4) for the parcels and the gas
    impulse ``fields.cell_gas_impulse`` for the next gas step, solved together per cell so that neither
    phase overshoots their common velocity however dense the cell, and momentum balances to round-off.

    ``cell_velocity``: the gas velocity the parcels were interpolated from; ``cell_fluid``: int32 mask
    (0: outside the fluid, whose share goes to the walls as with :func:`push_parcels`). Outputs in place
    unless ``particle_*_out`` are given; records drag impulses and rates as :func:`push_parcels` does.
    ``stencil``: a ``ParcelStencil``, brought up to the start positions here (only rows computed elsewhere, e.g.
    before a collision moved the parcel: none in the plain step) and read by the exchange's eight passes.
    ``cell_grad_p``: the gas's grad p' (Pa/m), held over the step while the gas relaxes with the parcels, so that a
    steady drag balances the pressure force (``kernels/deposit.py`` ``exchange_cells_kernel``); None: the gas's
    inertia alone, which carries at most ~M u / dt of drag per cell (a packed bed at 0.1 m/s and 5e-4 s: 8 Pa of
    the 62 Pa Ergun's law asks). ``max_weight``: as :func:`deposit_parcels`'s.
    """
    import warp as wp

    from kernels.deposit import exchange_cells, exchange_correct, exchange_deposit, exchange_voidage
    from kernels.interp import fill_stencil, interpolate_vec3_parcels, parcel_arrays
    from kernels.push import push_at_rate

    p = particles
    f = fields
    reserve_tent_records(grid, p, max_weight)  # once for the passes below
    g = parcel_grid(grid, fields, cell_fluid)
    x_out = p.x if particle_x_out is None else particle_x_out
    v_out = p.v if particle_v_out is None else particle_v_out
    wp.copy(f.parcel_x_start, p.x)
    start = parcel_arrays(p, x=f.parcel_x_start)  # the parcels as they were before the push
    if stencil is not None:
        fill_stencil(g, f.parcel_x_start, p.weight, stencil, only_stale=True, launches=f.launches)
    exchange_voidage(push_params, start, f.parcel_eps_s, parcel_voidage=f.parcel_voidage, launches=f.launches)
    slip_against = f.parcel_u_f
    for _ in range(EXCHANGE_PASSES):
        exchange_deposit(g, push_params, start, slip_against, f.parcel_eps_s, f.parcel_voidage, f.parcel_grad_p,
                         f.parcel_a_coll, parcel_rate=f.parcel_rate, parcel_exchange=f.parcel_exchange,
                         cell_exchange_sums=f.cell_exchange_sums, stencil=stencil, launches=f.launches)
        exchange_cells(float(gas_density) * grid.cell_volume, eps_f_min, cell_fluid, f.cell_eps_s, cell_velocity,
                       f.cell_exchange_sums, cell_exchange_coeff=f.cell_exchange_coeff,
                       cell_exchange_momentum=f.cell_exchange_momentum, cell_u_eq=f.cell_u_eq,
                       cell_gas_impulse=f.cell_gas_impulse, cell_mismatch=f.cell_mismatch,
                       cell_exchange_divisor=f.cell_exchange_divisor, cell_grad_p=cell_grad_p,
                       pressure_scale=0.0 if cell_grad_p is None else push_params.dt / float(gas_density),
                       launches=f.launches)
        interpolate_vec3_parcels(g, f.parcel_x_start, p.weight, f.cell_u_eq, f.parcel_u_eq, stencil=stencil,
                                 launches=f.launches)
        slip_against = f.parcel_u_eq
    push_at_rate(push_params, start, f.parcel_u_eq, f.parcel_rate, f.parcel_grad_p, f.parcel_a_coll,
                 f.parcel_drag_impulse, f.parcel_drag_coeff, particle_x_out=x_out, particle_v_out=v_out,
                 launches=f.launches)
    exchange_correct(g, push_params.dt, f.cell_exchange_divisor, f.cell_mismatch, start, f.parcel_exchange,
                     f.parcel_drag_impulse, particle_x_out=x_out, particle_v_out=v_out, stencil=stencil,
                     launches=f.launches)


def single_particle_response(*, diameter: float, density: float, config: PushConfig, dt: float,
                             max_time: float | None = None, tolerance: float = 1e-7, device=None) -> dict:
    """One particle released from rest in still gas, integrated with the engine's push kernel.

    Returns ``terminal_velocity`` (m/s, speed once a step changes it by less than ``tolerance``
    relative, or float32 stagnation), ``response_time`` (s, first time the speed reaches
    1 - 1/e = 63.2 % of the terminal speed, interpolated linearly within the step), ``steps``,
    ``converged``. Still gas: u_f = 0 and grad p' = 0 (hydrostatic pressure is in p' already).
    """
    import warp as wp

    from hel_warp.parcels.particles import Particles

    require_positive("diameter", diameter, "m")
    require_positive("density", density, "kg/m^3")
    require_positive("dt", dt, "s")
    g = float(np.linalg.norm(config.gravity))
    if not g > 0:
        raise ConfigError("gravity must be non-zero to settle a particle")
    if density <= config.fluid_density:
        raise ConfigError(f"particle density {density} kg/m^3 must exceed the gas density "
                          f"{config.fluid_density} kg/m^3 for the particle to settle")
    # Generous end time: 40 Stokes response times bound the approach from rest for any Re.
    tau_stokes = density * diameter**2 / (18.0 * config.fluid_viscosity)
    t_end = max_time if max_time is not None else 40.0 * tau_stokes
    n_steps_max = int(math.ceil(t_end / dt))
    chunk = int(min(max(n_steps_max, 1), 2000))

    parts = Particles.from_numpy(np.zeros((1, 3)), 0.5 * diameter, density=density, check_overlap=False,
                                 device=device)
    fields = CouplingFields.allocate(GridSpec(origin=(0, 0, 0), spacing=1.0, shape=(1, 1, 1)), 1, device=device)
    params = config.params(dt)
    history = wp.zeros(chunk, dtype=wp.vec3, device=parts.device)
    speeds = [np.zeros(1)]
    done = 0
    converged = False
    while done < n_steps_max and not converged:
        n = min(chunk, n_steps_max - done)
        for s in range(n):
            push_parcels(parts, fields, params)
            wp.copy(history, parts.v, dest_offset=s, count=1)
        block = np.linalg.norm(history.numpy()[:n].astype(np.float64), axis=1)
        speeds.append(block)
        done += n
        allv = np.concatenate(speeds[-2:])
        change = np.abs(np.diff(allv[-3:]))
        converged = bool(allv[-1] > 0 and np.all(change <= tolerance * allv[-1]))
    speed = np.concatenate(speeds)
    v_term = float(speed[-1])
    target = (1.0 - math.exp(-1.0)) * v_term
    k = int(np.argmax(speed >= target))
    t_resp = dt * ((k - 1) + (target - speed[k - 1]) / (speed[k] - speed[k - 1])) if k > 0 else 0.0
    return {"terminal_velocity": v_term, "response_time": float(t_resp), "steps": int(done),
            "converged": converged}

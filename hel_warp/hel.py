"""The HEL (hybrid Euler-Lagrange / MP-PIC) step, as the algorithm reads (docs/developer/architecture.md, "The step"):

    deposit -> gas step -> interpolate -> collide -> push -> outlets -> walls -> inject

``HelSolver.step()`` is those calls. The collision model is a strategy chosen per run:

- ``none``: no particle-particle interaction (a_coll = 0);
- ``ktgf``: the paper's HEL baseline, a_coll = -grad(p_s)/(eps_s rho_p) with the Table 1 closures
  (``kernels/ktgf.py``);
- ``surrogate``, ``surrogate-paper`` (HELSCM) and ``dem`` (CFD-DEM reference), from
  ``hel_warp.collisions.models``, resolved lazily by :data:`COLLISION_MODELS` / :func:`collision_model`.

The strategy interface: ``name``; ``accelerate(solver)`` fills ``solver.fields.parcel_a_coll``
(an acceleration, m/s^2, applied in the push) and may also change ``solver.pool.particles.v``
directly (a velocity jump, as the surrogate's post-collision velocities are); optional
``advance(solver)`` replaces the push (the strategy integrates the parcels itself, e.g. ``dem``
with Hertz sub-steps at the DEM dt and the fluid acceleration held over the step; it must still
record ``solver.fields.parcel_drag_impulse`` for the momentum hand-back); optional ``after_push(solver)``
runs right after the push (the surrogate's swept detection adds the in-step position changes of its
collisions there); optional ``counts()`` returns this step's collision counts ``{name: int}`` for the run
output.

Momentum bookkeeping: the push records each parcel's drag impulse; the next step's deposit hands
minus that to the gas (one step later), so particles + gas + :meth:`HelSolver.momentum_in_flight`
(minus the drag impulses of the last push, owed to the gas) is conserved by the coupling. The float64
sums are copied into the gas solver's float32 arrays, so the gas side holds them to float32 round-off.

After the push (docs/developer/architecture.md step 5): parcels past an outlet plane are removed (``Outlet``,
``ParcelPool.remove_beyond_plane``); parcels whose centre crossed the SDF wall are reflected with
e_n, e_t (``Material.wall_restitution_*``, Table 1: 0.8, ``kernels/reflect.py``); scheduled volume
injectors (``ScheduledInjection``) add the parcels due by the end of the step (``ParcelPool.inject``).
Outlets come before walls: a parcel that left through an outlet at the end of a geometry shape
has crossed the SDF boundary too and must be removed, not reflected.

Everything a restart needs is :meth:`HelSolver.state` / :meth:`HelSolver.set_state` (host copies,
at checkpoint intervals only); ``hel_warp.runs.run`` writes them.
"""

from __future__ import annotations

import dataclasses
import math
import time as _time
from dataclasses import dataclass

import numpy as np

from hel_warp.parcels.coupling import (CouplingFields, GridSpec, PushConfig, deposit_parcels, interpolate_gas,
                               exchange_push, ktgf_collision, push_parcels)
from hel_warp.errors import ConfigError, require_finite, require_positive
from hel_warp.material import Material
from hel_warp.parcels.pool import ParcelPool, VolumeInjection


class NoCollision:
    """``none``: parcels do not interact (a_coll stays zero)."""

    name = "none"

    def accelerate(self, solver: "HelSolver") -> None:
        solver.fields.parcel_a_coll.zero_()


class KtgfCollision:
    """``ktgf``: granular-pressure collision acceleration (paper eqs. (5)-(8), Table 1).

    Monodisperse closures: ``particle_diameter`` (m) and ``particle_density`` (kg/m^3) are the ones
    of the KTGF solids phase. The collision acceleration is limited to h / dt^2 with the step's dt (at most
    one cell of collision displacement per step; ``kernels/ktgf.py``, "Stability"). The dilute viscosity
    in the algebraic Theta is limited by the mean free path (Hrenya & Sinclair 1997) with
    L = ``mean_free_path_length`` (None: the cell size h, the smallest resolved shear length; 0: off):
    without it Theta ~ 1/eps_s in near-empty cells and heats the fringe parcels at dt <= 1e-4 s.

    ``collisional_limit``: the largest eps_s at which the radial distribution g0 is evaluated (None: 0.999 of
    ``packing``). A flow whose packed parcels carry the MP-PIC packing stress (``PackingStress``) lowers it: kinetic
    theory is the collisional regime, and g0 ~ 1 / (1 - (eps_s / eps_max)^(1/3)) in a settled bed (g0 ~ 1e3 at
    0.999 eps_max) with the explicit algebraic Theta turns the slightest fluctuation of the parcels into a pressure
    that blows the bed apart (``cases/bubbling_bed.py``, ``KTGF_COLLISIONAL_LIMIT``, has the measurements).

    ``dilute_limit``: the smallest eps_s of a cell that holds a solids phase (below it: no Theta, no stress, no
    resolved strain against it) and of a parcel's interpolated eps_s that feels the stress. Kinetic theory is a
    continuum: a cell with less than a particle in it has no granular temperature, and there the algebraic Theta
    (~ 1 / eps_s) only kicks the few parcels at its edge. A flow whose cells hold a few particles (a bed resolved at
    two diameters) sets it to one particle per cell; the default 1e-8 keeps every cell with solids.
    """

    name = "ktgf"

    def __init__(self, *, particle_diameter: float, particle_density: float, restitution: float = 0.9,
                 packing: float = 0.63, friction_packing: float = 0.61, friction_angle_deg: float = 30.0,
                 mean_free_path_length: float | None = None, collisional_limit: float | None = None,
                 dilute_limit: float = 1e-8):
        from kernels.ktgf import make_ktgf_params

        require_positive("particle_diameter", particle_diameter, "m")
        require_positive("particle_density", particle_density, "kg/m^3")
        if not 0.0 < restitution <= 1.0:
            raise ConfigError(f"restitution must lie in (0, 1] (got {restitution})")
        if not 0.0 < friction_packing < packing < 1.0:
            raise ConfigError(f"need 0 < friction_packing < packing < 1 (got {friction_packing}, {packing})")
        cap = 0.999
        if collisional_limit is not None:
            if not 0.0 < collisional_limit < packing:
                raise ConfigError(f"collisional_limit must lie in (0, packing = {packing}) (got {collisional_limit})")
            cap = collisional_limit / packing
        if not 0.0 < dilute_limit < packing:
            raise ConfigError(f"dilute_limit must lie in (0, packing = {packing}) (got {dilute_limit})")
        self.params = make_ktgf_params(particle_diameter=particle_diameter, particle_density=particle_density,
                                       restitution=restitution, packing=packing, friction_packing=friction_packing,
                                       friction_angle_deg=friction_angle_deg, max_fraction_of_packing=cap,
                                       eps_s_min=dilute_limit)
        if mean_free_path_length is not None and not mean_free_path_length >= 0.0:
            raise ConfigError(f"mean_free_path_length must be >= 0 m (got {mean_free_path_length}); 0 switches "
                              "the limit off, None takes the cell size")
        self.mean_free_path_length = mean_free_path_length

    def accelerate(self, solver: "HelSolver") -> None:
        length = self.mean_free_path_length
        self.params.mfp_length = float(solver.grid.spacing if length is None else length)
        ktgf_collision(solver.grid, solver.pool.particles, solver.fields, self.params, dt=solver.config.dt)


class _CollisionModels:
    """name -> strategy class. ``none`` and ``ktgf`` live here; ``surrogate``, ``surrogate-paper`` and
    ``dem`` are resolved lazily from ``hel_warp.collisions.models`` (classes ``SurrogateCollision``,
    ``SurrogatePaperCollision``, ``DemCollision``), so importing the HEL loop never loads the forest or
    the DEM."""

    _builtin = {"none": NoCollision, "ktgf": KtgfCollision}
    _lazy = {"surrogate": "SurrogateCollision", "surrogate-paper": "SurrogatePaperCollision",
             "dem": "DemCollision"}

    def keys(self):
        return [*self._builtin, *self._lazy]

    def __iter__(self):
        return iter(self.keys())

    def __contains__(self, name) -> bool:
        return name in self._builtin or name in self._lazy

    def __getitem__(self, name: str):
        if name in self._builtin:
            return self._builtin[name]
        if name in self._lazy:
            import importlib

            try:
                module = importlib.import_module("hel_warp.collisions.models")
            except ModuleNotFoundError as err:
                if err.name != "hel_warp.collisions.models":
                    raise
                raise ConfigError(f"collision model {name!r} lives in hel_warp.collisions.models, which is not "
                                  f"installed in this checkout; use none or ktgf") from err
            return getattr(module, self._lazy[name])
        raise ConfigError(f"unknown collision model {name!r}; choose one of {', '.join(self.keys())}")


COLLISION_MODELS = _CollisionModels()
"""name -> strategy class (``none``, ``ktgf``, ``surrogate``, ``surrogate-paper``, ``dem``)."""


def collision_model(name: str, **kwargs):
    """The collision strategy called ``name``, built with ``kwargs``; a typo is a ConfigError naming the valid names.

    A strategy has ``name`` and ``accelerate(solver)``; optionally ``advance(solver)`` (called by
    ``HelSolver.step`` INSTEAD of the push: the strategy moves the parcels itself, e.g. CFD-DEM Hertz
    sub-steps at the DEM dt with the fluid acceleration held over the step) and ``counts()`` (a dict
    ``{name: int}`` of this step's collision counts, written per step to the run output).
    """
    return COLLISION_MODELS[name](**kwargs)


@dataclass(frozen=True, kw_only=True)
class ScheduledInjection:
    """A volume injector: ``injection`` (box, count or mass, speed and direction, size distribution)
    released over the window [``t_start``, ``t_end``] (s), at a uniform rate.

    By the end of each step the cumulative release is ``count * f`` parcels (rounded) or ``mass * f`` kg
    (never more than one parcel over), ``f = (t - t_start) / (t_end - t_start)`` clipped to [0, 1];
    ``t_end = t_start`` (default) releases everything at once: at construction of the solver when
    ``t_start = 0``, else at the end of the step that reaches ``t_start``. Each release draws positions
    and sizes with a seed derived from (``injection.seed``, injector index, release number), so a
    restarted run injects the same parcels as an uninterrupted one.
    """

    injection: VolumeInjection
    t_start: float = 0.0
    """Start of the release window, s."""
    t_end: float | None = None
    """End of the release window, s (None: = t_start, an instantaneous release)."""

    def __post_init__(self):
        if not isinstance(self.injection, VolumeInjection):
            raise ConfigError("ScheduledInjection.injection must be a hel_warp.parcels.pool.VolumeInjection")
        require_finite("injection t_start", self.t_start)
        if self.t_start < 0:
            raise ConfigError(f"injection t_start must be >= 0 (got {self.t_start} s)")
        if self.t_end is None:
            object.__setattr__(self, "t_end", float(self.t_start))
        require_finite("injection t_end", self.t_end)
        if self.t_end < self.t_start:
            raise ConfigError(f"injection t_end {self.t_end} s must not precede t_start {self.t_start} s")

    def fraction_due(self, t: float, tolerance: float) -> float:
        """Fraction of the total released by time ``t`` (s); ``tolerance`` (s) absorbs time round-off."""
        if t < self.t_start - tolerance:
            return 0.0
        window = self.t_end - self.t_start
        if window <= tolerance:
            return 1.0
        return min(max((t + tolerance - self.t_start) / window, 0.0), 1.0)


@dataclass(frozen=True, kw_only=True)
class Outlet:
    """Outlet plane: parcels with ``(x - point) . normal > 0`` are removed (alive = 0)."""

    point: tuple[float, float, float]
    """A point of the plane, m."""
    normal: tuple[float, float, float]
    """Outward normal (out of the domain); normalised."""

    def __post_init__(self):
        point = np.asarray(self.point, float).reshape(-1)
        normal = np.asarray(self.normal, float).reshape(-1)
        if point.size != 3 or normal.size != 3:
            raise ConfigError("outlet point and normal must each have three components")
        require_finite("outlet point", point)
        require_finite("outlet normal", normal)
        if not np.linalg.norm(normal) > 0:
            raise ConfigError(f"outlet normal must be non-zero (got {self.normal!r})")
        object.__setattr__(self, "point", tuple(float(v) for v in point))
        object.__setattr__(self, "normal", tuple(float(v) for v in normal / np.linalg.norm(normal)))


DAMPING_RAMP = 0.01
"""Solids fraction above ``PackingStress.onset`` over which the contact damping rises from 0 to full."""


@dataclass(frozen=True, kw_only=True)
class PackingStress:
    """Enduring contacts of packed parcels: the MP-PIC particle normal stress added to every HEL collision model.

    tau(eps_s) = ``pressure`` eps_s^``beta`` / max(``packed`` - eps_s, ``eps`` (1 - eps_s)) of the deposited solids
    fraction (Harris & Crighton 1994; Snider 2001, J. Comput. Phys. 170: 523; OpenFOAM's ``HarrisCrighton``), as
    a_coll += -grad tau / (eps_s rho_p) (``coupling.packing_acceleration``). Ignored by ``dem``, whose Hertz contacts
    carry enduring contacts themselves; the surrogate's cell detection then leaves its own stress
    (``CellConfig.packing_stress``) to this one."""

    pressure: float = 10.0
    """P_s, Pa."""
    beta: float = 2.0
    """Exponent beta of eps_s."""
    packed: float = 0.6
    """Close-packed solids fraction eps_cp at which tau diverges."""
    onset: float = 0.0
    """Solids fraction below which parcels carry no enduring contacts (tau = 0), in [0, packed): tau =
    ``pressure`` max(eps_s - onset, 0)^beta / max(packed - eps_s, ...), the threshold of Johnson & Jackson's (1987)
    frictional pressure; 0: Harris & Crighton's form."""
    eps: float = 1.0e-7
    """Floor of the denominator, relative to 1 - eps_s (Snider 2001): tau stays finite past eps_cp."""
    damping: float = 0.0
    """Share of a parcel's velocity relative to the local mass-averaged solids velocity removed per step where eps_s
    exceeds ``onset`` by ``DAMPING_RAMP`` (O'Rourke & Snider 2010's collision damping, complete where contacts
    endure; ramped from the onset; momentum exact, ``kernels/ktgf.py`` ``contact_damping_kernel``). Needs an onset
    > 0. 0: none."""
    stiffness_limit: float = 0.25
    """Cap of d tau / d eps_s as a fraction of rho_p (h / dt)^2 (rho_p the material's density, h the grid spacing):
    above the solids fraction where tau is that stiff it goes on along its tangent. The explicit stress term is an
    acoustic one, c^2 = (d tau / d eps_s) / rho_p, stable while c dt < h; 0.25 keeps c dt <= h / 2. 0: no cap."""

    def __post_init__(self):
        require_positive("packing stress pressure", self.pressure, "Pa")
        require_positive("packing stress beta", self.beta)
        require_positive("packing stress eps", self.eps)
        if not 0.0 < self.packed < 1.0:
            raise ConfigError(f"packing stress packed fraction must lie in (0, 1) (got {self.packed})")
        if not 0.0 <= self.onset < self.packed:
            raise ConfigError(f"packing stress onset must lie in [0, packed = {self.packed}) (got {self.onset})")
        if not 0.0 <= self.damping <= 1.0:
            raise ConfigError(f"packing stress damping must lie in [0, 1] (got {self.damping})")
        if self.damping > 0.0 and self.onset <= 0.0:
            raise ConfigError("packing stress damping acts above the onset of enduring contacts: give onset > 0")
        if not self.stiffness_limit >= 0.0:
            raise ConfigError(f"packing stress stiffness_limit must be >= 0 (got {self.stiffness_limit})")

    def uncapped(self, eps_s):
        """tau(eps_s) without the stiffness cap, Pa (numpy, host side)."""
        e = np.clip(np.asarray(eps_s, float), 0.0, 0.999999)
        return (self.pressure * np.maximum(e - self.onset, 0.0) ** self.beta
                / np.maximum(self.packed - e, self.eps * (1.0 - e)))

    def knee(self, stiffness: float) -> tuple[float, float]:
        """(eps_K, tau(eps_K)): the solids fraction where d tau / d eps_s reaches ``stiffness`` (Pa) and the stress
        there; (1, 0) when ``stiffness`` <= 0 (no cap). d tau / d eps_s grows monotonically from the onset to
        eps_cp, so a bisection finds it."""
        if not stiffness > 0.0:
            return 1.0, 0.0

        def slope(e):
            x = e - self.onset
            if x <= 0.0:
                return 0.0
            gap = self.packed - e
            return self.pressure * x**self.beta * (self.beta / x + 1.0 / gap) / gap

        lo, hi = self.onset, self.packed - 1e-12
        if slope(hi) <= stiffness:
            return hi, float(self.uncapped(hi))
        for _ in range(100):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if slope(mid) < stiffness else (lo, mid)
        return lo, float(self.uncapped(lo))

    def stiffness(self, *, density: float, spacing: float, dt: float) -> float:
        """The cap of d tau / d eps_s, Pa: ``stiffness_limit`` rho_p (h / dt)^2."""
        return self.stiffness_limit * density * (spacing / dt) ** 2

    def stress(self, eps_s, *, density: float | None = None, spacing: float | None = None, dt: float | None = None):
        """tau(eps_s), Pa (numpy, host side), with the stiffness cap of the given density, spacing and dt."""
        tau = self.uncapped(eps_s)
        if density is None:
            return tau
        k = self.stiffness(density=density, spacing=spacing, dt=dt)
        knee, knee_stress = self.knee(k)
        e = np.clip(np.asarray(eps_s, float), 0.0, 0.999999)
        return np.where((k > 0) & (e > knee), knee_stress + k * (e - knee), tau)


@dataclass(frozen=True, kw_only=True)
class HelConfig:
    """Settings of the HEL loop."""

    dt: float = 1e-3
    """Time step of gas and parcels, s (the paper's HEL runs use 1e-3, 1e-4, 7.14e-5)."""
    push: PushConfig = PushConfig()
    """Drag law and gas properties seen by the parcels (must match the gas solver's)."""
    material: Material = Material()
    """Particle material; its ``wall_restitution_normal``/``_tangential`` (0.8, 0.8) act at the walls."""
    walls: bool = True
    """Reflect parcels at the SDF walls of the gas geometry (False: periodic boxes, tests)."""
    injectors: tuple = ()
    """``ScheduledInjection``s, in order (the order fixes the parcel indices)."""
    outlets: tuple = ()
    """``Outlet`` planes."""
    wall_friction: float | None = None
    """Coulomb cap of the tangential wall impulse (mu x the normal one; ``kernels/reflect.py``): None takes
    ``material.friction`` (0.3), 0 gives the bare e_t reflection (a parcel sliding along a wall then loses a
    factor e_t per step, i.e. more the smaller dt)."""
    wall_contact: str = "point"
    """Where a parcel meets the wall (``kernels/reflect.py``): ``point`` (MP-PIC: its centre crosses the wall) or
    ``surface`` (its surface: the centre a particle radius from the wall, as the DEM's sphere-wall contact)."""
    wall_spin: bool = False
    """Parcels meet the walls as rough solid spheres that carry their spin (``Particles.omega``; kernels/reflect.py
    ``reflect_spin``: the contact point's tangential velocity reversed by ``wall_spin_restitution``, Coulomb-capped),
    as the dem strategy's spheres do: one rolling along a wall keeps its speed. False: the spinless reflection with
    ``material.wall_restitution_tangential`` (Table 1). The gas exerts no torque; particle-particle collisions turn
    the spins only with ``particle_spin``."""
    particle_spin: bool = False
    """The surrogate's particle-particle collisions (pairwise mode, swept and cell detection) act at the contact point:
    the model is asked at the contact points' relative velocity (translation and spin) and its impulse turns both
    spins (``SurrogateCollision.particle_spin``; docs/physics/spin-and-mixtures.md). Meant with
    ``wall_spin``, where rolling parcels carry spin into their collisions; ignored by the other strategies."""
    wall_spin_restitution: float = 0.0
    """beta in [-1, 1] of ``wall_spin`` (0: a sticking impact leaves the sphere rolling; the Hertz-Mindlin wall of the
    dem strategy gives beta -0.58...+0.42 over 5-60 degrees of incidence, mean +0.04)."""
    coupling: str = "implicit"
    """Drag exchange between parcels and gas: ``implicit`` (default; gas and parcels relax together per
    cell, stable at any solids loading, momentum to round-off, ``coupling.exchange_push``) or ``explicit``
    (the parcels' impulses handed to the next gas step as a source; overshoots where
    dt K_sg / (eps_f rho_f) > 2, i.e. in dense cells at the paper's steps - kept for comparison)."""

    sort_every: int = 20
    """Reorder the parcel slots by grid cell before the first step and every this many steps after (0: never):
    the deposit's atomics and the gathers then touch neighbouring memory (at 1e6 parcels the parcel phase costs
    ~1.6x more in the random order of a fill). Parcel ids (``particle_id``) travel with the parcels; a strategy
    with per-parcel memory must provide ``permute_parcels(new_to_old, old_to_new)`` or the sort is skipped."""

    parcel_cloud: str = "density"
    """How wide a weighted parcel couples (deposit, interpolation, drag exchange; weight 1 is trilinear either way):
    ``density`` (default): its w real particles stand at the number density of the real particles around it, so
    its cloud is narrow in a dense stream and one particle per cell wide where the others are sparse
    (``GridSpec.cloud_density``, ``kernels/deposit.py`` ``cloud_width_kernel``); ``weight``: the weight rule, one
    particle per cell anywhere (a tent of half-width round(sqrt(w^(2/3) / 2 + 1)) cells; without collisions its
    weighted streams run ahead of weight 1's on the rig, 33 % against 23 % of the real particles past x = 50 mm at
    0.02 s)."""

    exchange_pressure: bool = False
    """``implicit`` coupling: the gas relaxes with the parcels under its pressure gradient held over the step
    (``coupling.exchange_push``), so a steady drag balances the pressure force: a packed bed's pressure drop is
    Ergun's. False: the gas's inertia alone, whose drag a packed bed caps near M u / dt per cell (8 Pa of Ergun's
    62 Pa in the bubbling bed at 0.1 m/s, dt = 5e-4 s); in dilute flows the two agree (the case API turns it on for
    flows that start from a filled bed, ``hel_warp.case.Gas.exchange_pressure``)."""
    packing_stress: PackingStress | None = None
    """Enduring contacts of packed parcels (:class:`PackingStress`) for every collision model but ``dem``; None: off
    (the surrogate's cell detection keeps its own ``CellConfig.packing_stress``)."""

    stencil_cache: bool = True
    """Compute each trilinear parcel's cloud-in-cell stencil once per step (at the deposit) and read it in the
    interpolation and the implicit exchange's passes (``kernels.interp.ParcelStencil``; a parcel moved in
    between, e.g. by a collision, has its stencil computed again): the same results bit for bit, the parcel
    phase 1.6-1.7x faster on the CPU. False: every pass computes the stencils (the reference the tests compare with);
    costs 108 bytes per parcel of capacity."""

    read_back: str = "auto"
    """When the host reads the device: ``step`` (every step checks itself: the gas CG's stop test after each
    iteration or solve, the NaN count, the largest parcel weight for the deposit's stencils), ``output`` (a steady
    step reads nothing: the gas CG loops on the device (``GasConfig.pcg_device_loop``), its failures and NaN
    cells are logged there and raised at the next output by ``check_finite``, the deposit sizes its stencils from
    a host bound of the weights, refreshed at each output and raised by every injection), or ``auto``: ``output``
    on CUDA, where each read is a sync that empties the GPU's queue of launches, ``step`` on the CPU, where a read
    is a view. Both give the same bits; ``output`` reports a failure up to one output interval late."""

    def __post_init__(self):
        require_positive("dt", self.dt, "s")
        if int(self.sort_every) != self.sort_every or self.sort_every < 0:
            raise ConfigError(f"sort_every must be an integer >= 0 (got {self.sort_every!r}); 0 switches sorting off")
        if self.coupling not in ("implicit", "explicit"):
            raise ConfigError(f"coupling must be 'implicit' or 'explicit' (got {self.coupling!r})")
        if self.parcel_cloud not in ("density", "weight"):
            raise ConfigError(f"parcel_cloud must be 'density' or 'weight' (got {self.parcel_cloud!r})")
        if not -1.0 <= float(self.wall_spin_restitution) <= 1.0:
            raise ConfigError(f"wall_spin_restitution must be in [-1, 1] (got {self.wall_spin_restitution})")
        if self.wall_contact not in ("point", "surface"):
            raise ConfigError(f"wall_contact must be 'point' or 'surface' (got {self.wall_contact!r})")
        if self.read_back not in ("auto", "step", "output"):
            raise ConfigError(f"read_back must be 'auto', 'step' or 'output' (got {self.read_back!r})")
        if self.packing_stress is not None and not isinstance(self.packing_stress, PackingStress):
            raise ConfigError("packing_stress must be a hel_warp.hel.PackingStress or None")
        object.__setattr__(self, "injectors", tuple(self.injectors))
        object.__setattr__(self, "outlets", tuple(self.outlets))
        for k, inj in enumerate(self.injectors):
            if not isinstance(inj, ScheduledInjection):
                raise ConfigError(f"injectors[{k}] must be a ScheduledInjection (got {type(inj).__name__})")
        for k, out in enumerate(self.outlets):
            if not isinstance(out, Outlet):
                raise ConfigError(f"outlets[{k}] must be an Outlet (got {type(out).__name__})")


class HelSolver:
    """Parcels (``ParcelPool``) coupled two-way to the ``GasSolver`` on its grid.

    ``gas_solver``/``gas``: ``hel_warp.gas.solver.GasSolver`` and its ``GasField`` (or any objects with
    ``step(gas, dt)`` and ``cell_velocity``, ``cell_grad_p``, ``cell_eps_s``, ``cell_momentum_source``,
    ``cell_drag_coeff`` float32 cell arrays). Updates ``pool.particles`` and ``gas`` in place.
    Walls need the geometry: ``gas.domain.geometry`` (a ``hel_warp.gas.grid.Geometry``).

    Bad input is refused here with a ConfigError that names the fix: live parcels or injector boxes
    outside the fluid (SDF >= 0), gas properties that differ from the gas solver's.
    """

    def __init__(self, *, pool: ParcelPool, gas_solver, gas, config: HelConfig, collision=None):
        import warp as wp

        from kernels.reflect import make_wall_params

        self.pool = pool
        self.gas_solver = gas_solver
        self.gas = gas
        self.config = config
        self.collision = collision if collision is not None else NoCollision()
        domain = getattr(gas, "domain", None) or getattr(gas_solver, "domain", None)
        self.grid = dataclasses.replace(GridSpec.of(domain.grid), cloud_density=config.parcel_cloud == "density")
        gas_config = getattr(gas_solver, "config", None)
        if gas_config is not None:
            for name, ours, theirs in (("density", config.push.fluid_density, gas_config.density),
                                       ("viscosity", config.push.fluid_viscosity, gas_config.viscosity)):
                if abs(ours - theirs) > 1e-12 * abs(theirs):
                    raise ConfigError(f"gas {name} differs between the parcels ({ours}) and the gas solver "
                                      f"({theirs}); give the same value to PushConfig and GasConfig")
        device = pool.particles.device
        self.fields = CouplingFields.allocate(self.grid, pool.capacity, device=device)
        self.stencil = None
        """The parcels' cached stencils (``HelConfig.stencil_cache``), or None."""
        if config.stencil_cache:
            from kernels.interp import make_parcel_stencil

            self.stencil = make_parcel_stencil(pool.capacity, device=device)
        self.push_params = config.push.params(config.dt)
        cell_fluid = getattr(domain, "cell_fluid", None)
        if cell_fluid is None:
            cell_fluid = wp.full(tuple(int(n) for n in self.grid.shape), 1, dtype=wp.int32, device=device)
        self.cell_fluid = cell_fluid
        self.eps_f_min = float(getattr(gas_config, "eps_f_min", 1.0 - config.push.packing))
        geometry = getattr(domain, "geometry", None)
        self.shapes = geometry.shapes_struct(device) if geometry is not None else None
        if config.walls and self.shapes is None:
            raise ConfigError("walls need the gas geometry (gas.domain.geometry); set HelConfig(walls=False) "
                              "for a geometry-free gas stand-in")
        wall_friction = config.material.friction if config.wall_friction is None else config.wall_friction
        if not wall_friction >= 0.0:
            raise ConfigError(f"wall_friction must be >= 0 (got {wall_friction}); 0 switches the Coulomb cap off")
        self.wall_params = make_wall_params(friction=wall_friction, surface=config.wall_contact == "surface",
                                            restitution_normal=config.material.wall_restitution_normal,
                                            restitution_tangential=config.material.wall_restitution_tangential,
                                            spin=bool(config.wall_spin),
                                            spin_restitution=float(config.wall_spin_restitution))
        self._wall_hits = wp.zeros(1, dtype=wp.int32, device=device)
        self._counter = wp.zeros(1, dtype=wp.int32, device=device)
        self._packing_knee = None
        self._injected_count = np.zeros(len(config.injectors), dtype=np.int64)
        self._injected_mass = np.zeros(len(config.injectors), dtype=np.float64)
        self._releases = np.zeros(len(config.injectors), dtype=np.int64)
        self.time = 0.0
        self.step_count = 0
        self.timings: dict[str, float] = {}
        """Wall-clock seconds of each sub-step of the last step (device-synchronised on CUDA)."""
        self.time_sub_steps = True
        """Record ``timings``; False skips the per-sub-step device syncs (CUDA graph capture, benchmarks)."""
        self.read_back = config.read_back if config.read_back != "auto" else ("output" if device.is_cuda else "step")
        """``HelConfig.read_back`` resolved for this device: 'step' or 'output'."""
        self._weight_bound = None
        """With ``read_back`` 'output': an upper bound of the live parcels' weights (host), else None (read)."""
        self._radius_bound, self._count_bound = 0.0, 0
        """With ``read_back`` 'output': the same bounds of their radii and count (:meth:`live_bounds`)."""
        if self.read_back == "output":
            if hasattr(gas_solver, "deferred_checks"):
                gas_solver.device_loop = True
                gas_solver.deferred_checks = True
            self._refresh_weight_bound()
        self.check_injectors_inside()
        self._inject_due(self.time)
        self.check_parcels_inside()

    # ------------------------------------------------------------------ the sub-steps
    def deposit(self) -> None:
        """1. parcels -> cells; hand eps_s, momentum source, sum beta V to the gas."""
        import warp as wp

        from kernels.deposit import to_float32

        deposit_parcels(self.grid, self.pool.particles, self.fields, self.cell_fluid, stencil=self.stencil,
                        max_weight=self._live_weight_bound())
        if self.config.coupling == "implicit":
            wp.copy(self.fields.cell_momentum_source, self.fields.cell_gas_impulse)
        wp.copy(self.gas.cell_eps_s, self.fields.cell_eps_s)
        to_float32(self.fields.cell_momentum_source, self.fields.cell_drag_coeff,
                   cell_momentum_source_f32=self.gas.cell_momentum_source,
                   cell_drag_coeff_f32=self.gas.cell_drag_coeff, launches=self.fields.launches)

    def gas_step(self) -> None:
        """2. eps_f-weighted Navier-Stokes step with the particle momentum source (``hel_warp.gas.solver``); with
        ``time_sub_steps`` its phases go into ``timings`` as ``gas_<phase>`` (inside ``gas_step``'s own time)."""
        solver = self.gas_solver
        if hasattr(solver, "time_phases"):  # a GasSolver (a test's stand-in gas may not time itself)
            solver.time_phases = self.time_sub_steps
        solver.step(self.gas, self.config.dt)
        if self.time_sub_steps:
            self.timings.update({f"gas_{name}": seconds for name, seconds in getattr(solver, "timings", {}).items()})

    def interpolate(self) -> None:
        """3. gas velocity, grad p' and eps_s at the parcels, with the deposit's weights."""
        interpolate_gas(self.grid, self.pool.particles, self.gas.cell_velocity, self.gas.cell_grad_p, self.fields,
                        self.cell_fluid, stencil=self.stencil)

    def collide(self) -> None:
        """4. the collision model's acceleration (and/or velocity jumps), then the packing stress of enduring
        contacts (``HelConfig.packing_stress``) on top."""
        stress = self.config.packing_stress
        if stress is not None and stress.damping > 0.0 and getattr(self.collision, "name", None) != "dem":
            from hel_warp.parcels.coupling import parcel_grid
            from kernels.ktgf import contact_damping

            # before the collisions: the deposit's solids velocities are those of these velocities (momentum exact)
            contact_damping(parcel_grid(self.grid, self.fields, self.cell_fluid), self.pool.particles,
                            self.fields.cell_eps_s, self.fields.cell_solid_velocity, onset=stress.onset,
                            ramp=DAMPING_RAMP, damping=stress.damping)
        self.collision.accelerate(self)
        if stress is not None and getattr(self.collision, "name", None) != "dem":
            from hel_warp.parcels.coupling import packing_acceleration

            if getattr(self.collision, "_kicked", False):  # the swept detection pushed inside its collisions
                raise ConfigError("packing_stress acts through the push, which the surrogate's swept detection "
                                  "runs inside its collisions; use detection='cell' for packed parcels")

            if self._packing_knee is None:  # fixed by the parameters, the material, h and dt: once
                k = stress.stiffness(density=self.config.material.density, spacing=self.grid.spacing,
                                     dt=self.config.dt)
                self._packing_knee = (*stress.knee(k), k)
            knee, knee_stress, k = self._packing_knee
            packing_acceleration(self.grid, self.pool.particles, self.fields, pressure=stress.pressure,
                                 beta=stress.beta, packed=stress.packed, eps=stress.eps, dt=self.config.dt,
                                 onset=stress.onset, knee=knee, knee_stress=knee_stress, stiffness=k)

    def push(self) -> None:
        """5. eq. (4), semi-implicit drag; records the drag impulses for the next deposit.

        A strategy with ``advance(solver)`` moves the parcels itself instead (CFD-DEM sub-steps)."""
        advance = getattr(self.collision, "advance", None)
        self._straight_push = advance is None
        if advance is not None:
            advance(self)
        else:
            import warp as wp

            p = self.pool.particles
            if getattr(self, "_x_step_start", None) is None or self._x_step_start.shape != p.x.shape:
                self._x_step_start = wp.empty_like(p.x)
            wp.copy(self._x_step_start, p.x)  # the straight paths' starts: walls reflect where a path crossed them
            self.fluid_push()
        after_push = getattr(self.collision, "after_push", None)
        if after_push is not None:
            after_push(self)  # e.g. the in-step position changes of swept collisions

    def fluid_push(self, *, particle_x_out=None, particle_v_out=None) -> None:
        """Eq. (4) with the configured drag exchange (``HelConfig.coupling``), in place unless ``*_out`` given;
        records the drag impulses (and, ``implicit``, the gas impulse of the next step)."""
        p = self.pool.particles
        if self.config.coupling == "implicit":
            exchange_push(self.grid, p, self.fields, self.push_params, cell_velocity=self.gas.cell_velocity,
                          cell_fluid=self.cell_fluid, gas_density=self.config.push.fluid_density,
                          eps_f_min=self.eps_f_min, particle_x_out=particle_x_out, particle_v_out=particle_v_out,
                          stencil=self.stencil, max_weight=self._live_weight_bound(),
                          cell_grad_p=self.gas.cell_grad_p if self.config.exchange_pressure else None)
        else:
            push_parcels(p, self.fields, self.push_params, particle_x_out=particle_x_out,
                         particle_v_out=particle_v_out)

    def sort_parcels(self) -> bool:
        """Reorder the used parcel slots by grid cell (dead ones last), with every per-parcel array of the
        particles, the coupling fields and the strategy (``permute_parcels``). False when skipped (a strategy
        with per-parcel memory but no ``permute_parcels``). ``pool.used`` and the parcel ids are unchanged."""
        import warp as wp

        from kernels.contacts import launch_gather
        from kernels.interp import cell_order
        from hel_warp.parcels.particles import FIELDS_FLOAT, FIELDS_INT, FIELDS_VEC3

        strategy_permute = getattr(self.collision, "permute_parcels", None)
        if getattr(self.collision, "has_parcel_memory", False) and strategy_permute is None:
            return False
        p = self.pool.particles
        n = p.count
        if self.pool.used < 2:
            return False
        if getattr(self, "_sort_scratch", None) is None:
            dev = p.device
            self._sort_scratch = {"keys": wp.zeros(2 * n, dtype=wp.int32, device=dev),
                                  "values": wp.zeros(2 * n, dtype=wp.int32, device=dev),
                                  "old_to_new": wp.zeros(n, dtype=wp.int32, device=dev), "by_dtype": {}}
        s = self._sort_scratch
        cell_order(self.grid.cell_grid(), self.pool.used, p.x, p.alive, s["keys"], s["values"], s["old_to_new"])
        new_to_old = s["values"]
        arrays = [getattr(p, name) for name in FIELDS_VEC3 + FIELDS_FLOAT + FIELDS_INT]
        arrays += [getattr(self.fields, f.name) for f in dataclasses.fields(self.fields) if f.name.startswith("parcel_")]
        for array in arrays:
            scratch = s["by_dtype"].get(array.dtype)
            if scratch is None:
                scratch = s["by_dtype"][array.dtype] = wp.empty(n, dtype=array.dtype, device=p.device)
            launch_gather(array, new_to_old, scratch)
            wp.copy(array, scratch)
        if strategy_permute is not None:
            strategy_permute(new_to_old, s["old_to_new"])
        return True

    def remove_at_outlets(self) -> None:
        """Parcels past an outlet plane leave the run (alive = 0; counted in ``pool.removed_count()``)."""
        for outlet in self.config.outlets:
            self.pool.remove_beyond_plane(outlet.point, outlet.normal)

    def reflect_at_walls(self) -> None:
        """Parcels whose centre crossed the SDF wall come back with e_n, e_t (``kernels/reflect.py``), against the
        wall where their straight path of the push crossed it (a strategy with its own ``advance`` moved them on
        other paths: the end point's nearest wall).

        Skipped for a strategy with ``handles_walls = True`` (``dem``: sphere-wall contacts in its sub-steps)."""
        if self.config.walls and not getattr(self.collision, "handles_walls", False):
            from kernels.reflect import reflect_at_walls

            p = self.pool.particles
            start = self._x_step_start if getattr(self, "_straight_push", False) else None
            reflect_at_walls(self.shapes, self.wall_params, p.alive, p.x, p.v, self._wall_hits, p.radius,
                             particle_x_start=start, particle_omega=p.omega)

    def wrap_periodic(self) -> None:
        """Parcels that left through a periodic face come back through the opposite one (the grid's periodic
        axes)."""
        from kernels.free_flight import wrap_axes

        g = self.grid
        length = tuple(n * g.spacing for n in g.shape)
        wrap_axes(self.pool.particles.x, self.pool.particles.alive, g.origin, length, g.periodic)

    def inject(self) -> None:
        """Scheduled injectors add the parcels due by the end of this step."""
        self._inject_due(self.time + self.config.dt)

    def step(self) -> None:
        """One HEL step of ``config.dt`` (docs/developer/architecture.md, "The step")."""
        every = int(self.config.sort_every)
        if every and self.step_count % every == 0:  # step 0 too: a fill's random slot order costs ~1.6x at 1e6
            self._timed(self.sort_parcels)
        self._timed(self.deposit)
        self._timed(self.gas_step)
        self._timed(self.interpolate)
        self._timed(self.collide)
        self._timed(self.push)
        self._timed(self.remove_at_outlets)
        self._timed(self.reflect_at_walls)
        if any(self.grid.periodic):
            self._timed(self.wrap_periodic)
        self._timed(self.inject)
        self.time += self.config.dt
        self.step_count += 1

    # ------------------------------------------------------------------ the step's building blocks
    def _timed(self, sub_step) -> None:
        import warp as wp

        if not self.time_sub_steps:
            sub_step()
            return
        start = _time.perf_counter()
        sub_step()
        wp.synchronize_device(self.pool.particles.device)  # CUDA launches are asynchronous; a no-op on the CPU
        self.timings[sub_step.__name__] = _time.perf_counter() - start

    def _inject_due(self, t: float) -> None:
        """Release what each injector owes by time ``t`` (s); host sampling only on release steps."""
        tolerance = 1e-6 * self.config.dt
        for k, scheduled in enumerate(self.config.injectors):
            inj = scheduled.injection
            frac = scheduled.fraction_due(t, tolerance)
            if frac <= 0.0:
                continue
            seed = int(np.random.SeedSequence([inj.seed, k, int(self._releases[k])]).generate_state(1)[0])
            if inj.count is not None:
                due = int(round(inj.count * frac)) - int(self._injected_count[k])
                if due <= 0:
                    continue
                release = dataclasses.replace(inj, count=due, seed=seed)
            else:
                due = inj.mass * frac - self._injected_mass[k]
                if due <= 1e-9 * inj.mass:
                    continue
                release = dataclasses.replace(inj, mass=due, seed=seed)
            diameters = 2.0 * release.sample()["radius"]
            n = self.pool.inject(release)
            self._injected_count[k] += n
            self._injected_mass[k] += float(np.sum(inj.weight * inj.density * math.pi / 6.0 * diameters**3))
            self._releases[k] += 1

    def injected(self) -> list[dict]:
        """Per injector: parcels and real-particle mass (kg) released so far."""
        return [{"count": int(c), "mass": float(m)} for c, m in zip(self._injected_count, self._injected_mass)]

    # ------------------------------------------------------------------ checks of the input
    def _sdf(self, points: np.ndarray) -> np.ndarray:
        import warp as wp

        from kernels.sdf import eval_sdf

        device = self.pool.particles.device
        pts = wp.array(np.asarray(points, np.float32).reshape(-1, 3), dtype=wp.vec3, device=device)
        distance = wp.zeros(pts.shape[0], dtype=float, device=device)
        normal = wp.zeros(pts.shape[0], dtype=wp.vec3, device=device)
        eval_sdf(self.shapes, pts, distance, normal)
        return distance.numpy()

    def check_injectors_inside(self, samples: int = 5) -> None:
        """ConfigError when an injector box reaches outside the fluid (SDF >= 0 on a samples^3 lattice)."""
        if self.shapes is None:
            return
        for k, scheduled in enumerate(self.config.injectors):
            inj = scheduled.injection
            axes = [np.linspace(lo, hi, samples) for lo, hi in zip(inj.box_lo, inj.box_hi)]
            points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
            d = self._sdf(points)
            if np.any(d >= 0.0):
                worst = int(np.argmax(d))
                raise ConfigError(
                    f"injector {k}: box {list(inj.box_lo)}..{list(inj.box_hi)} reaches outside the fluid "
                    f"(SDF {d[worst]:.3g} m >= 0 at {points[worst].round(6).tolist()}); move or shrink the box so "
                    "that it lies inside the geometry")

    def check_parcels_inside(self) -> None:
        """ConfigError when a live parcel lies outside the fluid (SDF >= 0); one int read when all is well."""
        if self.shapes is None:
            return
        from kernels.reflect import count_outside

        p = self.pool.particles
        self._counter.zero_()
        count_outside(self.shapes, p.x, p.alive, self._counter)
        outside = int(self._counter.numpy()[0])
        if outside:
            alive = p.alive.numpy().astype(bool)
            x = p.x.numpy()
            d = np.where(alive, self._sdf(x), -np.inf)
            worst = int(np.argmax(d))
            raise ConfigError(f"{outside} live parcel(s) lie outside the fluid (SDF >= 0), e.g. parcel {worst} at "
                              f"{x[worst].round(6).tolist()} (SDF {d[worst]:.3g} m); place the parcels inside the "
                              "geometry (or fix the geometry's boxes)")

    def check_finite(self) -> None:
        """HelWarpError naming the fields that hold NaN/inf: a device reduction, one small read (output
        intervals, not every step)."""
        import warp as wp

        from hel_warp.errors import HelWarpError
        from kernels.finite import count_nonfinite

        check = getattr(self.gas_solver, "check", None)
        if check is not None:  # what a gas step with deferred checks logged on the device
            try:
                check()
            except HelWarpError as err:
                raise HelWarpError(f"at step {self.step_count} (t = {self.time:.6g} s): {err}") from None
        if self.read_back == "output":
            self._refresh_weight_bound()
        p = self.pool.particles
        named = [("particle x", p.x), ("particle v", p.v), ("gas cell_velocity", self.gas.cell_velocity),
                 ("gas cell_pressure", self.gas.cell_pressure), ("gas cell_grad_p", self.gas.cell_grad_p),
                 ("cell eps_s", self.fields.cell_eps_s), ("parcel drag impulse", self.fields.parcel_drag_impulse),
                 ("parcel collision acceleration", self.fields.parcel_a_coll)]
        bad = wp.zeros(len(named), dtype=wp.int32, device=p.device)
        for slot, (_, array) in enumerate(named):
            count_nonfinite(array, bad, slot)
        counts = bad.numpy()
        if counts.any():
            which = ", ".join(f"{name} ({int(c)} entries)" for (name, _), c in zip(named, counts) if c)
            raise HelWarpError(f"NaN/inf at step {self.step_count} (t = {self.time:.6g} s) in {which}; the run "
                               "blew up: reduce dt, check the inputs for NaN, or restart from the last checkpoint")

    def _live_weight_bound(self) -> float | None:
        """read_back 'output': an upper bound of the live weights, the last read's raised by what was placed since
        (no read); 'step': None (the deposit reads the largest live weight)."""
        if self._weight_bound is None:
            return None
        return max(self._weight_bound, float(getattr(self.pool, "weight_placed_since", 0.0)))

    def live_bounds(self) -> tuple[float, float, int]:
        """(max weight, max radius, live count) of the live parcels: with ``read_back`` 'output' host upper bounds,
        the last read's raised by what the pool placed since (no read); else read now."""
        if self._weight_bound is None:
            return tuple(self.pool.particles.live_extremes()[1:4]) if self.pool.particles.count else (0.0, 0.0, 0)
        pool = self.pool
        return (self._live_weight_bound(), max(self._radius_bound, float(getattr(pool, "radius_placed_since", 0.0))),
                self._count_bound + int(getattr(pool, "count_placed_since", 0)))

    def _refresh_weight_bound(self) -> None:
        """``_weight_bound`` (and the radius and count bounds of :meth:`live_bounds`) from the live parcels (one
        read: set-up, outputs, restarts)."""
        extremes = self.pool.particles.live_extremes() if self.pool.particles.count else (0.0, 0.0, 0.0, 0, 0)
        self._weight_bound, self._radius_bound, self._count_bound = (float(extremes[1]), float(extremes[2]),
                                                                     int(extremes[3]))
        for name, zero in (("weight_placed_since", 0.0), ("radius_placed_since", 0.0), ("count_placed_since", 0)):
            if hasattr(self.pool, name):
                setattr(self.pool, name, zero)

    # ------------------------------------------------------------------ restart state (host copies)
    def _gas_arrays(self) -> dict:
        import warp as wp

        arrays = {}
        for name, value in vars(self.gas).items():
            if isinstance(value, wp.array):
                arrays[name] = value
            elif all(isinstance(getattr(value, a, None), wp.array) for a in "xyz"):
                for a in "xyz":
                    arrays[f"{name}.{a}"] = getattr(value, a)
        return arrays

    def state(self) -> dict[str, np.ndarray]:
        """Everything a restart needs, as host arrays: parcels (all slots, incl. alive/stream/weight), pool
        counters, coupling fields (the drag impulses owed to the gas), gas fields, time, step, injector
        progress, wall hits, and the strategy's own ``state()`` if it has one. A sync: checkpoints only."""
        from hel_warp.parcels.particles import FIELDS_FLOAT, FIELDS_INT, FIELDS_VEC3

        p = self.pool.particles
        out = {f"particles/{n}": getattr(p, n).numpy().copy() for n in FIELDS_VEC3 + FIELDS_FLOAT + FIELDS_INT}
        out["pool/used"] = np.array(self.pool.used, np.int64)
        out["pool/removed"] = self.pool._removed_counter.numpy().copy()
        for f in dataclasses.fields(self.fields):
            if f.metadata.get("checkpoint", True):
                out[f"coupling/{f.name}"] = getattr(self.fields, f.name).numpy().copy()
        for name, array in self._gas_arrays().items():
            out[f"gas/{name}"] = array.numpy().copy()
        out["gas/_started"] = np.array(bool(getattr(self.gas, "_started", True)))
        out["time"] = np.array(self.time, np.float64)
        out["step"] = np.array(self.step_count, np.int64)
        out["inject/count"] = self._injected_count.copy()
        out["inject/mass"] = self._injected_mass.copy()
        out["inject/releases"] = self._releases.copy()
        out["walls/hits"] = self._wall_hits.numpy().copy()
        strategy_state = getattr(self.collision, "state", None)
        if strategy_state is not None:
            out.update({f"collision/{k}": np.asarray(v) for k, v in strategy_state().items()})
        return out

    def set_state(self, state: dict) -> None:
        """Restore :meth:`state` (same capacity, grid and injectors); the run then continues bitwise."""
        from hel_warp.parcels.particles import FIELDS_FLOAT, FIELDS_INT, FIELDS_VEC3

        def put(array, name):
            value = np.asarray(state[name])
            if value.shape != tuple(array.numpy().shape):
                raise ConfigError(f"checkpoint entry {name} has shape {value.shape}, the run has "
                                  f"{tuple(array.numpy().shape)}; restart with the configuration that wrote it")
            array.assign(value)

        p = self.pool.particles
        for n in FIELDS_VEC3 + FIELDS_FLOAT + FIELDS_INT:
            put(getattr(p, n), f"particles/{n}")
        self.pool.used = int(state["pool/used"])
        put(self.pool._removed_counter, "pool/removed")
        for f in dataclasses.fields(self.fields):
            if f.metadata.get("checkpoint", True):
                put(getattr(self.fields, f.name), f"coupling/{f.name}")
        for name, array in self._gas_arrays().items():
            put(array, f"gas/{name}")
        if hasattr(self.gas, "_started"):
            self.gas._started = bool(state["gas/_started"])
        self.time = float(state["time"])
        self.step_count = int(state["step"])
        if np.asarray(state["inject/count"]).shape != self._injected_count.shape:
            raise ConfigError("the checkpoint was written with another number of injectors; restart with the "
                              "configuration that wrote it")
        self._injected_count = np.asarray(state["inject/count"], np.int64).copy()
        self._injected_mass = np.asarray(state["inject/mass"], np.float64).copy()
        self._releases = np.asarray(state["inject/releases"], np.int64).copy()
        put(self._wall_hits, "walls/hits")
        set_strategy_state = getattr(self.collision, "set_state", None)
        if set_strategy_state is not None:
            prefix = "collision/"
            set_strategy_state({k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)})
        if self.read_back == "output":
            self._refresh_weight_bound()

    # ------------------------------------------------------------------ diagnostics (host reads)
    def collision_counts(self) -> dict:
        """This step's collision counts from the strategy's optional ``counts()`` ({} when it has none)."""
        counts = getattr(self.collision, "counts", None)
        return dict(counts()) if counts is not None else {}

    def collision_count_arrays(self):
        """The strategy's ``count_arrays()`` (device arrays behind :meth:`collision_counts` and host extras), or
        None where it has none: the run loop then reads :meth:`collision_counts` each step."""
        staged = getattr(self.collision, "count_arrays", None)
        return staged() if staged is not None else None

    def collision_counts_from(self, host: dict, extras: dict) -> dict:
        """:meth:`collision_counts` from host copies of :meth:`collision_count_arrays`."""
        return dict(self.collision.counts_from(host, extras))

    def wall_hit_count(self) -> int:
        """Parcel-wall reflections so far (host read)."""
        return int(self._wall_hits.numpy()[0])

    def momentum_in_flight(self):
        """Momentum (N s, numpy (3,)) the gas receives at the next deposit: ``implicit``, the cell gas impulses
        in the fluid; ``explicit``, minus the last push's drag impulses."""
        if self.config.coupling == "implicit":
            fluid = self.cell_fluid.numpy().astype(bool)
            return self.fields.cell_gas_impulse.numpy()[fluid].sum(axis=0).astype(np.float64)
        alive = self.pool.particles.alive.numpy().astype(bool)
        return -self.fields.parcel_drag_impulse.numpy()[alive].sum(axis=0).astype(np.float64)

"""The HEL (hybrid Euler-Lagrange / MP-PIC) step, as the algorithm reads (ARCHITECTURE.md, "The step"):

    deposit -> gas step -> interpolate -> collide -> push

``HelSolver.step()`` is those five calls. The collision model is a strategy chosen per run:

- ``none``: no particle-particle interaction (a_coll = 0);
- ``ktgf``: the paper's HEL baseline, a_coll = -grad(p_s)/(eps_s rho_p) with the Table 1 closures
  (``kernels/ktgf.py``);
- ``surrogate``, ``surrogate-paper`` (HELSCM) and ``dem`` (CFD-DEM reference), from
  ``hel_warp.collision_models``, resolved lazily by :data:`COLLISION_MODELS` / :func:`collision_model`.

The strategy interface: ``name``; ``accelerate(solver)`` fills ``solver.fields.parcel_a_coll``
(an acceleration, m/s^2, applied in the push) and may also change ``solver.pool.particles.v``
directly (a velocity jump, as the surrogate's post-collision velocities are); optional
``advance(solver)`` replaces the push (the strategy integrates the parcels itself, e.g. ``dem``
with Hertz sub-steps at the DEM dt and the fluid acceleration held over the step; it must still
record ``solver.fields.parcel_drag_impulse`` for the momentum hand-back); optional ``counts()``
returns this step's collision counts ``{name: int}`` for the run output.

Momentum bookkeeping: the push records each parcel's drag impulse; the next step's deposit hands
minus that to the gas (one step later), so particles + gas + :meth:`HelSolver.momentum_in_flight`
(minus the drag impulses of the last push, owed to the gas) is conserved by the coupling. The float64 sums are copied into
the gas solver's float32 arrays, so the gas side holds them to float32 round-off.

Walls (SDF reflection, e_n = e_t = 0.8), injection timing and outlets are the integration step that
follows; ``pool.remove_beyond_plane`` and ``pool.inject`` already exist.
"""

from __future__ import annotations

from dataclasses import dataclass

from hel_warp.coupling import (CouplingFields, GridSpec, PushConfig, deposit_parcels, interpolate_gas,
                               ktgf_collision, push_parcels)
from hel_warp.errors import ConfigError, require_positive
from hel_warp.parcels import ParcelPool


class NoCollision:
    """``none``: parcels do not interact (a_coll stays zero)."""

    name = "none"

    def accelerate(self, solver: "HelSolver") -> None:
        solver.fields.parcel_a_coll.zero_()


class KtgfCollision:
    """``ktgf``: granular-pressure collision acceleration (paper eqs. (5)-(8), Table 1).

    Monodisperse closures: ``particle_diameter`` (m) and ``particle_density`` (kg/m^3) are the ones
    of the KTGF solids phase.
    """

    name = "ktgf"

    def __init__(self, *, particle_diameter: float, particle_density: float, restitution: float = 0.9,
                 packing: float = 0.63, friction_packing: float = 0.61, friction_angle_deg: float = 30.0):
        from kernels.ktgf import make_ktgf_params

        require_positive("particle_diameter", particle_diameter, "m")
        require_positive("particle_density", particle_density, "kg/m^3")
        if not 0.0 < restitution <= 1.0:
            raise ConfigError(f"restitution must lie in (0, 1] (got {restitution})")
        if not 0.0 < friction_packing < packing < 1.0:
            raise ConfigError(f"need 0 < friction_packing < packing < 1 (got {friction_packing}, {packing})")
        self.params = make_ktgf_params(particle_diameter=particle_diameter, particle_density=particle_density,
                                       restitution=restitution, packing=packing, friction_packing=friction_packing,
                                       friction_angle_deg=friction_angle_deg)

    def accelerate(self, solver: "HelSolver") -> None:
        ktgf_collision(solver.grid, solver.pool.particles, solver.fields, self.params)


class _CollisionModels:
    """name -> strategy class. ``none`` and ``ktgf`` live here; ``surrogate``, ``surrogate-paper`` and
    ``dem`` are resolved lazily from ``hel_warp.collision_models`` (classes ``SurrogateCollision``,
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
                module = importlib.import_module("hel_warp.collision_models")
            except ModuleNotFoundError as err:
                if err.name != "hel_warp.collision_models":
                    raise
                raise ConfigError(f"collision model {name!r} lives in hel_warp.collision_models, which is not "
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
class HelConfig:
    """Settings of the HEL loop."""

    dt: float = 1e-3
    """Time step of gas and parcels, s (the paper's HEL runs use 1e-3, 1e-4, 7.14e-5)."""
    push: PushConfig = PushConfig()
    """Drag law and gas properties seen by the parcels (must match the gas solver's)."""

    def __post_init__(self):
        require_positive("dt", self.dt, "s")


class HelSolver:
    """Parcels (``ParcelPool``) coupled two-way to engineer F's ``GasSolver`` on its grid.

    ``gas_solver``/``gas``: ``hel_warp.gas.GasSolver`` and its ``GasField`` (or any objects with
    ``step(gas, dt)`` and ``cell_velocity``, ``cell_grad_p``, ``cell_eps_s``, ``cell_momentum_source``,
    ``cell_drag_coeff`` float32 cell arrays). Updates ``pool.particles`` and ``gas`` in place.
    """

    def __init__(self, *, pool: ParcelPool, gas_solver, gas, config: HelConfig, collision=None):
        self.pool = pool
        self.gas_solver = gas_solver
        self.gas = gas
        self.config = config
        self.collision = collision if collision is not None else NoCollision()
        grid = gas.domain.grid if hasattr(gas, "domain") else gas_solver.domain.grid
        self.grid = GridSpec.of(grid)
        gas_config = getattr(gas_solver, "config", None)
        if gas_config is not None:
            for name, ours, theirs in (("density", config.push.fluid_density, gas_config.density),
                                       ("viscosity", config.push.fluid_viscosity, gas_config.viscosity)):
                if abs(ours - theirs) > 1e-12 * abs(theirs):
                    raise ConfigError(f"gas {name} differs between the parcels ({ours}) and the gas solver "
                                      f"({theirs}); give the same value to PushConfig and GasConfig")
        self.fields = CouplingFields.allocate(self.grid, pool.capacity, device=pool.particles.device)
        self.push_params = config.push.params(config.dt)
        self.time = 0.0

    # ------------------------------------------------------------------ the five sub-steps
    def deposit(self) -> None:
        """1. parcels -> cells; hand eps_s, momentum source, sum beta V to the gas."""
        import warp as wp

        from kernels.deposit import to_float32

        deposit_parcels(self.grid, self.pool.particles, self.fields)
        wp.copy(self.gas.cell_eps_s, self.fields.cell_eps_s)
        to_float32(self.fields.cell_momentum_source, self.fields.cell_drag_coeff,
                   cell_momentum_source_f32=self.gas.cell_momentum_source,
                   cell_drag_coeff_f32=self.gas.cell_drag_coeff)

    def gas_step(self) -> None:
        """2. eps_f-weighted Navier-Stokes step with the particle momentum source (engineer F)."""
        self.gas_solver.step(self.gas, self.config.dt)

    def interpolate(self) -> None:
        """3. gas velocity, grad p' and eps_s at the parcels, with the deposit's weights."""
        interpolate_gas(self.grid, self.pool.particles, self.gas.cell_velocity, self.gas.cell_grad_p, self.fields)

    def collide(self) -> None:
        """4. the collision model's acceleration (and/or velocity jumps)."""
        self.collision.accelerate(self)

    def push(self) -> None:
        """5. eq. (4), semi-implicit drag; records the drag impulses for the next deposit.

        A strategy with ``advance(solver)`` moves the parcels itself instead (CFD-DEM sub-steps)."""
        advance = getattr(self.collision, "advance", None)
        if advance is not None:
            advance(self)
        else:
            push_parcels(self.pool.particles, self.fields, self.push_params)

    def collision_counts(self) -> dict:
        """This step's collision counts from the strategy's optional ``counts()`` ({} when it has none)."""
        counts = getattr(self.collision, "counts", None)
        return dict(counts()) if counts is not None else {}

    def step(self) -> None:
        """One HEL step of ``config.dt``."""
        self.deposit()
        self.gas_step()
        self.interpolate()
        self.collide()
        self.push()
        self.time += self.config.dt

    # ------------------------------------------------------------------ diagnostics (host reads)
    def momentum_in_flight(self):
        """Momentum (N s, numpy (3,)) the gas receives at the next deposit: minus the last push's drag impulses."""
        import numpy as np

        alive = self.pool.particles.alive.numpy().astype(bool)
        return -self.fields.parcel_drag_impulse.numpy()[alive].sum(axis=0).astype(np.float64)

"""A gas-free granular flow in a triply periodic box: parcels fly on straight lines and collide.

No gas, no drag, no walls: the collision model is the only physics, which makes the box the place to check each
model against kinetic theory (``cases/homogeneous_cooling.py``: Haff's cooling law, Enskog's collision
frequency). Per step of dt, by model ("flights"):

- ``none``: ballistic, ``x += v dt``, wrapped into [0, L);
- ``ktgf``: the engine's KTGF term (``hel_warp.hel.KtgfCollision``) as the HEL step applies it, on a periodic grid
  of about ``KTGF_CELL`` (rounded to tile the box): the parcels deposited with the engine's cloud-in-cell coupling,
  each parcel kicked by a = -grad(p_s) / (eps_s rho_p) (limited to h / dt^2), then the ballistic move. It has no
  binary collisions (count 0); in a homogeneous gas its only gradients are those of the sampling noise;
- ``surrogate`` / ``surrogate-paper`` (HELSCM): ``strategy.collide(particles, dt)`` (swept: the step's collisions
  in time order; overlap: the pairs overlapping now; cell: stochastic per collision cell tiling the box), the
  ballistic move, the strategy's in-step position corrections, the wrap;
- ``dem``: Hertz-Mindlin sub-steps across dt (``DemCollision.advance_free``: contacts only, periodic, wrapped).
"""

from __future__ import annotations

import inspect
import time as _time
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from hel_warp.errors import ConfigError, HelWarpError

KTGF_CELL = 1.0e-3
"""Target cell size of the KTGF grid in a periodic box, m (the colliding-streams rig's)."""


def _accepts(func, name: str) -> bool:
    try:
        return name in inspect.signature(func).parameters
    except (TypeError, ValueError):
        return False


@dataclass(frozen=True, kw_only=True)
class GranularConfig:
    """Settings of a gas-free periodic run."""

    dt: float
    """Time step, s."""
    box: tuple
    """Periodic box sides (Lx, Ly, Lz), m (origin 0)."""
    collisions: str
    """Collision model name."""


class BallisticFlight:
    """``none``: x += v dt, wrapped."""

    name = "none"

    def __init__(self, box, **_):
        self.box = tuple(float(b) for b in box)
        self.notes = []
        self.strategy = None

    def step(self, particles, dt: float) -> None:
        from kernels.free_flight import drift, wrap_periodic

        drift(particles.x, particles.v, particles.alive, dt)
        wrap_periodic(particles.x, particles.alive, self.box)

    def counts(self) -> dict:
        return {}

    def diagnostics(self, particles) -> dict:
        return {}


class KtgfFlight(BallisticFlight):
    """``ktgf``: deposit on a periodic grid, the engine's KTGF acceleration, v += a dt, then the ballistic move."""

    name = "ktgf"

    def __init__(self, box, *, parcels: int, device, ktgf_diameter: float, density: float, restitution: float,
                 dt: float, **_):
        from hel_warp.parcels.coupling import CouplingFields, GridSpec
        from hel_warp.hel import KtgfCollision

        super().__init__(box)
        L = self.box[0]
        cells = max(3, int(round(L / KTGF_CELL)))
        self.grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=L / cells, shape=(cells,) * 3,
                             periodic=(True, True, True))
        self.fields = CouplingFields.allocate(self.grid, parcels, device=device)
        self.ktgf_diameter = ktgf_diameter
        self.strategy = KtgfCollision(particle_diameter=ktgf_diameter, particle_density=density,
                                      restitution=restitution)
        self.dt = dt
        self.notes = [f"ktgf: the engine's KtgfCollision on a periodic {cells}^3 grid of h = {L / cells:.4g} m "
                      f"({parcels / cells**3:.3g} parcels per cell), deposited with the engine's cloud-in-cell "
                      "coupling, no gas (no drag, K_sg = 0); it has no binary collisions (count 0); what it does "
                      "to Theta comes from the sampling-noise gradients of p_s only"]

    def step(self, particles, dt: float) -> None:
        from hel_warp.parcels.coupling import deposit_parcels
        from kernels.free_flight import kick

        deposit_parcels(self.grid, particles, self.fields)
        view = SimpleNamespace(grid=self.grid, pool=SimpleNamespace(particles=particles), fields=self.fields,
                               config=SimpleNamespace(dt=dt))
        self.strategy.accelerate(view)
        kick(particles.v, self.fields.parcel_a_coll, particles.alive, dt)
        super().step(particles, dt)

    def diagnostics(self, particles) -> dict:
        """The KTGF cell state of the last step: eps_s-weighted cell Theta, |a_coll| dt (velocity kick per step)."""
        eps = self.fields.cell_eps_s.numpy().astype(np.float64)
        theta = self.fields.cell_theta.numpy().astype(np.float64)
        a = np.linalg.norm(self.fields.parcel_a_coll.numpy().astype(np.float64), axis=1)
        return {"ktgf_cell_theta_eps_weighted": float((eps * theta).sum() / max(eps.sum(), 1e-300)),
                "ktgf_cell_theta_max": float(theta.max()), "ktgf_cell_eps_s_max": float(eps.max()),
                "ktgf_cells_with_solids": int((eps > float(self.strategy.params.eps_s_min)).sum()),
                "ktgf_kick_mean": float(a.mean() * self.dt), "ktgf_kick_max": float(a.max() * self.dt)}


class SurrogateFlight(BallisticFlight):
    """``surrogate`` / ``surrogate-paper``: collide (swept: the coming step's collisions; overlap: the current
    positions), x += v dt, the strategy's in-step position corrections, wrap."""

    def __init__(self, box, *, collisions: str, model: str, seed: int, weights, detection: str | None = None,
                 cell: dict | None = None, particle_spin: bool = False, **_):
        import hel_warp.collisions.models as cm

        super().__init__(box)
        self.name = collisions
        cls = cm.SurrogateCollision if collisions == "surrogate" else cm.SurrogatePaperCollision
        kwargs = {"model_dir": model, "periodic_box": self.box}
        if detection is not None:
            kwargs["detection"] = detection
        if detection == "cell":
            kwargs["seed"] = seed  # the collision cells' random numbers
            if cell:
                from hel_warp.collisions.cells import CellConfig

                kwargs["cell"] = CellConfig(**cell)
        if particle_spin:
            kwargs["particle_spin"] = True
        self.strategy = cls(**kwargs)
        self.detection = getattr(self.strategy, "detection", detection or "overlap")
        self._collide_takes_dt = _accepts(self.strategy.collide, "dt")
        self._correct = getattr(self.strategy, "correct_positions", None)
        self.weight = min(weights)
        self.last_substeps = 1
        self._sub_counts = {}

    def substeps(self, particles, dt: float) -> int:
        """Sub-steps of the swept detection this step: its search spans 2 (r_max + v_max dt) and must stay below
        half the periodic box (no parcel meets its own image); a fast gas in a small box takes the step in k equal
        sub-steps, each within that span (1 whenever the whole step fits)."""
        if self.detection != "swept":
            return 1
        p = particles
        alive = p.alive.numpy().astype(bool)
        if not alive.any():
            return 1
        r_max = float(p.radius.numpy()[alive].max())
        v_max = float(np.sqrt((p.v.numpy()[alive].astype(np.float64) ** 2).sum(axis=1)).max())
        half = 0.5 * min(self.box)
        if 2.0 * (r_max + v_max * dt) <= half * (1.0 - 1e-3):
            return 1
        room = 0.45 * half - 2.0 * r_max
        if room <= 0.0:
            raise ConfigError(f"the periodic box of side {min(self.box):.4g} m is smaller than 9 particle diameters; "
                              "raise the particle count or lower the solids fraction")
        return int(np.ceil(2.0 * v_max * dt / room))

    def step(self, particles, dt: float) -> None:
        from kernels.free_flight import drift, wrap_periodic

        k = self.substeps(particles, dt) if self._collide_takes_dt else 1
        self.last_substeps = k
        for _ in range(k):
            h = dt / k
            if self._collide_takes_dt:
                self.strategy.collide(particles, h)
            else:
                self.strategy.collide(particles)
            drift(particles.x, particles.v, particles.alive, h)
            if self._correct is not None:
                self._correct(particles)
            wrap_periodic(particles.x, particles.alive, self.box)
            if k > 1:
                counts = self.strategy.counts()
                for key, value in counts.items():
                    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
                        self._sub_counts[key] = self._sub_counts.get(key, 0) + value

    def counts(self) -> dict:
        if self.last_substeps > 1:  # the sub-steps' counts, summed
            total, self._sub_counts = self._sub_counts, {}
            return total
        return dict(self.strategy.counts())


class DemFlight(BallisticFlight):
    """``dem``: ``DemCollision(periodic_box=...).advance_free(particles, dt)`` (contacts only, wraps positions)."""

    name = "dem"

    def __init__(self, box, *, material, **_):
        from hel_warp.collisions.cfd_dem import DemCollision

        super().__init__(box)
        self.strategy = DemCollision(material=material, periodic_box=self.box)

    def step(self, particles, dt: float) -> None:
        self.strategy.advance_free(particles, dt)

    def counts(self) -> dict:
        return dict(self.strategy.counts())


FLIGHTS = {"none": BallisticFlight, "ktgf": KtgfFlight, "surrogate": SurrogateFlight,
           "surrogate-paper": SurrogateFlight, "dem": DemFlight}


class GranularSimulation:
    """Parcels of a gas-free periodic box advanced by one of the :data:`FLIGHTS` (the interface ``hel_warp.runs.run.Run``
    drives: ``step``, ``time``, ``step_count``, ``state`` / ``set_state``, ``check_finite``, ``collision_counts``).

    ``observers``: objects with ``after_step(sim)`` (and optionally ``state()`` / ``set_state(state)`` for the
    checkpoints), called after every step, e.g. a case's per-step record of the velocity moments."""

    def __init__(self, particles, config: GranularConfig, flight, *, observers=()):
        from hel_warp.parcels.coupling import GridSpec

        self.config = config
        self.flight = flight
        self.particles = particles
        self.pool = SimpleNamespace(particles=particles, capacity=particles.count, used=particles.count,
                                    removed_count=lambda: 0, alive_count=lambda: int(particles.alive.numpy().sum()))
        strategy = flight.strategy
        self.collision = SimpleNamespace(name=config.collisions, config=getattr(strategy, "config", None),
                                         strategy=strategy)
        box = config.box
        self.grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=float(min(box)), shape=(1, 1, 1),
                             periodic=(True, True, True))
        self.gas = None
        self.gas_solver = None
        self.time = 0.0
        self.step_count = 0
        self.timings: dict[str, float] = {}
        self.last_counts: dict = {}
        """The collision counts of the last step (``flight.counts()``, read once per step)."""
        self.observers = list(observers)

    def step(self) -> None:
        start = _time.perf_counter()
        self.flight.step(self.particles, self.config.dt)
        self.last_counts = self.flight.counts()
        self.time += self.config.dt
        self.step_count += 1
        self.timings = {"flight": _time.perf_counter() - start}
        for observer in self.observers:
            observer.after_step(self)

    def collision_counts(self) -> dict:
        return dict(self.last_counts)

    def wall_hit_count(self) -> int:
        return 0

    def check_finite(self) -> None:
        x = self.particles.x.numpy()
        v = self.particles.v.numpy()
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
            raise HelWarpError(f"NaN/inf in the parcel positions or velocities at step {self.step_count} (t = "
                               f"{self.time:.6g} s): reduce dt or check the start")

    def state(self) -> dict:
        from hel_warp.parcels.particles import FIELDS_FLOAT, FIELDS_INT, FIELDS_VEC3

        p = self.particles
        out = {f"particles/{n}": getattr(p, n).numpy().copy() for n in FIELDS_VEC3 + FIELDS_FLOAT + FIELDS_INT}
        out["time"] = np.array(self.time, np.float64)
        out["step"] = np.array(self.step_count, np.int64)
        strategy_state = getattr(self.flight.strategy, "state", None)
        if strategy_state is not None:
            out.update({f"collision/{k}": np.asarray(v) for k, v in strategy_state().items()})
        for k, observer in enumerate(self.observers):
            if hasattr(observer, "state"):
                out.update({f"observer{k}/{name}": np.asarray(v) for name, v in observer.state().items()})
        return out

    def set_state(self, state: dict) -> None:
        from hel_warp.parcels.particles import FIELDS_FLOAT, FIELDS_INT, FIELDS_VEC3

        p = self.particles
        for n in FIELDS_VEC3 + FIELDS_FLOAT + FIELDS_INT:
            value = np.asarray(state[f"particles/{n}"])
            if value.shape != tuple(getattr(p, n).shape) + (() if value.ndim == 1 else (3,)):
                raise ConfigError(f"checkpoint entry particles/{n} has shape {value.shape}; resume with the options "
                                  "that wrote it")
            getattr(p, n).assign(value)
        self.time = float(state["time"])
        self.step_count = int(state["step"])
        set_strategy_state = getattr(self.flight.strategy, "set_state", None)
        if set_strategy_state is not None:
            set_strategy_state({k[len("collision/"):]: v for k, v in state.items() if k.startswith("collision/")})
        for k, observer in enumerate(self.observers):
            if hasattr(observer, "set_state"):
                prefix = f"observer{k}/"
                observer.set_state({name[len(prefix):]: v for name, v in state.items() if name.startswith(prefix)})

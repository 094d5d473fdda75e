"""From a :class:`~hel_warp.case.flow.Flow` to a running simulation.

``build(flow, settings)`` makes, in this order: the grid and the fluid geometry (``hel_warp.gas.grid``), the gas solver
and its field (``hel_warp.gas.solver``), the parcel pool with the initial fills and placed parcels, the collision
strategy, and the HEL solver (``hel_warp.hel.HelSolver``) that steps them together, with the flow's inlet
schedules, explicit releases and observers (:class:`CaseSolver`). A flow without gas becomes a
:class:`~hel_warp.case.granular.GranularSimulation` (a periodic box of colliding parcels).

``Settings`` are the run's choices that are not the flow's: the collision model and its options, dt, seed,
device. ``hel_warp.case.main`` fills them from the command line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hel_warp.errors import ConfigError, HelWarpError
from hel_warp.hel import HelSolver


@dataclass(frozen=True, kw_only=True)
class Settings:
    """The run's choices (validated by ``hel_warp.case.main`` before anything is built)."""

    collisions: str = "none"
    """Collision model: none, ktgf, surrogate, surrogate-paper, dem."""
    dt: float = 1.0e-3
    """Time step, s."""
    seed: int = 0
    """Seed of the fills, injectors and stochastic collision cells."""
    device: str = "cpu"
    model: str | None = None
    """Surrogate model directory (``hel-warp train`` output)."""
    strategy: dict = field(default_factory=dict)
    """Keyword arguments of the collision strategy (the flow's ``collision_defaults`` for the model, overridden
    by these)."""
    particle_contacts: bool = True
    """``dem``: False switches the particle-particle contacts off (the walls-only reference)."""
    particle_spin: bool = False
    """``surrogate``: particle-particle collisions at the contact point, the spins turned."""
    read_back: str = "auto"
    """``HelConfig.read_back``: when the host reads the device (auto, step, output)."""


def sauter_mean_diameter(flow) -> float:
    """The one diameter of the KTGF closures: a mixture's Sauter mean d_32 = sum N E[d^3] / sum N E[d^2] over the
    real particles (one species: its mean diameter)."""
    species = flow.species_list
    if len(species) == 1:
        return species[0].diameter
    counts = {s.name: 0.0 for s in species}
    for fill in flow.fills:
        counts[fill.species] += fill.real_particles(flow.species_named(fill.species))
    for inj in flow.injectors:
        sp = flow.species_named(inj.species)
        if inj.count is not None:
            counts[inj.species] += inj.count * sp.weight
        else:
            mass = inj.mass if inj.mass is not None else inj.mass_flow * (inj.end - inj.start)
            counts[inj.species] += mass / sp.particle_mass
    for ps in flow.particle_sets:
        counts[ps.species] += len(ps.x)
    if not any(counts.values()):
        counts = {s.name: 1.0 for s in species}
    cube = sum(counts[s.name] * (s.diameter**3 + 3 * s.diameter * s.diameter_std**2) for s in species)
    square = sum(counts[s.name] * (s.diameter**2 + s.diameter_std**2) for s in species)
    return cube / square


def collision_strategy(flow, settings: Settings, *, periodic_box=None):
    """The collision strategy of the run (``hel_warp.hel.collision_model``), with the flow's defaults for it."""
    from hel_warp.hel import collision_model

    name = settings.collisions
    options = dict(flow.collision_defaults.get(name, {}))
    options.update(settings.strategy)
    material = flow.species_list[0].material
    if name == "none":
        return collision_model("none")
    if name == "ktgf":
        kwargs = {"particle_diameter": sauter_mean_diameter(flow), "particle_density": material.density,
                  "restitution": material.restitution}
        kwargs.update(options)
        return collision_model("ktgf", **kwargs)
    if name in ("surrogate", "surrogate-paper"):
        if not settings.model:
            raise ConfigError(f"--collisions {name} needs --model MODEL_DIR (a `hel-warp train` output)")
        kwargs = {"model_dir": settings.model}
        if name == "surrogate":
            kwargs["seed"] = settings.seed
            if periodic_box is not None:
                kwargs["periodic_box"] = periodic_box
            cell = options.pop("cell", None)
            if isinstance(cell, dict) and cell:
                from hel_warp.collisions.cells import CellConfig

                cell = CellConfig(**cell)
            if cell:
                kwargs["cell"] = cell
            kwargs.update(options)
        return collision_model(name, **kwargs)
    if name == "dem":
        kwargs = {"material": material}
        if not settings.particle_contacts:
            kwargs["particle_contacts"] = False
        if periodic_box is not None:
            kwargs["periodic_box"] = periodic_box
        kwargs.update(options)
        return collision_model("dem", **kwargs)
    raise ConfigError(f"unknown collision model {name!r}")


# ---------------------------------------------------------------------------------------------- geometry
def grid_of(flow):
    from hel_warp.gas.grid import Grid

    return Grid(origin=flow.lo, spacing=flow.spacing, shape=flow.grid_shape, periodic=flow.periodic)


def fluid_shapes(flow) -> tuple:
    """The fluid region: the flow's shapes, or the domain box extended past every face that parcels cross
    (periodic faces, and open boundaries that remove parcels), so that no wall stands there."""
    from hel_warp.gas.grid import Box

    if flow.shapes is not None:
        return flow.shapes
    lo, hi = list(flow.lo), list(flow.hi)
    beyond = 5.0 * flow.spacing
    for axis in range(3):
        if flow.periodic[axis]:
            lo[axis] -= beyond
            hi[axis] += beyond
    for boundary in flow.boundaries:
        from hel_warp.case.flow import FACES

        axis, side = FACES[boundary.face]
        full = boundary.lo is None and boundary.hi is None
        if boundary.particles == "remove" and full:
            if side == "min":
                lo[axis] -= beyond
            else:
                hi[axis] += beyond
    return (Box(lo=tuple(lo), hi=tuple(hi), name="domain"),)


def patch_region(flow, boundary) -> tuple:
    big = 1.0e3 * max(np.subtract(flow.hi, flow.lo))
    lo = boundary.lo if boundary.lo is not None else tuple(-big for _ in range(3))
    hi = boundary.hi if boundary.hi is not None else tuple(big for _ in range(3))
    return lo, hi


def face_centres(grid, axis: int, side: str, mask_cells: np.ndarray) -> np.ndarray:
    """Centres (n, 3) of the boundary faces on (axis, side) over the selected cells of the boundary layer."""
    centres = grid.cell_centres()
    layer = [slice(None)] * 3
    layer[axis] = 0 if side == "min" else grid.shape[axis] - 1
    c = centres[tuple(layer)].copy()
    c[..., axis] = grid.origin[axis] + (0 if side == "min" else grid.shape[axis]) * grid.spacing
    return c[mask_cells]


def boundary_layer_fluid(grid, shapes, axis: int, side: str, lo, hi) -> np.ndarray:
    """Fluid cells of the boundary layer whose centres lie in the patch region (2D bool)."""
    import warp as wp

    from hel_warp.gas.grid import Geometry
    from kernels import sdf as sdf_kernels

    cell_fluid = wp.zeros(grid.shape, dtype=wp.int32, device="cpu")
    sdf_kernels.eval_fluid_mask(Geometry(shapes=tuple(shapes)).shapes_struct("cpu"), grid.origin, grid.spacing,
                                cell_fluid)
    fluid = cell_fluid.numpy().astype(bool)
    layer = [slice(None)] * 3
    layer[axis] = 0 if side == "min" else grid.shape[axis] - 1
    centres = grid.cell_centres()[tuple(layer)]
    inside = fluid[tuple(layer)].copy()
    for other in range(3):
        if other != axis:
            inside &= (centres[..., other] >= lo[other]) & (centres[..., other] <= hi[other])
    return inside


def geometry_of(flow, grid):
    """(Geometry, {inlet name: (schedule, profile factors or None, axis, side)}, inlet speeds at t = 0)."""
    from hel_warp.case.flow import FACES, Inlet
    from hel_warp.gas.grid import Geometry, Patch

    shapes = fluid_shapes(flow)
    patches, schedules, speeds = [], {}, {}
    for boundary in flow.boundaries:
        axis, side = FACES[boundary.face]
        lo, hi = patch_region(flow, boundary)
        inward = 1.0 if side == "min" else -1.0
        if isinstance(boundary, Inlet):
            cells = boundary_layer_fluid(grid, shapes, axis, side, lo, hi)
            area = float(cells.sum()) * grid.spacing**2
            if area == 0.0:
                raise ConfigError(f"inlet {boundary.name!r} on face {boundary.face} covers no fluid cell at grid "
                                  f"spacing {grid.spacing:.4g} m; move its patch onto the geometry or refine the grid")
            if boundary.flow_rate is not None:
                speed0 = boundary.flow_rate / area
                schedule = None
            else:
                schedule = boundary.velocity
                speed0 = float(schedule(0.0))
            profile = None
            if boundary.profile is not None:
                profile = boundary.profile(face_centres(grid, axis, side, cells))
            speeds[boundary.name] = speed0
            velocity = [0.0, 0.0, 0.0]
            # the inlet's velocity vector must point into the domain at construction: the schedule's sign
            # is set on the faces below (a schedule that starts at 0 is built with a unit speed and zeroed)
            velocity[axis] = inward * (speed0 if speed0 > 0 else 1.0)
            patches.append(Patch(name=boundary.name, kind="inlet", axis=axis, side=side, lo=lo, hi=hi,
                                 velocity=tuple(velocity)))
            if schedule is not None or profile is not None:
                schedules[boundary.name] = (schedule, profile, axis, side)
        else:
            patches.append(Patch(name=boundary.name, kind="outlet", axis=axis, side=side, lo=lo, hi=hi,
                                 pressure=boundary.pressure))
    return Geometry(shapes=shapes, patches=tuple(patches)), schedules, speeds


# ---------------------------------------------------------------------------------------------- parcels
def _derived_seed(seed: int, *path: int) -> int:
    return int(np.random.SeedSequence([int(seed), *path]).generate_state(1)[0])


def fill_injections(flow, settings: Settings, *, progress=None):
    """(ScheduledInjection list released at t = 0, placed parcel arrays list, capacity, fill notes)."""
    from hel_warp.case import packing
    from hel_warp.case.flow import RANDOM_CLOSE_PACKING
    from hel_warp.hel import ScheduledInjection

    releases, placed, capacity, notes = [], [], 0, []
    for k, fill in enumerate(flow.fills):
        sp = flow.species_named(fill.species)
        stream = fill.stream if fill.stream is not None else flow.species_index(fill.species)
        real = fill.real_particles(sp)
        volume = float(np.prod(np.subtract(fill.region.hi, fill.region.lo)))
        fraction = real * sp.particle_volume / volume
        if fraction > RANDOM_CLOSE_PACKING:
            raise ConfigError(f"fill of {fill.species!r}: {real} particles fill {fraction:.3f} of its region, more than "
                              f"random close packing {RANDOM_CLOSE_PACKING}; enlarge the region or fill fewer")
        seed = _derived_seed(settings.seed, 1, k)
        if fill.settles and sp.weight == 1:
            bed = packing.poured_bed(sp, fill.region, real, flow.gravity, seed, dense=fill.packing == "dense",
                                     device="cpu", progress=progress)
            n = len(bed["x"])
            v = np.tile(np.asarray(fill.velocity, float), (n, 1))
            placed.append({"x": bed["x"], "radius": bed["radius"], "v": v, "density": sp.density,
                           "weight": sp.weight, "stream": stream})
            notes.append(f"{fill.species}: a bed of {n} spheres poured in {bed['pour_time']:.2f} s of DEM, "
                         f"{bed['height'] * 1e3:.1f} mm high at solids fraction {bed['solids_fraction']:.3f}")
            capacity += n
            continue
        parcels = max(1, int(round(real / sp.weight)))
        if fill.settles:
            injection = packing.weighted_bed(sp, fill.region, parcels, real, fill.settled_fraction, flow.gravity,
                                             seed)
        else:
            injection = packing.random_injection(sp, fill.region, parcels, seed, fill.velocity)
        from dataclasses import replace

        injection = replace(injection, stream=int(stream))
        releases.append(ScheduledInjection(injection=injection, t_start=0.0, t_end=0.0))
        capacity += parcels
    for ps in flow.particle_sets:
        sp = flow.species_named(ps.species)
        n = len(ps.x)
        radius = 0.5 * sp.diameter if ps.radius is None else np.asarray(ps.radius, float)
        weight = sp.weight if ps.weight is None else np.asarray(ps.weight, float)
        stream = flow.species_index(ps.species) if ps.stream is None else np.asarray(ps.stream, np.int32)
        placed.append({"x": np.asarray(ps.x, float), "radius": radius,
                       "v": np.zeros((n, 3)) if ps.v is None else np.asarray(ps.v, float), "density": sp.density,
                       "weight": weight, "stream": stream})
        capacity += n
    return releases, placed, capacity, notes


def injector_schedule(flow, settings: Settings, first_index: int):
    """(ScheduledInjection list, capacity) of the flow's injectors."""
    from hel_warp.hel import ScheduledInjection
    from hel_warp.parcels.pool import VolumeInjection

    out, capacity = [], 0
    for k, inj in enumerate(flow.injectors):
        sp = flow.species_named(inj.species)
        stream = inj.stream if inj.stream is not None else flow.species_index(inj.species)
        seed = inj.seed if inj.seed is not None else _derived_seed(settings.seed, 2, k)
        lo, hi = inj.region.lo, inj.region.hi
        amount = {}
        if inj.count is not None:
            amount["count"] = int(inj.count)
            capacity += int(inj.count)
        else:
            mass = inj.mass if inj.mass is not None else inj.mass_flow * (inj.end - inj.start)
            amount["mass"] = float(mass)
            capacity += int(math.ceil(1.3 * mass / (sp.weight * sp.particle_mass))) + 16
        volume = VolumeInjection(box_lo=lo, box_hi=hi, diameter_mean=sp.diameter, diameter_std=sp.diameter_std,
                                 density=sp.density, speed=float(inj.speed), direction=inj.direction,
                                 weight=sp.weight, stream=int(stream), seed=int(seed), **amount)
        out.append(ScheduledInjection(injection=volume, t_start=float(inj.start),
                                      t_end=float(inj.end if inj.end is not None else inj.start)))
    return out, capacity


# ---------------------------------------------------------------------------------------------- the HEL solver
class CaseSolver(HelSolver):
    """``HelSolver`` with what a flow adds around the step: inlet speeds that follow their schedules (set on the
    inlet faces before each step, for the step's end time), parcels released at given times and places, and
    observers called after each step (their ``state()`` goes into the checkpoints)."""

    def __init__(self, *, inlet_schedules=None, releases=(), observers=(), **kwargs):
        self._inlets = []
        self._timed_releases = list(releases)
        self._released = 0
        self.observers = list(observers)
        super().__init__(**kwargs)
        domain = self.gas.domain
        for name, (schedule, profile, axis, side) in (inlet_schedules or {}).items():
            _, mask = domain.patch_faces[name]
            array = (domain.face_bc.velocity_x, domain.face_bc.velocity_y, domain.face_bc.velocity_z)[axis]
            shape = np.ones(int(mask.sum())) if profile is None else np.asarray(profile, np.float64)
            self._inlets.append({"name": name, "schedule": schedule, "mask": mask, "array": array, "axis": axis,
                                 "sign": 1.0 if side == "min" else -1.0, "shape": shape, "value": None})
        self.set_inlets(self.time)

    def inlet_speed(self, name: str, t: float) -> float:
        for inlet in self._inlets:
            if inlet["name"] == name:
                return float(inlet["schedule"](t)) if inlet["schedule"] is not None else 1.0
        raise KeyError(name)

    def set_inlets(self, t: float) -> None:
        """Inlet faces at their schedules' speed at time ``t`` (a host write when a speed changes; none otherwise)."""
        for inlet in self._inlets:
            value = float(inlet["schedule"](t)) if inlet["schedule"] is not None else 1.0
            if value == inlet["value"]:
                continue
            host = inlet["array"].numpy().copy() if inlet.get("host") is None else inlet["host"]
            inlet["host"] = host
            host[inlet["mask"], inlet["axis"]] = inlet["sign"] * value * inlet["shape"]
            inlet["array"].assign(host)
            # the gas step keeps inlet faces fixed at the velocity they hold: set that too, not only the BC record
            faces = (self.gas.face_velocity.x, self.gas.face_velocity.y, self.gas.face_velocity.z)[inlet["axis"]]
            current = faces.numpy()
            current[inlet["mask"]] = host[inlet["mask"], inlet["axis"]]
            faces.assign(current)
            inlet["value"] = value

    def release_due(self) -> None:
        """Explicit releases due by the start of this step (exact positions)."""
        import warp as wp

        tolerance = 1e-6 * self.config.dt
        while self._released < len(self._timed_releases) and self._timed_releases[self._released]["time"] <= self.time + tolerance:
            r = self._timed_releases[self._released]
            for k in range(len(r["x"])):
                self.pool.inject(r["injection"][k])
                slot = self.pool.used - 1
                wp.copy(self.pool.particles.x, wp.array(r["x"][k][None].astype(np.float32), dtype=wp.vec3,
                                                        device=self.pool.particles.device), dest_offset=slot, count=1)
            self._released += 1

    def step(self) -> None:
        if self._timed_releases:
            self.release_due()
        if self._inlets:
            self.set_inlets(self.time + self.config.dt)
        super().step()
        for observer in self.observers:
            observer.after_step(self)

    def state(self) -> dict:
        out = super().state()
        out["case/released"] = np.array(self._released, np.int64)
        for k, observer in enumerate(self.observers):
            if hasattr(observer, "state"):
                out.update({f"observer{k}/{name}": np.asarray(v) for name, v in observer.state().items()})
        return out

    def set_state(self, state: dict) -> None:
        super().set_state(state)
        self._released = int(state.get("case/released", 0))
        for inlet in self._inlets:
            inlet["value"] = None
        self.set_inlets(self.time)
        for k, observer in enumerate(self.observers):
            if hasattr(observer, "set_state"):
                prefix = f"observer{k}/"
                observer.set_state({n[len(prefix):]: v for n, v in state.items() if n.startswith(prefix)})


@dataclass
class Simulation:
    """What ``build`` returns: the stepping object (``solver``: a ``CaseSolver`` or a ``GranularSimulation``),
    the flow and settings it was built from, and what the build measured (``inlet_speeds`` at t = 0, m/s;
    ``notes``)."""

    flow: object
    settings: Settings
    solver: object
    grid: object = None
    geometry: object = None
    domain: object = None
    inlet_speeds: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)

    @property
    def fluid_cells(self) -> int:
        if self.domain is None:
            return 0
        return int(self.domain.cell_fluid.numpy().sum())

    def warm_up(self) -> int:
        """The gas alone for ``flow.gas.warmup`` s in steps of at most ``warmup_dt`` (the flow established before
        the particles start); returns the steps taken."""
        gas = self.flow.gas
        if gas is None or gas.warmup <= 0:
            return 0
        n = int(math.ceil(gas.warmup / gas.warmup_dt - 1e-9))
        for _ in range(n):
            self.solver.gas_solver.step(self.solver.gas, gas.warmup / n)
        return n


def build(flow, settings: Settings, *, observers=(), progress=None) -> Simulation:
    """The simulation of ``flow`` with ``settings`` (module docstring)."""
    from hel_warp._warp import init_warp

    init_warp(settings.device)
    if not flow.species_list:
        raise ConfigError(f"flow {flow.name!r} has no particle species; add one with flow.species(...)")
    if settings.collisions == "dem":
        heavy = [s.name for s in flow.species_list if s.weight != 1]
        if heavy:
            raise ConfigError(f"--collisions dem resolves real spheres: species {', '.join(heavy)} must have one "
                              "particle per parcel (--particles-per-parcel 1)")
    if flow.gas is None:
        return _build_granular(flow, settings, observers)
    return _build_hel(flow, settings, observers, progress)


def _build_granular(flow, settings: Settings, observers) -> Simulation:
    from hel_warp.case.granular import FLIGHTS, GranularConfig, GranularSimulation
    from hel_warp.parcels.particles import Particles

    if not all(flow.periodic) or any(flow.lo):
        raise ConfigError("a flow without gas runs in a triply periodic box with its origin at 0 (periodic=(True, "
                          "True, True), lo=(0, 0, 0)); give the gas or make the box periodic")
    if flow.fills or flow.injectors or flow.releases or len(flow.particle_sets) != 1:
        raise ConfigError("a flow without gas takes its parcels from one flow.place(...) set")
    box = tuple(np.subtract(flow.hi, flow.lo))
    ps = flow.particle_sets[0]
    sp = flow.species_named(ps.species)
    radius = 0.5 * sp.diameter if ps.radius is None else np.asarray(ps.radius)
    weight = np.full(len(ps.x), float(sp.weight)) if ps.weight is None else np.asarray(ps.weight)
    stream = 0 if ps.stream is None else np.asarray(ps.stream)
    particles = Particles.from_numpy(np.asarray(ps.x), radius, v=ps.v, density=sp.density, weight=weight,
                                     stream=stream, check_overlap=False, device=settings.device)
    options = dict(flow.collision_defaults.get(settings.collisions, {}))
    options.update(settings.strategy)
    ktgf_diameter = options.pop("ktgf_diameter", None) or sauter_mean_diameter(flow)
    flight = FLIGHTS[settings.collisions](box, collisions=settings.collisions, model=settings.model,
                                          seed=settings.seed, parcels=len(ps.x), device=settings.device,
                                          ktgf_diameter=ktgf_diameter, density=sp.density,
                                          restitution=sp.material.restitution, dt=settings.dt,
                                          material=sp.material, weights=[s.weight for s in flow.species_list],
                                          particle_spin=settings.particle_spin, **options)
    sim = GranularSimulation(particles, GranularConfig(dt=settings.dt, box=box, collisions=settings.collisions),
                             flight, observers=observers)
    return Simulation(flow=flow, settings=settings, solver=sim, notes=list(flight.notes))


def _build_hel(flow, settings: Settings, observers, progress) -> Simulation:
    from hel_warp.parcels.coupling import PushConfig
    from hel_warp.gas.solver import GasConfig, GasField, GasSolver
    from hel_warp.hel import HelConfig, Outlet
    from hel_warp.parcels.pool import ParcelPool, VolumeInjection
    from hel_warp.case.flow import FACES

    grid = grid_of(flow)
    geometry, schedules, speeds = geometry_of(flow, grid)
    device = settings.device
    domain = geometry.build(grid, device=device)
    gas_config = GasConfig(density=flow.gas.density, viscosity=flow.gas.viscosity,
                           smagorinsky_constant=flow.gas.smagorinsky_constant,
                           mean_pressure_gradient=flow.gas.mean_pressure_gradient,
                           inlet_superficial=bool(flow.fills) if flow.gas.inlet_superficial is None
                           else bool(flow.gas.inlet_superficial))
    gas_solver = GasSolver(domain, gas_config, device=device)
    gas = GasField(domain, device=device)
    fills, placed, capacity, notes = fill_injections(flow, settings, progress=progress)
    injectors, inj_capacity = injector_schedule(flow, settings, len(fills))
    release_list = []
    for r in flow.releases:
        sp = flow.species_named(r.species)
        streams = r.stream if r.stream is not None else np.full(len(r.x), flow.species_index(r.species))
        injections = []
        for k in range(len(r.x)):
            injections.append(VolumeInjection(box_lo=tuple(r.x[k] - 1e-9), box_hi=tuple(r.x[k] + 1e-9),
                                              diameter_mean=sp.diameter, density=sp.density, count=1,
                                              speed=r.speed, direction=tuple(r.directions[k]),
                                              weight=sp.weight, stream=int(streams[k])))
        release_list.append({"time": r.time, "x": r.x, "injection": injections})
    release_list.sort(key=lambda r: r["time"])
    capacity += inj_capacity + sum(len(r["x"]) for r in release_list)
    if flow.capacity is not None:
        capacity = int(flow.capacity)
    if capacity < 1:
        raise ConfigError(f"flow {flow.name!r} has no particles: add a fill, an injector, placed parcels or releases")
    pool = ParcelPool.empty(capacity, device=device)
    for p in placed:
        pool.place(p["x"], p["radius"], v=p["v"], density=p["density"], weight=p["weight"], stream=p["stream"])
    material = flow.species_list[0].material
    walls = flow.walls
    material_walls = material
    from dataclasses import replace

    if walls.restitution_normal is not None or walls.restitution_tangential is not None:
        material_walls = replace(material, wall_restitution_normal=walls.restitution_normal
                                 if walls.restitution_normal is not None else material.wall_restitution_normal,
                                 wall_restitution_tangential=walls.restitution_tangential
                                 if walls.restitution_tangential is not None else material.wall_restitution_tangential)
    push = PushConfig(drag=flow.gas.drag, fluid_density=gas_config.density, fluid_viscosity=gas_config.viscosity,
                      gravity=flow.gravity)
    outlets = []
    for boundary in flow.boundaries:
        if boundary.particles == "remove":
            axis, side = FACES[boundary.face]
            point = [0.0, 0.0, 0.0]
            normal = [0.0, 0.0, 0.0]
            point[axis] = flow.lo[axis] if side == "min" else flow.hi[axis]
            normal[axis] = -1.0 if side == "min" else 1.0
            outlets.append(Outlet(point=tuple(point), normal=tuple(normal)))
    outlets += [Outlet(point=p, normal=n) for p, n in flow.outlet_planes]
    periodic_box = None
    if all(flow.periodic) and not any(flow.lo):
        periodic_box = tuple(np.subtract(flow.hi, flow.lo))
    collision = collision_strategy(flow, settings, periodic_box=periodic_box)
    extra = {}
    if walls.friction is not None:
        extra["wall_friction"] = walls.friction
    config = HelConfig(dt=settings.dt, push=push, material=material_walls, walls=not all(flow.periodic),
                       wall_contact=walls.contact, wall_spin=walls.spin,
                       particle_spin=settings.particle_spin,
                       injectors=tuple(fills) + tuple(injectors), outlets=tuple(outlets),
                       exchange_pressure=bool(flow.fills) if flow.gas.exchange_pressure is None
                       else bool(flow.gas.exchange_pressure),
                       packing_stress=flow.packing_stress, read_back=settings.read_back, **extra)
    solver = CaseSolver(pool=pool, gas_solver=gas_solver, gas=gas, config=config, collision=collision,
                        inlet_schedules=schedules, releases=release_list, observers=observers)
    return Simulation(flow=flow, settings=settings, solver=solver, grid=grid, geometry=geometry, domain=domain,
                      inlet_speeds=speeds, notes=notes)

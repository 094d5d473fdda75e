"""The description of a flow: what a case script writes, before anything is built.

A :class:`Flow` holds the domain and grid, the fluid geometry (a union of shapes), the gas and its boundaries,
gravity, the particle species, how the particles enter (initial fills, injectors, explicit releases), the
probes and the collision models' defaults. It is plain data, validated as it is written: every mistake a user
can make here is a :class:`~hel_warp.errors.ConfigError` whose one line says what to change. ``hel_warp.case.build``
turns it into a running simulation; ``hel_warp.case.main`` gives it a command line.

Axes and faces: ``x-``/``x+``/``y-``/``y+``/``z-``/``z+`` name the six faces of the domain box ``lo``..``hi``.
Units are SI throughout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from hel_warp.errors import ConfigError, require_finite, require_positive
from hel_warp.gas.grid import Box, Channel, Cylinder
from hel_warp.material import Material

FACES = {"x-": (0, "min"), "x+": (0, "max"), "y-": (1, "min"), "y+": (1, "max"), "z-": (2, "min"),
         "z+": (2, "max")}
"""Face name -> (axis, side)."""

COLLISION_MODELS = ("none", "ktgf", "surrogate", "surrogate-paper", "dem")

RANDOM_CLOSE_PACKING = 0.64
"""Densest solids fraction of randomly packed equal spheres (Scott & Kilgour 1969; Torquato et al. 2000):
no fill may ask for more."""


def _vec3(name: str, value) -> tuple:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.size != 3:
        raise ConfigError(f"{name} must have three components (got {value!r})")
    require_finite(name, arr)
    return tuple(float(v) for v in arr)


def _face(name: str, face: str) -> tuple:
    if face not in FACES:
        raise ConfigError(f"{name}: face must be one of {', '.join(FACES)} (got {face!r})")
    return FACES[face]


@dataclass(frozen=True, kw_only=True)
class Gas:
    """The gas phase (incompressible, eps_f-weighted Navier-Stokes; ``hel_warp.gas.solver``)."""

    density: float = 1.205
    """rho_f, kg/m^3 (air at 20 C)."""
    viscosity: float = 1.81e-5
    """mu_f, Pa s (air at 20 C)."""
    smagorinsky_constant: float = 0.17
    """C_s of the sub-grid viscosity; 0 for laminar flow."""
    mean_pressure_gradient: tuple = (0.0, 0.0, 0.0)
    """An imposed mean gradient of the modified pressure, Pa/m, e.g. to drive a periodic riser."""
    warmup: float = 0.0
    """Gas-only time before the particles start, s (the gas flow established first)."""
    warmup_dt: float = 1.0e-3
    """Largest step of the warm-up, s."""
    drag: str = "gidaspow"
    """Drag law of the parcels: ``gidaspow`` (Wen-Yu above eps_f 0.8, Ergun below) or ``schiller-naumann``."""
    exchange_pressure: bool | None = None
    """The implicit drag exchange relaxes the gas under its pressure gradient held over the step, so that a packed
    bed's drag balances the pressure force (Ergun's pressure drop) instead of being capped near M u / dt per cell
    (``hel_warp.hel.HelConfig.exchange_pressure``). None: on when the flow starts from a filled bed (a ``fill``),
    where it matters; in dilute flows the two agree."""
    inlet_superficial: bool | None = None
    """Inlet velocities are superficial: the gas enters with eps_f = 1 on the inlet faces, whatever solids lie
    beside them (``hel_warp.gas.solver.GasConfig.inlet_superficial``). None: on when the flow starts from a filled bed."""

    def __post_init__(self):
        require_positive("gas density", self.density, "kg/m^3")
        require_positive("gas viscosity", self.viscosity, "Pa s")
        require_finite("smagorinsky_constant", self.smagorinsky_constant)
        object.__setattr__(self, "mean_pressure_gradient", _vec3("mean_pressure_gradient",
                                                                 self.mean_pressure_gradient))
        require_finite("gas warmup", self.warmup)
        if self.warmup < 0:
            raise ConfigError(f"gas warmup must be >= 0 s (got {self.warmup})")
        require_positive("gas warmup_dt", self.warmup_dt, "s")


@dataclass(frozen=True, kw_only=True)
class Walls:
    """How parcels meet the walls of the geometry (HEL; the ``dem`` reference has its own Hertz-Mindlin wall)."""

    restitution_normal: float | None = None
    """Normal restitution at the walls (None: the first species' ``Material.wall_restitution_normal``)."""
    restitution_tangential: float | None = None
    """Tangential restitution at the walls (None: the material's)."""
    friction: float | None = None
    """Coulomb friction at the walls (None: the material's ``friction``)."""
    contact: str = "surface"
    """``surface``: a parcel meets a wall with its surface, as the DEM's spheres; ``point``: with its centre."""
    spin: bool = False
    """Parcels meet the walls as rough spheres that carry their spin."""

    def __post_init__(self):
        for name in ("restitution_normal", "restitution_tangential"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise ConfigError(f"wall {name} must lie in [0, 1] (got {value})")
        if self.friction is not None and not (math.isfinite(self.friction) and self.friction >= 0):
            raise ConfigError(f"wall friction must be >= 0 (got {self.friction})")
        if self.contact not in ("surface", "point"):
            raise ConfigError(f"wall contact must be 'surface' or 'point' (got {self.contact!r})")


@dataclass(frozen=True, kw_only=True)
class Inlet:
    """A velocity inlet on a face, or on the patch of it whose face centres lie in ``lo``..``hi`` (the face's own
    axis is ignored there). The gas enters normal to the face at ``velocity`` m/s (a number, a ``Ramp``, ``Levels``
    or any function of time), shaped over the patch by ``profile``; or at ``flow_rate`` m^3/s, the speed then
    being the flow rate over the discrete patch area (the fluid faces the patch covers on the grid).

    ``particles``: what parcels meet there: ``wall`` (default: a distributor plate, parcels bounce) or ``remove``
    (parcels leave through it)."""

    name: str
    face: str
    velocity: object = None
    flow_rate: float | None = None
    profile: object = None
    lo: tuple | None = None
    hi: tuple | None = None
    particles: str = "wall"

    def __post_init__(self):
        _face(f"inlet {self.name!r}", self.face)
        if (self.velocity is None) == (self.flow_rate is None):
            raise ConfigError(f"inlet {self.name!r}: give exactly one of velocity (m/s) and flow_rate (m^3/s)")
        if self.flow_rate is not None:
            require_positive(f"inlet {self.name!r} flow_rate", self.flow_rate, "m^3/s")
        else:
            from hel_warp.case.schedule import as_schedule

            object.__setattr__(self, "velocity", as_schedule(self.velocity))
        if self.particles not in ("wall", "remove"):
            raise ConfigError(f"inlet {self.name!r}: particles must be 'wall' or 'remove' (got {self.particles!r})")
        _patch_region(self)


@dataclass(frozen=True, kw_only=True)
class Outlet:
    """A pressure outlet on a face (or a patch of it, as :class:`Inlet`) at modified pressure ``pressure`` Pa.
    ``particles``: ``remove`` (default: parcels leave) or ``wall`` (a filter: parcels bounce)."""

    name: str
    face: str
    pressure: float = 0.0
    lo: tuple | None = None
    hi: tuple | None = None
    particles: str = "remove"

    def __post_init__(self):
        _face(f"outlet {self.name!r}", self.face)
        require_finite(f"outlet {self.name!r} pressure", self.pressure)
        if self.particles not in ("wall", "remove"):
            raise ConfigError(f"outlet {self.name!r}: particles must be 'wall' or 'remove' (got {self.particles!r})")
        _patch_region(self)


def _patch_region(patch) -> None:
    for end in ("lo", "hi"):
        value = getattr(patch, end)
        if value is not None:
            arr = np.asarray(value, dtype=np.float64).reshape(-1)
            if arr.size != 3 or np.any(np.isnan(arr)):
                raise ConfigError(f"{patch.name!r}: {end} must be three coordinates, m (got {value!r})")
            object.__setattr__(patch, end, tuple(float(v) for v in arr))


@dataclass(frozen=True, kw_only=True)
class Species:
    """One kind of particle: a size distribution (normal, truncated at 3 sigma), a material, and the real
    particles each parcel stands for (``weight``; the ``dem`` reference needs 1)."""

    name: str
    diameter: float
    diameter_std: float = 0.0
    material: Material = Material()
    weight: float = 1.0

    def __post_init__(self):
        require_positive(f"species {self.name!r} diameter", self.diameter, "m")
        require_finite(f"species {self.name!r} diameter_std", self.diameter_std)
        if not 0.0 <= self.diameter_std < self.diameter / 3.0:
            raise ConfigError(f"species {self.name!r}: diameter_std must lie in [0, diameter / 3) "
                              f"(got {self.diameter_std} m)")
        if not isinstance(self.material, Material):
            raise ConfigError(f"species {self.name!r}: material must be a hel_warp.material.Material")
        require_positive(f"species {self.name!r} weight", self.weight)

    @property
    def density(self) -> float:
        return self.material.density

    @property
    def particle_mass(self) -> float:
        """Mean mass of one real particle, kg: rho pi E[d^3] / 6 with E[d^3] = d^3 + 3 d sigma^2."""
        return self.density * math.pi / 6.0 * (self.diameter**3 + 3.0 * self.diameter * self.diameter_std**2)

    @property
    def particle_volume(self) -> float:
        return self.particle_mass / self.density


@dataclass(frozen=True, kw_only=True)
class Fill:
    """An initial fill of ``region`` (a ``Box``) with one species: ``count`` real particles, or the
    ``solids_fraction`` of the region, or ``mass`` kg. ``packing``:

    - ``random``: parcels at random non-overlapping places over the whole region, at rest or at ``velocity``;
    - ``settled``: a bed at rest packed at the bottom of the region (against gravity), without overlaps: the real
      spheres poured by a short DEM (cached), or, for weighted parcels, placed at random over the height that the
      real particles fill at ``settled_fraction``. Frictional spheres pour into a loose random packing;
    - ``dense``: as ``settled``, the real spheres poured without friction into a dense random packing (towards
      random close packing, as a bed tapped after filling; ``hel_warp.case.packing``), then given their material.
    """

    species: str
    region: Box
    count: int | None = None
    solids_fraction: float | None = None
    mass: float | None = None
    packing: str = "random"
    velocity: tuple = (0.0, 0.0, 0.0)
    settled_fraction: float = 0.6
    """Solids fraction of a settled bed of weighted parcels (the DEM pour's is measured, not assumed)."""
    stream: int | None = None
    """Tag of the parcels in the outputs (None: the species' index)."""

    def __post_init__(self):
        if not isinstance(self.region, Box):
            raise ConfigError(f"fill of {self.species!r}: region must be a Box")
        given = [v is not None for v in (self.count, self.solids_fraction, self.mass)]
        if sum(given) != 1:
            raise ConfigError(f"fill of {self.species!r}: give exactly one of count, solids_fraction and mass")
        if self.count is not None and (int(self.count) != self.count or self.count < 1):
            raise ConfigError(f"fill of {self.species!r}: count must be a positive integer (got {self.count!r})")
        if self.solids_fraction is not None:
            require_finite("fill solids_fraction", self.solids_fraction)
            if not 0.0 < self.solids_fraction <= RANDOM_CLOSE_PACKING:
                raise ConfigError(f"fill of {self.species!r}: solids_fraction {self.solids_fraction} must lie in (0, "
                                  f"{RANDOM_CLOSE_PACKING}] (random close packing); lower it")
        if self.mass is not None:
            require_positive("fill mass", self.mass, "kg")
        if self.packing not in ("random", "settled", "dense"):
            raise ConfigError(f"fill of {self.species!r}: packing must be 'random', 'settled' or 'dense' "
                              f"(got {self.packing!r})")
        object.__setattr__(self, "velocity", _vec3("fill velocity", self.velocity))
        if not 0.3 <= self.settled_fraction <= RANDOM_CLOSE_PACKING:
            raise ConfigError(f"fill settled_fraction must lie in [0.3, {RANDOM_CLOSE_PACKING}] "
                              f"(got {self.settled_fraction})")

    @property
    def settles(self) -> bool:
        """True for a bed at rest on the region's floor (``settled`` or ``dense``): poured, or placed over its
        settled height."""
        return self.packing in ("settled", "dense")

    def real_particles(self, species: Species) -> int:
        """Real particles of the fill."""
        volume = float(np.prod(np.subtract(self.region.hi, self.region.lo)))
        if self.count is not None:
            return int(self.count)
        if self.solids_fraction is not None:
            return max(1, int(round(self.solids_fraction * volume / species.particle_volume)))
        return max(1, int(round(self.mass / species.particle_mass)))


@dataclass(frozen=True, kw_only=True)
class Injector:
    """Parcels released into ``region`` (a ``Box``) over [``start``, ``end``] s at a uniform rate: ``count`` parcels,
    ``mass`` kg of real particles, or ``mass_flow`` kg/s until ``end``; at ``speed`` m/s along ``direction``."""

    species: str
    region: Box
    count: int | None = None
    mass: float | None = None
    mass_flow: float | None = None
    start: float = 0.0
    end: float | None = None
    speed: float = 0.0
    direction: tuple = (1.0, 0.0, 0.0)
    stream: int | None = None
    seed: int | None = None
    """Seed of the positions and sizes (None: derived from the run's ``--seed`` and the injector's index)."""

    def __post_init__(self):
        if not isinstance(self.region, Box):
            raise ConfigError(f"injector of {self.species!r}: region must be a Box")
        given = [v is not None for v in (self.count, self.mass, self.mass_flow)]
        if sum(given) != 1:
            raise ConfigError(f"injector of {self.species!r}: give exactly one of count, mass and mass_flow")
        require_finite("injector start", self.start)
        if self.start < 0:
            raise ConfigError(f"injector start must be >= 0 s (got {self.start})")
        if self.mass_flow is not None:
            require_positive("injector mass_flow", self.mass_flow, "kg/s")
            if self.end is None:
                raise ConfigError(f"injector of {self.species!r}: a mass_flow needs an end time (s)")
        if self.end is not None:
            require_finite("injector end", self.end)
            if self.end < self.start:
                raise ConfigError(f"injector end {self.end} s precedes its start {self.start} s")
        require_finite("injector speed", self.speed)
        if self.speed < 0:
            raise ConfigError(f"injector speed must be >= 0 m/s (got {self.speed}); turn the direction instead")
        object.__setattr__(self, "direction", _vec3("injector direction", self.direction))


@dataclass(frozen=True, kw_only=True)
class Particles:
    """Parcels given one by one (positions, velocities; optional per-parcel radius, weight and stream): a start
    the fills do not describe, e.g. a Maxwellian granular gas."""

    species: str
    x: np.ndarray
    v: np.ndarray | None = None
    radius: np.ndarray | None = None
    weight: np.ndarray | None = None
    stream: np.ndarray | None = None
    check_overlap: bool = True

    def __post_init__(self):
        x = np.asarray(self.x, np.float64)
        if x.ndim != 2 or x.shape[1] != 3 or len(x) == 0:
            raise ConfigError(f"particles of {self.species!r}: x must be an (n, 3) array of positions, m")
        require_finite("particle positions", x)
        if self.v is not None:
            v = np.asarray(self.v, np.float64)
            if v.shape != x.shape:
                raise ConfigError(f"particles of {self.species!r}: v must have the shape of x {x.shape}")
            require_finite("particle velocities", v)


@dataclass(frozen=True, kw_only=True)
class Release:
    """Parcels that appear at ``time`` s at exactly the positions ``x`` (n, 3) with velocity ``speed`` along
    ``directions`` (n, 3): nozzles that emit one particle at a time."""

    species: str
    time: float
    x: np.ndarray
    speed: float
    directions: np.ndarray
    stream: np.ndarray | None = None


@dataclass
class Flow:
    """A flow to simulate. Build it with keyword arguments and the methods below, then hand it to
    ``hel_warp.case.main`` (command line) or ``hel_warp.case.build`` (a simulation object).

    ``lo``, ``hi``: the domain box, m. The grid: ``spacing`` h (m) or ``cells`` (nx, ny, nz) (one of them; with
    ``cells`` the box must give cubic cells). ``periodic``: a flag per axis. ``gas``: a :class:`Gas`, or None
    for a gas-free granular flow (no drag, the parcels fly and collide). ``shapes``: the fluid region as a union of
    ``Box``, ``Channel`` and ``Cylinder`` (None: the whole domain box).
    """

    name: str
    lo: tuple
    hi: tuple
    spacing: float | None = None
    cells: tuple | None = None
    periodic: tuple = (False, False, False)
    gravity: tuple = (0.0, 0.0, 0.0)
    gas: Gas | None = field(default_factory=Gas)
    shapes: tuple | None = None
    walls: Walls = field(default_factory=Walls)
    boundaries: list = field(default_factory=list)
    species_list: list = field(default_factory=list)
    fills: list = field(default_factory=list)
    injectors: list = field(default_factory=list)
    particle_sets: list = field(default_factory=list)
    releases: list = field(default_factory=list)
    probes: list = field(default_factory=list)
    outlet_planes: list = field(default_factory=list)
    """Extra planes (point, outward normal) past which parcels leave (beyond those of the open faces)."""
    packing_stress: object = None
    """Enduring contacts of packed parcels for every collision model but ``dem`` (a ``hel_warp.hel.PackingStress``:
    the MP-PIC particle normal stress, with its onset and contact damping); None: none (dilute flows)."""
    collision_defaults: dict = field(default_factory=dict)
    """Per model name, keyword arguments of its strategy that suit this flow (the command line's options win)."""
    capacity: int | None = None
    """Parcel slots (None: every fill, particle set, release and injector's count, plus what a mass injector needs)."""
    attrs: dict = field(default_factory=dict)
    """What the case stores with its run (JSON), e.g. the layout a report reads."""

    def __post_init__(self):
        self.lo = _vec3("domain lo", self.lo)
        self.hi = _vec3("domain hi", self.hi)
        if any(h <= l for l, h in zip(self.lo, self.hi)):
            raise ConfigError(f"domain hi {self.hi} must exceed lo {self.lo} on every axis")
        self.periodic = tuple(bool(p) for p in self.periodic)
        if len(self.periodic) != 3:
            raise ConfigError(f"periodic must have three flags (got {self.periodic!r})")
        self.gravity = _vec3("gravity", self.gravity)
        if (self.spacing is None) == (self.cells is None):
            raise ConfigError(f"flow {self.name!r}: give exactly one of spacing (m) and cells (nx, ny, nz)")
        extent = np.subtract(self.hi, self.lo)
        if self.cells is not None:
            cells = tuple(int(c) for c in np.atleast_1d(self.cells))
            if len(cells) != 3 or any(c < 1 for c in cells):
                raise ConfigError(f"cells must be three positive integers (got {self.cells!r})")
            sizes = extent / np.asarray(cells)
            if np.ptp(sizes) > 1e-6 * sizes.max():
                raise ConfigError(f"cells {cells} give cells of {sizes.round(9).tolist()} m: the grid needs cubic "
                                  f"cells; choose cells proportional to the box {extent.round(9).tolist()} m")
            self.cells = cells
            self.spacing = float(sizes.mean())
        else:
            require_positive("grid spacing", self.spacing, "m")
            self.cells = tuple(max(1, int(math.ceil(e / self.spacing - 1e-9))) for e in extent)
        if self.packing_stress is not None:
            from hel_warp.hel import PackingStress

            if not isinstance(self.packing_stress, PackingStress):
                raise ConfigError("packing_stress must be a hel_warp.hel.PackingStress or None "
                                  f"(got {type(self.packing_stress).__name__})")
        if self.shapes is not None:
            shapes = tuple(self.shapes)
            for s in shapes:
                if not isinstance(s, (Box, Channel, Cylinder)):
                    raise ConfigError(f"shapes must be Box, Channel or Cylinder (got {type(s).__name__})")
            self.shapes = shapes

    # ------------------------------------------------------------------ boundaries
    def inlet(self, name: str, face: str, velocity=None, *, flow_rate=None, profile=None, lo=None, hi=None,
              particles: str = "wall") -> Inlet:
        """Add a velocity inlet (see :class:`Inlet`)."""
        inlet = Inlet(name=name, face=face, velocity=velocity, flow_rate=flow_rate, profile=profile, lo=lo, hi=hi,
                      particles=particles)
        self._add_boundary(inlet)
        return inlet

    def outlet(self, name: str, face: str, pressure: float = 0.0, *, lo=None, hi=None,
               particles: str = "remove") -> Outlet:
        """Add a pressure outlet (see :class:`Outlet`)."""
        outlet = Outlet(name=name, face=face, pressure=pressure, lo=lo, hi=hi, particles=particles)
        self._add_boundary(outlet)
        return outlet

    def _add_boundary(self, boundary) -> None:
        if any(b.name == boundary.name for b in self.boundaries):
            raise ConfigError(f"a boundary named {boundary.name!r} exists already; give each boundary its own name")
        axis, _ = FACES[boundary.face]
        if self.periodic[axis]:
            raise ConfigError(f"{boundary.name!r} lies on face {boundary.face}, but axis {'xyz'[axis]} is periodic; "
                              "make the axis non-periodic or drop the boundary")
        self.boundaries.append(boundary)

    # ------------------------------------------------------------------ particles
    def species(self, name: str, diameter: float, *, diameter_std: float = 0.0, material: Material | None = None,
                density: float | None = None, weight: float = 1.0) -> Species:
        """Add a particle species (``density`` overrides the material's)."""
        if any(s.name == name for s in self.species_list):
            raise ConfigError(f"a species named {name!r} exists already")
        material = material or Material()
        if density is not None:
            material = replace(material, density=float(density))
        sp = Species(name=name, diameter=diameter, diameter_std=diameter_std, material=material, weight=weight)
        self.species_list.append(sp)
        return sp

    def species_named(self, name: str) -> Species:
        for s in self.species_list:
            if s.name == name:
                return s
        known = ", ".join(s.name for s in self.species_list) or "none yet"
        raise ConfigError(f"no species named {name!r} (known: {known}); add it with flow.species(...) first")

    def species_index(self, name: str) -> int:
        return [s.name for s in self.species_list].index(self.species_named(name).name)

    def fill(self, species, region, *, count=None, solids_fraction=None, mass=None, packing="random",
             velocity=(0.0, 0.0, 0.0), settled_fraction=0.6, stream=None) -> Fill:
        """Fill ``region`` (a Box, or (lo, hi)) with ``species`` at the start (see :class:`Fill`)."""
        name = species.name if isinstance(species, Species) else species
        self.species_named(name)
        fill = Fill(species=name, region=_as_box(region, "fill region"), count=count,
                    solids_fraction=solids_fraction, mass=mass, packing=packing, velocity=velocity,
                    settled_fraction=settled_fraction, stream=stream)
        self._check_region(fill.region, f"fill of {name!r}")
        self.fills.append(fill)
        return fill

    def inject(self, species, region, *, count=None, mass=None, mass_flow=None, start=0.0, end=None, speed=0.0,
               direction=(1.0, 0.0, 0.0), stream=None, seed=None) -> Injector:
        """Release parcels of ``species`` into ``region`` over time (see :class:`Injector`)."""
        name = species.name if isinstance(species, Species) else species
        self.species_named(name)
        injector = Injector(species=name, region=_as_box(region, "injector region"), count=count, mass=mass,
                            mass_flow=mass_flow, start=start, end=end, speed=speed, direction=direction,
                            stream=stream, seed=seed)
        self._check_region(injector.region, f"injector of {name!r}")
        self.injectors.append(injector)
        return injector

    def place(self, species, x, *, v=None, radius=None, weight=None, stream=None, check_overlap=True) -> Particles:
        """Place parcels one by one at the start (see :class:`Particles`)."""
        name = species.name if isinstance(species, Species) else species
        self.species_named(name)
        particles = Particles(species=name, x=x, v=v, radius=radius, weight=weight, stream=stream,
                              check_overlap=check_overlap)
        self.particle_sets.append(particles)
        return particles

    def release(self, species, time: float, x, *, speed: float, directions, stream=None) -> Release:
        """Parcels that appear at ``time`` at exactly ``x`` (see :class:`Release`)."""
        name = species.name if isinstance(species, Species) else species
        self.species_named(name)
        release = Release(species=name, time=float(time), x=np.atleast_2d(np.asarray(x, np.float64)),
                          speed=float(speed), directions=np.atleast_2d(np.asarray(directions, np.float64)),
                          stream=None if stream is None else np.atleast_1d(np.asarray(stream, np.int32)))
        self.releases.append(release)
        return release

    def remove_beyond(self, point, normal) -> None:
        """Parcels past the plane through ``point`` with outward ``normal`` leave the run."""
        self.outlet_planes.append((_vec3("outlet plane point", point), _vec3("outlet plane normal", normal)))

    def probe(self, probe):
        """Add a probe (``hel_warp.case.probes``)."""
        if any(p.name == probe.name for p in self.probes):
            raise ConfigError(f"a probe named {probe.name!r} exists already")
        probe.check(self)
        self.probes.append(probe)
        return probe

    # ------------------------------------------------------------------ checks
    def _check_region(self, region: Box, what: str) -> None:
        lo = np.maximum(region.lo, self.lo)
        hi = np.minimum(region.hi, self.hi)
        if np.any(hi <= lo):
            raise ConfigError(f"{what}: region {list(region.lo)}..{list(region.hi)} lies outside the domain "
                              f"{list(self.lo)}..{list(self.hi)}; move it inside")

    @property
    def grid_shape(self) -> tuple:
        return tuple(self.cells)

    @property
    def real_particles(self) -> int:
        total = 0
        for fill in self.fills:
            total += fill.real_particles(self.species_named(fill.species))
        for ps in self.particle_sets:
            sp = self.species_named(ps.species)
            w = sp.weight if ps.weight is None else np.asarray(ps.weight, np.float64)
            total += int(round(float(np.sum(np.broadcast_to(w, (len(ps.x),))))))
        return total


def _as_box(region, what: str) -> Box:
    if isinstance(region, Box):
        return region
    try:
        lo, hi = region
    except (TypeError, ValueError):
        raise ConfigError(f"{what} must be a Box or a pair (lo, hi) of corners, m (got {region!r})") from None
    return Box(lo=lo, hi=hi, name=what)

"""N-body soft-sphere DEM (Cundall & Strack 1979) with Hertz-Mindlin contacts, on Warp.

Model (fixed): :class:`DEMConfig` — material, walls, gravity, time step, neighbour-list settings —
and the contact constants derived from it. State (changing): :class:`~hel_warp.parcels.particles.Particles`,
the persistent contact list with its shear history, the wall shear history, forces.

One :meth:`DEMSolver.step` (velocity Verlet, ``kernels/integrate.py``)::

    half kick + drift            x <- x + (v + a dt/2) dt
    neighbour list check         rebuild (hash grid + list, shear carried) if max |x - x_build| > skin/2
    contact forces               Hertz-Mindlin particle-particle, then box planes and SDF walls
    half kick                    v <- v + a dt/2

The time step defaults to eq. (12) of the paper for the smallest radius
(``Material.time_step(r_min).chosen``); a larger requested dt is a ConfigError.
:meth:`DEMSolver.simulate` runs n steps with no host synchronisation: the conditional rebuild is a
``wp.capture_if`` (a conditional graph node under capture, on CUDA or with ``capture_on_cpu``; outside a
capture a host branch on the one-int flag: a memory read on the CPU, a pinned copy and a sync on CUDA).
The contact-list overflow counter is checked once at the end of ``simulate`` and raises, never silently
drops contacts.

Collisions: every force evaluation after a drift counts contact onsets (a pair whose overlap became > 0
while it was not touching at the previous step: one real collision; a contact lasting across list
rebuilds is counted once) per stream pair with its impact speed (``kernels/contacts.py``,
:class:`OnsetCounter`); contacts present at construction are not onsets. Read with
:meth:`DEMSolver.onset_counts`, :meth:`DEMSolver.onset_events` (``DEMConfig.onset_events > 0``),
zeroed by :meth:`DEMSolver.reset_onsets`.

On the CPU the same step runs as a half contact list (each pair once) in one fused pass per step
(``kernels/dem_step.py``, ``DEMConfig.half_list``), bit-identical to the full list and separate kernels
that CUDA keeps.
"""

from __future__ import annotations

import math
import sys
from dataclasses import asdict, dataclass, field

import numpy as np

from hel_warp.errors import ConfigError, HelWarpError, require_positive
from hel_warp.material import Material
from hel_warp.parcels.particles import Particles

WALL_NAMES = ("x-", "x+", "y-", "y+", "z-", "z+")


class ContactOverflowError(HelWarpError):
    """A particle had more neighbour candidates than the contact-list capacity."""


@dataclass(frozen=True, kw_only=True)
class DEMConfig:
    """Fixed settings of an N-body DEM run (SI units). Validated at construction."""

    material: Material = field(default_factory=Material)
    """Particle material (E, nu, restitution e, friction mu, rolling friction)."""
    wall_material: Material | None = None
    """Material of the walls; None = rigid walls (their terms in E*, G* vanish) with the particle
    material's restitution and friction."""
    box_lo: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Lower corner of the box, m."""
    box_hi: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Upper corner of the box, m."""
    walls: tuple[str, ...] = WALL_NAMES
    """Which box faces are walls: any of 'x-', 'x+', 'y-', 'y+', 'z-', 'z+' (() = no walls)."""
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    """Gravitational acceleration, m/s^2."""
    dt: float | None = None
    """Time step, s; None = eq. (12) for the smallest radius. Larger than that: ConfigError."""
    max_speed: float = 20.0
    """V_max of the Hertz time step eq. (14), m/s."""
    skin: float | None = None
    """Neighbour-list skin, m; None = 0.3 r_max. Larger: fewer rebuilds, longer rows."""
    contact_capacity: int = 32
    """Slots per particle in the contact list; an overflow raises ContactOverflowError."""
    sort_every: int | None = None
    """Spatially sort the particle arrays every this many list rebuilds (0 = never). None: 10 on the
    CPU (measured: 3.2x faster steps at 3e5 spheres in random memory order, scripts/bench_dem.py
    --shuffle), 0 on CUDA so that ``simulate`` can run as a captured graph."""
    tangential_damping: float = 0.0
    """Dimensionless tangential dashpot c_t of kernels/hertz.py (0 = none)."""
    half_list: bool | None = None
    """Each pair in one row only (j > i), computed once, in fused passes (one per step in ``simulate``,
    two in ``step``; ``kernels/dem_step.py``; bit-identical results). None: on the CPU (its threads run in order), off on
    CUDA (concurrent threads keep the full list). True on CUDA is a ConfigError."""
    sdf_walls: tuple = ()
    """Extra walls: ``@wp.func`` phi(x: vec3) -> float, m, > 0 inside the domain."""
    sdf_gradient_step: float = 1e-6
    """Central-difference step for the SDF normal, m."""
    cuda_graph_steps: int = 50
    """On CUDA: steps per captured CUDA graph in ``simulate`` (0 = launch eagerly). Graphs need
    ``sort_every = 0`` (the sort decision is a host one); otherwise the solver launches eagerly."""
    capture_on_cpu: bool = False
    """Also run ``simulate`` as captured graphs on the CPU device (Warp >= 1.19 records a CPU graph and replays
    it in C++, ``capture_if`` included): the CUDA path through the same calls, tested on the CPU
    (tests/test_device_paths.py); bit-identical to the eager steps with ``sort_every = 0``."""
    n_streams: int = 4
    """Stream tags whose contact onsets are counted separately (tags outside [0, n_streams) count as the
    nearest end)."""
    onset_events: int = 0
    """Capacity of the list of contact onsets (ids, impact speed, step) kept since the last
    ``reset_onsets``; 0 = counts and speed sums only. A full list stops recording; counts stay exact."""

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.box_lo, float), np.asarray(self.box_hi, float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo)) or not np.all(np.isfinite(hi)):
            raise ConfigError(f"box_lo/box_hi must be three finite numbers each (got {self.box_lo}, {self.box_hi})")
        if not np.all(hi > lo):
            raise ConfigError(f"box_hi {self.box_hi} must exceed box_lo {self.box_lo} on every axis")
        unknown = [w for w in self.walls if w not in WALL_NAMES]
        if unknown:
            raise ConfigError(f"unknown wall name(s) {unknown}; choose from {list(WALL_NAMES)}")
        if self.dt is not None:
            require_positive("dt", self.dt, "s")
        require_positive("max_speed", self.max_speed, "m/s")
        if self.skin is not None:
            require_positive("skin", self.skin, "m")
        if self.contact_capacity < 1:
            raise ConfigError(f"contact_capacity must be >= 1 (got {self.contact_capacity}); 32 suits most packings")
        if self.cuda_graph_steps < 0:
            raise ConfigError(f"cuda_graph_steps must be >= 0 (got {self.cuda_graph_steps})")
        if self.sort_every is not None and self.sort_every < 0:
            raise ConfigError(f"sort_every must be >= 0 (got {self.sort_every})")
        if self.n_streams < 1:
            raise ConfigError(f"n_streams must be >= 1 (got {self.n_streams})")
        if self.onset_events < 0:
            raise ConfigError(f"onset_events must be >= 0 (got {self.onset_events})")

    def as_dict(self) -> dict:
        d = asdict(self)
        d["material"] = self.material.as_dict()
        d["wall_material"] = None if self.wall_material is None else self.wall_material.as_dict()
        d["sdf_walls"] = [getattr(f, "key", str(f)) for f in self.sdf_walls]
        return d


@dataclass
class ContactList:
    """Per-particle contact rows (see ``kernels/contacts.py``). The (N, capacity) arrays hold row i in row i
    in the padded layout (every device, the default); a packed list (``DEMSolver`` with the half list on the
    CPU) keeps its rows back to back from ``start[i]`` in the same memory: read it with :meth:`padded`."""

    partner: object
    """(N, capacity) int32 partner index (padded layout: -1 where empty, rows sorted)."""
    count: object
    """(N,) int32 entries used per row."""
    start: object
    """(N,) int32 flat index of row i's first entry (padded: i * capacity)."""
    shear: object
    """(N, capacity) vec3 Mindlin shear displacement, m."""
    touching: object
    """(N, capacity) int32, 1 where the contact was closed at the last force evaluation (onset counting)."""

    def rows(self):
        """The ``kernels.contacts.ContactRows`` view of these arrays (flat views, no copy)."""
        from kernels.contacts import ContactRows

        n, capacity = self.partner.shape
        r = ContactRows()
        r.partner = self.partner.reshape((n * capacity,))
        r.shear = self.shear.reshape((n * capacity,))
        r.touching = self.touching.reshape((n * capacity,))
        r.count, r.start, r.capacity = self.count, self.start, int(capacity)
        return r

    def padded(self) -> dict:
        """Host copies of the rows in the padded layout, whatever the device layout: ``partner`` (-1 where
        empty), ``count``, ``shear``, ``touching`` as (N, capacity) / (N,) numpy arrays."""
        n, capacity = self.partner.shape
        count, start = self.count.numpy(), self.start.numpy().astype(np.int64)
        flat = {"partner": self.partner.numpy().reshape(-1), "shear": self.shear.numpy().reshape(-1, 3),
                "touching": self.touching.numpy().reshape(-1)}
        k = np.arange(capacity)
        used = k[None, :] < count[:, None]
        index = np.where(used, start[:, None] + k[None, :], 0)
        out = {name: a[index] for name, a in flat.items()}
        out["partner"] = np.where(used, out["partner"], -1).astype(np.int32)
        out["shear"] = np.where(used[:, :, None], out["shear"], 0.0).astype(np.float32)
        out["touching"] = np.where(used, out["touching"], 0).astype(np.int32)
        out["count"] = count
        return out

    @classmethod
    def empty(cls, n: int, capacity: int, device) -> "ContactList":
        import warp as wp

        return cls(partner=wp.full((n, capacity), -1, dtype=wp.int32, device=device),
                   count=wp.zeros(n, dtype=wp.int32, device=device),
                   start=wp.array(np.arange(n, dtype=np.int32) * np.int32(capacity), dtype=wp.int32, device=device),
                   shear=wp.zeros((n, capacity), dtype=wp.vec3, device=device),
                   touching=wp.zeros((n, capacity), dtype=wp.int32, device=device))

    def copy_from(self, other: "ContactList") -> None:
        import warp as wp

        wp.copy(self.partner, other.partner)
        wp.copy(self.count, other.count)
        wp.copy(self.start, other.start)
        wp.copy(self.shear, other.shear)
        wp.copy(self.touching, other.touching)


class OnsetCounter:
    """Device counters of contact onsets (new sphere-sphere contacts; ``kernels/contacts.py``) and their host read-back.

    An onset is a pair whose overlap becomes > 0 at a force evaluation while it was not touching at the
    previous one; it is one real binary collision. Counted per stream pair (integer atomics: deterministic)
    with its impact speed, the normal approach speed ``(v_i - v_j) . n`` just before contact. The speed sum
    is kept per particle slot (one writer each: deterministic) and reduced on the host in float64.
    ``event_capacity > 0`` also keeps a list of the onsets (particle ids, speed, sub-step) since the last
    :meth:`reset`; the counts stay exact when the list fills (``truncated`` then says so).
    """

    def __init__(self, particles: Particles, n_streams: int, event_capacity: int = 0):
        import warp as wp

        from kernels.contacts import ContactOnsets

        dev = particles.device
        n = particles.count
        self.n_streams = int(n_streams)
        self.pair_onsets = wp.zeros(self.n_streams**2, dtype=wp.int32, device=dev)
        self.speed_sum = wp.zeros(n, dtype=wp.float64, device=dev)
        self.substep = wp.zeros(1, dtype=wp.int32, device=dev)
        self.event_count = wp.zeros(1, dtype=wp.int32, device=dev)
        self.struct = ContactOnsets()
        s = self.struct
        s.counting = 1
        s.stream, s.particle_id, s.n_streams = particles.stream, particles.particle_id, self.n_streams
        s.pair_onsets, s.speed_sum, s.substep, s.event_count = (self.pair_onsets, self.speed_sum, self.substep,
                                                                self.event_count)
        self._allocate_events(int(event_capacity))

    def _allocate_events(self, capacity: int) -> None:
        import warp as wp

        dev = self.pair_onsets.device
        size = max(capacity, 1)
        s = self.struct
        s.event_capacity = capacity
        s.event_a = wp.zeros(size, dtype=wp.int32, device=dev)
        s.event_b = wp.zeros(size, dtype=wp.int32, device=dev)
        s.event_speed = wp.zeros(size, dtype=wp.float32, device=dev)
        s.event_substep = wp.zeros(size, dtype=wp.int32, device=dev)
        s.event_pair = wp.zeros(size, dtype=wp.int32, device=dev)

    @property
    def event_capacity(self) -> int:
        return int(self.struct.event_capacity)

    def grow_events(self, needed: int) -> None:
        """Make room for ``needed`` events (clears the list: call between counting periods)."""
        if needed > self.event_capacity:
            self._allocate_events(max(needed, 2 * self.event_capacity))

    def reset(self) -> None:
        """Zero every counter and the event list."""
        for a in (self.pair_onsets, self.speed_sum, self.substep, self.event_count):
            a.zero_()

    def advance_substep(self) -> None:
        """Next sub-step index for the event list (launched only when events are recorded)."""
        if self.event_capacity > 0:
            from kernels.contacts import launch_advance_substep

            launch_advance_substep(self.substep)

    def matrix(self) -> np.ndarray:
        """(S, S) onsets per stream pair (upper triangle, a <= b)."""
        return self.pair_onsets.numpy().reshape(self.n_streams, self.n_streams).astype(np.int64)

    def totals(self) -> dict:
        """``collisions`` (onsets), ``collisions_<a>_<b>`` per stream pair a <= b, ``impact_speed_sum`` (m/s,
        float64 sum over the onsets; divide by ``collisions`` for the mean)."""
        from hel_warp.collisions.pairs import pair_counts

        m = self.matrix()
        return {"collisions": int(m.sum()), **pair_counts("collisions", m),
                "impact_speed_sum": float(self.speed_sum.numpy().sum(dtype=np.float64))}

    @property
    def offered_events(self) -> int:
        """Onsets offered to the event list since the last reset (stored or not)."""
        return int(self.event_count.numpy()[0])

    def events(self) -> dict:
        """The recorded onsets as host arrays sorted by (substep, particle_a, particle_b): ``particle_a`` <
        ``particle_b`` (particle ids), ``speed`` (impact speed, m/s), ``substep`` (index of the sub-step of the
        onset, from 1 at the first sub-step after the last reset), ``stream_a`` <= ``stream_b`` (the pair's
        stream tags, clamped to [0, n_streams)), ``truncated`` (bool: the list was full)."""
        offered = self.offered_events
        k = min(offered, self.event_capacity)
        s = self.struct
        a, b = s.event_a.numpy()[:k], s.event_b.numpy()[:k]
        speed, sub = s.event_speed.numpy()[:k], s.event_substep.numpy()[:k]
        pair = s.event_pair.numpy()[:k]
        order = np.lexsort((speed, b, a, sub))
        return {"particle_a": a[order], "particle_b": b[order], "speed": speed[order], "substep": sub[order],
                "stream_a": pair[order] // self.n_streams, "stream_b": pair[order] % self.n_streams,
                "truncated": offered > k}


def damping_for(restitution: float) -> float:
    """Dimensionless Hertz dashpot c(e) that returns restitution e with the force clipped at zero."""
    from hel_warp.collisions.contact_law import damping_coefficient

    return float(damping_coefficient(restitution))


def contact_params(material: Material, other: Material | None, *, tangential_damping: float = 0.0):
    """``kernels.hertz.ContactParams`` of a material pair (Johnson 1985 §4.2, Mindlin 1949):
    ``1/E* = (1-nu1^2)/E1 + (1-nu2^2)/E2``, ``1/G* = 2(2-nu1)(1+nu1)/E1 + 2(2-nu2)(1+nu2)/E2``.
    ``other = None`` is a rigid wall (its terms vanish) with the first material's e, mu and mu_r;
    otherwise e, mu, mu_r are those of ``other`` (the wall's, for a wall material). R*, m* are set per contact.
    """
    from kernels.hertz import MODEL_HERTZ, ContactParams

    def compliance(m: Material) -> tuple[float, float]:
        nu, E = m.poisson_ratio, m.youngs_modulus
        return (1.0 - nu**2) / E, 2.0 * (2.0 - nu) * (1.0 + nu) / E

    inv_e, inv_g = compliance(material)
    if other is not None:
        inv_e2, inv_g2 = compliance(other)
        inv_e, inv_g = inv_e + inv_e2, inv_g + inv_g2
    props = material if other is None else other
    p = ContactParams()
    p.model = MODEL_HERTZ
    p.youngs_eff = 1.0 / inv_e
    p.shear_eff = 1.0 / inv_g
    p.normal_damping = damping_for(props.restitution)
    p.friction = props.friction
    p.tangential_damping = tangential_damping
    p.rolling_friction = props.rolling_friction
    return p


class DEMSolver:
    """N-body DEM: fixed :class:`DEMConfig`, changing :class:`Particles` (updated in place)."""

    def __init__(self, config: DEMConfig, particles: Particles):
        import warp as wp

        self.config = config
        self.particles = particles
        self.device = particles.device
        n = particles.count
        radius = particles.radius.numpy()
        self.r_min = float(radius.min())
        self.r_max = float(radius.max())
        x = particles.x.numpy()
        lo, hi = np.asarray(config.box_lo), np.asarray(config.box_hi)
        slack = 1e-6 * float(np.max(np.abs(np.concatenate([lo, hi]))))  # float32 round-off of the positions
        outside = np.flatnonzero(np.any((x - radius[:, None] < lo - slack) | (x + radius[:, None] > hi + slack),
                                        axis=1))
        if outside.size:
            raise ConfigError(f"particle {outside[0]} at {x[outside[0]].tolist()} is not fully inside the box "
                              f"{config.box_lo}..{config.box_hi}; {outside.size} affected — move them or enlarge the box")

        material = config.material
        stable = material.time_step(self.r_min, max_speed=config.max_speed).chosen
        if config.dt is None:
            self.dt = stable
        else:
            material.check_time_step(config.dt, self.r_min, max_speed=config.max_speed)
            self.dt = float(config.dt)
        self.skin = float(config.skin) if config.skin is not None else 0.3 * self.r_max
        self.cell_size = 2.0 * self.r_max + self.skin
        self.gravity = wp.vec3(*config.gravity)

        # contact constants (E*, G* of the material pair; R*, m* are set per contact in the kernels)
        self.params = contact_params(material, material, tangential_damping=config.tangential_damping)
        self.wall_params = contact_params(material, config.wall_material, tangential_damping=config.tangential_damping)

        # plane walls of the box, inward normals
        points, normals = [], []
        for name in config.walls:
            axis = "xyz".index(name[0])
            normal = np.zeros(3)
            normal[axis] = 1.0 if name[1] == "-" else -1.0
            points.append(lo if name[1] == "-" else hi)
            normals.append(normal)
        n_walls = max(1, len(points))
        self.wall_point = wp.array(np.asarray(points, np.float32).reshape(-1, 3), dtype=wp.vec3, device=self.device)
        self.wall_normal = wp.array(np.asarray(normals, np.float32).reshape(-1, 3), dtype=wp.vec3, device=self.device)
        from kernels.walls import make_sdf_wall_kernel

        self.sdf_kernels = [make_sdf_wall_kernel(f) for f in config.sdf_walls]

        # state beyond the particles
        cap = config.contact_capacity
        self.contacts = ContactList.empty(n, cap, self.device)
        self._old_contacts = ContactList.empty(n, cap, self.device)
        self.wall_shear = wp.zeros((n, n_walls), dtype=wp.vec3, device=self.device)
        self.sdf_shear = [wp.zeros(n, dtype=wp.vec3, device=self.device) for _ in self.sdf_kernels]
        self.force = wp.zeros(n, dtype=wp.vec3, device=self.device)
        self.torque = wp.zeros(n, dtype=wp.vec3, device=self.device)
        self.x_at_build = wp.zeros(n, dtype=wp.vec3, device=self.device)
        # kernel views (the arrays are only ever updated in place, so the views stay valid)
        from kernels.integrate import sphere_arrays

        self.spheres = sphere_arrays(particles)
        self.rows = self.contacts.rows()
        self.old_rows = self._old_contacts.rows()
        self.rebuild_flag = wp.ones(1, dtype=wp.int32, device=self.device)
        self.overflow = wp.zeros(1, dtype=wp.int32, device=self.device)
        self.rebuild_count = wp.zeros(1, dtype=wp.int32, device=self.device)
        self.onsets = OnsetCounter(particles, config.n_streams, config.onset_events)
        from kernels.contacts import open_space
        from kernels.dem_step import plane_walls

        self.box = open_space()  # built once: a struct per launch costs ~30 us of host time
        on_cuda = wp.get_device(self.device).is_cuda
        if config.half_list and on_cuda:
            raise ConfigError("half_list needs a device that runs threads in order (the CPU); use None on CUDA")
        self.half_list = (not on_cuda) if config.half_list is None else bool(config.half_list)
        self.plane_walls = plane_walls(self.wall_point, self.wall_normal, len(config.walls), self.wall_params,
                                       self.wall_shear, wp.zeros(n, dtype=wp.int32, device=self.device))
        dims = np.clip(np.ceil((hi - lo) / self.cell_size).astype(int), 1, 256)
        self.grid = wp.HashGrid(int(dims[0]), int(dims[1]), int(dims[2]), device=self.device)
        self.grid.reserve(n)
        self.time = 0.0
        self.steps_done = 0
        self._host_rebuilds = 0
        self._sort_scratch = None
        self._graph = None
        is_cuda = wp.get_device(self.device).is_cuda
        # CUDA graphs with a conditional node (capture_if) need CUDA >= 12.4 and a driver for it; else eager steps
        graph_device = (is_cuda and wp.is_conditional_graph_supported()) or (not is_cuda and config.capture_on_cpu)
        if config.capture_on_cpu and tuple(int(v) for v in wp.__version__.split(".")[:2]) < (1, 19):
            raise ConfigError(f"capture_on_cpu needs Warp >= 1.19 (CPU graph capture); this is {wp.__version__}")
        self.sort_every = config.sort_every if config.sort_every is not None else (0 if graph_device else 10)
        self._use_graph = bool(graph_device and config.cuda_graph_steps > 0 and self.sort_every == 0)

        self._rebuild()
        self.onsets.struct.counting = 0  # contacts present at the start are not onsets
        self._compute_forces()
        self.onsets.struct.counting = 1
        self.check_overflow()

    # ------------------------------------------------------------------ the step
    def step(self) -> None:
        """Advance one time step dt (particles updated in place)."""
        self._advance()
        self.steps_done += 1
        self.time += self.dt

    def simulate(self, n_steps: int) -> None:
        """Advance ``n_steps`` steps without host synchronisation, then check the contact list.

        On CUDA (``cuda_graph_steps > 0``) the steps replay a captured graph whose rebuild branch is a
        conditional node; the remainder runs eagerly. The captured body is ``_advance``, the eager step itself;
        ``capture_on_cpu`` takes this branch on the CPU too (its test), so only the graph backend differs there.
        """
        import warp as wp

        full, rest = (divmod(n_steps, self.config.cuda_graph_steps) if self._use_graph else (0, n_steps))
        replayed = 0
        try:
            if full and self._graph is None:
                with wp.ScopedCapture(device=self.device) as capture:
                    for _ in range(self.config.cuda_graph_steps):
                        self._advance()
                self._graph = capture.graph
            for _ in range(full):
                wp.capture_launch(self._graph)
                replayed += 1
        except RuntimeError as exc:
            # a graph the driver will not instantiate (first seen on an H200 with Warp 1.19: "Graph creation error:
            # invalid argument" for the rebuild's conditional body) has run no step: those steps go eagerly, and so
            # does the rest of the run
            if replayed or not wp.get_device(self.device).is_cuda:
                raise
            print(f"hel-warp: warning: DEM: the CUDA graph of {self.config.cuda_graph_steps} steps could not be "
                  f"created ({str(exc).splitlines()[0][:120]}); the steps launch eagerly", file=sys.stderr)
            self._use_graph, self._graph = False, None
            rest += full * self.config.cuda_graph_steps
        if self.half_list and not self.sdf_kernels and rest > 1:
            self._simulate_fused(rest)
        else:
            for _ in range(rest):
                self._advance()
        self.steps_done += n_steps
        self.time += n_steps * self.dt
        self.check_overflow()

    def _advance(self) -> None:
        import warp as wp

        from kernels.contacts import launch_flag_rebuild
        from kernels.integrate import launch_kick, launch_kick_drift

        self.onsets.advance_substep()
        if self.half_list:  # two passes (kernels/dem_step.py; simulate fuses them further, _simulate_fused);
            # the kick is fused unless SDF walls add forces
            from kernels.dem_step import launch_kick_drift_flag

            launch_kick_drift_flag(self.spheres, self.force, self.torque, self.gravity, self.dt, self.x_at_build,
                                   0.5 * self.skin, self.rebuild_flag)
            wp.capture_if(self.rebuild_flag, on_true=self._rebuild)
            self._compute_forces(kick=not self.sdf_kernels)
            if self.sdf_kernels:
                launch_kick(self.spheres, self.force, self.torque, self.gravity, self.dt)
            return
        launch_kick_drift(self.spheres, self.force, self.torque, self.gravity, self.dt)
        launch_flag_rebuild(self.spheres, self.x_at_build, 0.5 * self.skin, self.rebuild_flag)
        if wp.get_device(self.device).is_capturing:
            # Under graph capture the hash grid is built every step, outside the conditional body: the H200's driver
            # refused to instantiate a graph whose capture_if body holds wp.HashGrid.build, and accepted it built
            # plainly (scripts/probe_dem_graph.py). Between list builds the grid is not read, and at one it is
            # the grid of these positions either way, so the steps are the eager steps' bits.
            self.grid.build(self.particles.x, self.cell_size)
            wp.capture_if(self.rebuild_flag, on_true=self._rebuild_lists)
        else:
            wp.capture_if(self.rebuild_flag, on_true=self._rebuild)
        self._compute_forces()
        launch_kick(self.spheres, self.force, self.torque, self.gravity, self.dt)

    def _simulate_fused(self, n_steps: int) -> None:
        """``n_steps`` steps of the half list in n + 1 launches (``kernels/dem_step.py``): the first pass, then
        per step the list check and one pass whose tail is the next step's first pass; the last step ends
        without it. The same operations in the same order as ``_advance``, so the same bits. The launches
        are recorded once (``record_cmd``: packing a launch's arguments costs ~0.3 ms of host time), valid
        for this call, in which no array of the solver is reallocated."""
        import warp as wp

        from kernels.dem_step import launch_forces_kick, launch_kick_drift_flag

        half_skin = 0.5 * self.skin
        first = launch_kick_drift_flag(self.spheres, self.force, self.torque, self.gravity, self.dt, self.x_at_build,
                                       half_skin, self.rebuild_flag, record=True)
        passes = [launch_forces_kick(self.spheres, self.rows, self.params, self.box, self.plane_walls, self.gravity,
                                     self.dt, self.onsets.struct, self.force, self.torque, kick=True,
                                     x_at_build=self.x_at_build, half_skin=half_skin, rebuild_flag=self.rebuild_flag,
                                     drift=drift, record=True) for drift in (True, False)]
        first.launch()
        for k in range(n_steps):
            self.onsets.advance_substep()
            wp.capture_if(self.rebuild_flag, on_true=self._rebuild)
            passes[0 if k < n_steps - 1 else 1].launch()

    def _compute_forces(self, kick: bool = False) -> None:
        """Forces and torques at the current positions; ``kick`` (half list only): the second half kick too.
        The half list accumulates: ``kick_drift_flag`` zeroes the arrays, the first evaluation starts at zero."""
        from kernels.contacts import launch_contact_forces
        from kernels.walls import launch_plane_wall_forces, launch_sdf_wall_forces

        if self.half_list:
            from kernels.dem_step import launch_forces_kick

            launch_forces_kick(self.spheres, self.rows, self.params, self.box, self.plane_walls, self.gravity,
                               self.dt, self.onsets.struct, self.force, self.torque, kick=kick,
                               x_at_build=self.x_at_build, half_skin=0.5 * self.skin, rebuild_flag=self.rebuild_flag)
        else:
            launch_contact_forces(self.spheres, self.rows, self.params, self.dt, self.force, self.torque,
                                  box=self.box, onsets=self.onsets.struct)
        if self.config.walls and not self.half_list:
            launch_plane_wall_forces(self.spheres, self.wall_point, self.wall_normal, self.wall_params, self.dt,
                                     self.wall_shear, self.force, self.torque)
        for kernel, shear in zip(self.sdf_kernels, self.sdf_shear):
            launch_sdf_wall_forces(kernel, self.spheres, self.wall_params, self.dt, self.config.sdf_gradient_step,
                                   shear, self.force, self.torque)

    def _rebuild(self, grid_built: bool = False) -> None:
        """Hash grid + contact list (shear carried by partner id); optional spatial sort first. ``grid_built``: the
        grid is already that of the current positions (``_advance`` under graph capture)."""
        from kernels import contacts as kc
        from kernels.contacts import launch_build_contact_list

        if not grid_built:
            self.grid.build(self.particles.x, self.cell_size)
        kc.launch_count_rebuild(self.rebuild_count)
        self._host_rebuilds += 1  # only for the sort decision (eager launches)
        every = self.sort_every
        if every and self._host_rebuilds % every == 1 % every:
            self._spatial_sort()
            self.grid.build(self.particles.x, self.cell_size)
        else:
            self._old_contacts.copy_from(self.contacts)
        launch_build_contact_list(self.grid, self.spheres, self.r_max, self.skin, self.old_rows, self.rows,
                                  self.x_at_build, self.overflow, box=self.box, half=self.half_list,
                                  packed=self.half_list)
        if self.half_list and self.config.walls:
            from kernels.dem_step import launch_mark_near_walls

            launch_mark_near_walls(self.spheres, self.plane_walls, self.skin)
        self.rebuild_flag.zero_()

    def _rebuild_lists(self) -> None:
        """:meth:`_rebuild` after the grid was built (the conditional body under graph capture)."""
        self._rebuild(grid_built=True)

    def _spatial_sort(self) -> None:
        """Reorder every per-particle array by hash-grid cell; contact rows go to ``_old_contacts``."""
        import warp as wp

        from kernels import contacts as kc

        n = self.particles.count
        if self._sort_scratch is None:
            self._sort_scratch = {
                "new_to_old": wp.zeros(n, dtype=wp.int32, device=self.device),
                "old_to_new": wp.zeros(n, dtype=wp.int32, device=self.device),
                "vec3": wp.zeros(n, dtype=wp.vec3, device=self.device),
                "float": wp.zeros(n, dtype=wp.float32, device=self.device),
                "int": wp.zeros(n, dtype=wp.int32, device=self.device),
                "wall": wp.zeros_like(self.wall_shear),
            }
        s = self._sort_scratch
        wp.launch(kc.sorted_order, dim=n, inputs=[self.grid.id], outputs=[s["new_to_old"], s["old_to_new"]],
                  device=self.device)
        p = self.particles
        for arr in (p.x, p.v, p.omega, self.force, self.torque, *self.sdf_shear):
            kc.launch_gather(arr, s["new_to_old"], s["vec3"])
            wp.copy(arr, s["vec3"])
        for arr in (p.radius, p.density, p.weight):
            kc.launch_gather(arr, s["new_to_old"], s["float"])
            wp.copy(arr, s["float"])
        for arr in (p.stream, p.alive, p.particle_id):
            kc.launch_gather(arr, s["new_to_old"], s["int"])
            wp.copy(arr, s["int"])
        wp.launch(kc.gather_rows_vec3, dim=n, inputs=[self.wall_shear, s["new_to_old"], s["wall"]], device=self.device)
        wp.copy(self.wall_shear, s["wall"])
        kc.launch_gather_contact_rows(self.rows, s["new_to_old"], s["old_to_new"], self.old_rows)

    # ------------------------------------------------------------------ checks and read-back
    @property
    def rebuilds(self) -> int:
        """Neighbour-list builds so far, including the initial one (device counter; a host sync)."""
        return int(self.rebuild_count.numpy()[0])

    def check_overflow(self) -> None:
        """Raise ContactOverflowError if any contact row overflowed since the start (host sync)."""
        need = int(self.overflow.numpy()[0])
        if need > 0:
            raise ContactOverflowError(
                f"contact list overflow: a particle had {need} neighbours within r_i + r_j + skin but the "
                f"capacity is {self.config.contact_capacity}; set contact_capacity >= {need} "
                f"(or reduce the skin {self.skin:.3e} m)")

    def onset_counts(self) -> dict:
        """Contact onsets since construction or :meth:`reset_onsets` (host sync): ``collisions``,
        ``collisions_<a>_<b>`` per stream pair a <= b, ``impact_speed_sum`` (m/s)."""
        return self.onsets.totals()

    def onset_events(self) -> dict:
        """The onsets since the last reset, one entry each (``OnsetCounter.events``; ``substep`` counts steps
        from the reset). Needs ``DEMConfig.onset_events > 0``."""
        if self.onsets.event_capacity == 0:
            raise ConfigError("onset events are not recorded: set DEMConfig(onset_events=...) to the list size")
        return self.onsets.events()

    def reset_onsets(self) -> None:
        """Zero the onset counters and the event list (the contacts' touching flags are kept)."""
        self.onsets.reset()

    def touching_pairs(self, *, as_numpy: bool = True):
        """Compact list of touching pairs (i < j, overlap > 0) in the current device order.

        Returns host arrays ``(pair_i, pair_j)``, or with ``as_numpy=False`` the device arrays
        ``(pair_i, pair_j, pair_count)`` for collision-rate kernels (``pair_count`` a 1-element
        array; the arrays hold ``max(count, 1)`` entries). Reads one total back to size the arrays.
        """
        import warp as wp

        from kernels import contacts as kc

        n = self.particles.count
        counts = wp.zeros(n, dtype=wp.int32, device=self.device)
        wp.launch(kc.count_touching_pairs, dim=n, device=self.device,
                  inputs=[self.particles.x, self.particles.radius, self.rows], outputs=[counts])
        offsets = wp.zeros(n, dtype=wp.int32, device=self.device)
        wp.utils.array_scan(counts, offsets, inclusive=False)
        total = int(counts.numpy().sum())
        pair_i = wp.zeros(max(total, 1), dtype=wp.int32, device=self.device)
        pair_j = wp.zeros(max(total, 1), dtype=wp.int32, device=self.device)
        wp.launch(kc.fill_touching_pairs, dim=n, device=self.device,
                  inputs=[self.particles.x, self.particles.radius, self.rows, offsets], outputs=[pair_i, pair_j])
        if not as_numpy:
            return pair_i, pair_j, wp.array([total], dtype=wp.int32, device=self.device)
        return pair_i.numpy()[:total], pair_j.numpy()[:total]

    def resolved_config(self) -> dict:
        """The configuration with every default resolved (for run attrs)."""
        return {**self.config.as_dict(), "dt": self.dt, "skin": self.skin, "sort_every": self.sort_every, "cell_size": self.cell_size,
                "particles": self.particles.count, "r_min": self.r_min, "r_max": self.r_max,
                "normal_damping": self.params.normal_damping, "wall_normal_damping": self.wall_params.normal_damping}


def run_with_output(solver: DEMSolver, *, end_time: float, writer=None, snapshots: int = 10,
                    progress: bool = True, extra_arrays=None) -> int:
    """Advance ``solver`` to ``end_time`` (s), writing ``snapshots`` evenly spaced snapshots (plus t=0).

    Between outputs the solver runs :meth:`DEMSolver.simulate` chunks (no host syncs); the tqdm bar
    advances per chunk. ``extra_arrays(solver) -> dict`` adds named arrays to every snapshot.
    Returns the number of steps taken.
    """
    from tqdm import tqdm

    require_positive("end time", end_time, "s")
    n_steps = max(1, int(math.ceil(end_time / solver.dt - 1e-9)))
    snapshots = max(1, int(snapshots))
    # split into output intervals and, inside one, progress chunks of at most ~1 % of the run
    marks = sorted(set(int(round(k * n_steps / snapshots)) for k in range(1, snapshots + 1)))
    chunk = max(1, n_steps // 100)

    def output():
        if writer is None:
            return
        data = solver.particles.to_numpy()
        arrays = {name: data[name] for name in ("x", "v", "omega", "radius", "density", "stream", "alive",
                                                  "particle_id")}
        if extra_arrays is not None:
            arrays.update(extra_arrays(solver))
        writer.write_snapshot(arrays, time=solver.time, step=solver.steps_done)

    output()
    done = 0
    with tqdm(total=n_steps, unit="step", disable=not progress, mininterval=0.5) as bar:
        for mark in marks:
            while done < mark:
                k = min(chunk, mark - done)
                solver.simulate(k)
                done += k
                bar.update(k)
            output()
    return n_steps

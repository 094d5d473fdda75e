"""HEL parcels on the host side: a fixed-capacity pool of ``Particles``, volume injection, outlet removal.

A parcel stands for ``weight`` identical real particles (the paper's runs use weight 1; its
second HEL configuration uses 8). Parcels may come to overlap in flight (MP-PIC), but an injection
never creates an overlap (see below).

The pool is a ``hel_warp.parcels.particles.Particles`` of fixed capacity; unused slots have
``alive = 0``. Injected parcels fill slots ``[used, used + n)`` in order and removed parcels
are not reused, so the parcel index is stable for the whole run (deterministic output). A
run that injects more than the capacity stops with a ConfigError that names the capacity.

Volume injection (paper section 8): parcels at random positions in a box, all with one velocity
``speed * direction``, diameters from a normal distribution truncated at mean +- 3 sigma (and at
10 % of the mean), either a given number of parcels or as many as carry a given mass.

Positions never overlap (paper sec. 4.1: overlapped starts are resolved explosively by a DEM, the
"100 m/s" artefact). The box is cut into a lattice of ``floor(L / s)`` cells per axis with
``s = d_max (1 + PLACEMENT_CLEARANCE)`` (``d_max`` the largest diameter of the release); each parcel
takes a distinct cell, drawn in random order with the release's seed, at a jittered point that stays
``s / 2`` from the cell faces, so any two parcels of one release are at least ``s >= r_i + r_j`` apart.
``ParcelPool.inject`` also rejects a site within ``(r_i + r_j)(1 + PLACEMENT_CLEARANCE)`` of a live parcel
already in the pool (``kernels/injection.py`` ``flag_blocked_sites``) and moves that parcel to the next
cell of the random order. A release that does not fit (too few free cells) is refused with a
ConfigError naming the fix (a longer injection window or a larger box); nothing is carried over.
Same seed and same pool state give the same positions (a restarted run injects bit-identically).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hel_warp.errors import ConfigError, require_finite, require_positive
from hel_warp.parcels.particles import Particles

PLACEMENT_CLEARANCE = 1e-3
"""Relative gap kept between injected parcels and their neighbours: absorbs the float32 rounding of positions."""


@dataclass(frozen=True, kw_only=True)
class VolumeInjection:
    """Parcels released once into a box (SI units). Exactly one of ``count`` and ``mass`` is given."""

    box_lo: tuple[float, float, float]
    """Lower corner of the injection box, m."""
    box_hi: tuple[float, float, float]
    """Upper corner of the injection box, m."""
    diameter_mean: float
    """Mean particle diameter, m."""
    diameter_std: float = 0.0
    """Standard deviation of the (normal) diameter distribution, m; 0 = monodisperse."""
    density: float = 1000.0
    """Particle material density, kg/m^3."""
    count: int | None = None
    """Number of parcels to inject."""
    mass: float | None = None
    """Total mass of real particles to inject, kg (parcels are added until it is reached)."""
    speed: float = 0.0
    """Initial speed of every parcel, m/s."""
    direction: tuple[float, float, float] = (1.0, 0.0, 0.0)
    """Direction of the initial velocity (normalised here)."""
    weight: float = 1.0
    """Real particles per parcel."""
    stream: int = 0
    """Integer tag of the stream (colour in outputs)."""
    seed: int = 0
    """Seed of the random positions and diameters."""

    def __post_init__(self):
        lo = np.asarray(self.box_lo, dtype=np.float64)
        hi = np.asarray(self.box_hi, dtype=np.float64)
        if lo.shape != (3,) or hi.shape != (3,):
            raise ConfigError("box_lo and box_hi must each hold three coordinates (m)")
        require_finite("box_lo", lo)
        require_finite("box_hi", hi)
        if not np.all(hi > lo):
            raise ConfigError(f"injection box_hi {hi.tolist()} must exceed box_lo {lo.tolist()} on every axis")
        require_positive("diameter_mean", self.diameter_mean, "m")
        require_finite("diameter_std", self.diameter_std)
        if self.diameter_std < 0:
            raise ConfigError(f"diameter_std must be >= 0 (got {self.diameter_std} m)")
        require_positive("density", self.density, "kg/m^3")
        require_positive("weight", self.weight)
        require_finite("speed", self.speed)
        if self.speed < 0:
            raise ConfigError(f"speed must be >= 0 (got {self.speed} m/s); reverse the direction instead")
        d = np.asarray(self.direction, dtype=np.float64)
        require_finite("direction", d)
        if d.shape != (3,) or not np.linalg.norm(d) > 0:
            raise ConfigError(f"direction must be a non-zero 3-vector (got {self.direction!r})")
        if (self.count is None) == (self.mass is None):
            raise ConfigError("give exactly one of count (parcels) and mass (kg) for a volume injection")
        if self.count is not None and (int(self.count) != self.count or self.count < 1):
            raise ConfigError(f"count must be a positive integer (got {self.count!r})")
        if self.mass is not None:
            require_positive("mass", self.mass, "kg")

    def sample(self, blocked=None) -> dict[str, np.ndarray]:
        """Host arrays ``x`` (n,3), ``v`` (n,3), ``radius`` (n,) of the parcels to inject.

        Parcels of the release never overlap each other. ``blocked`` (optional): a function
        ``(x (m,3) float32, radius (m,) float32) -> bool (m,)`` that flags candidates overlapping a parcel
        already present; flagged parcels move to other lattice cells. The diameters do not depend on it.
        """
        rng = np.random.default_rng(self.seed)
        lo, hi = np.asarray(self.box_lo, float), np.asarray(self.box_hi, float)

        def diameters(n):
            if self.diameter_std == 0.0:
                return np.full(n, self.diameter_mean)
            d = rng.normal(self.diameter_mean, self.diameter_std, size=n)
            low = max(self.diameter_mean - 3.0 * self.diameter_std, 0.1 * self.diameter_mean)
            return np.clip(d, low, self.diameter_mean + 3.0 * self.diameter_std)

        if self.count is not None:
            d = diameters(int(self.count))
        else:
            mean_mass = self.weight * self.density * math.pi / 6.0 * (self.diameter_mean**3
                                                                      + 3.0 * self.diameter_mean * self.diameter_std**2)
            guess = int(math.ceil(1.2 * self.mass / mean_mass)) + 16
            d = diameters(guess)
            cum = np.cumsum(self.weight * self.density * math.pi / 6.0 * d**3)
            while cum[-1] < self.mass:  # rare: the sample came out light; extend it
                d = np.concatenate([d, diameters(guess)])
                cum = np.cumsum(self.weight * self.density * math.pi / 6.0 * d**3)
            n = int(np.searchsorted(cum, self.mass * (1.0 - 1e-12))) + 1
            d = d[:n]
        x = self._place(rng, lo, hi, 0.5 * d, blocked)
        n = d.size
        direction = np.asarray(self.direction, float) / np.linalg.norm(self.direction)
        v = np.tile(self.speed * direction, (n, 1))
        return {"x": x, "v": v, "radius": 0.5 * d}

    def _place(self, rng, lo, hi, radius, blocked) -> np.ndarray:
        """Non-overlapping centres (n,3) in the box for parcels of ``radius`` (module docstring)."""
        n = radius.size
        spacing = 2.0 * float(radius.max()) * (1.0 + PLACEMENT_CLEARANCE)
        # one layer along an axis thinner than the spacing (e.g. a point or sheet box): sites then
        # differ along another axis, whose cells are at least one spacing wide, so they cannot overlap
        cells = np.maximum(np.floor((hi - lo) / spacing), 1).astype(np.int64)
        n_sites = int(np.prod([int(c) for c in cells]))

        def refuse(places: str):
            raise ConfigError(
                f"injection box {list(self.box_lo)}..{list(self.box_hi)} has {places} for non-overlapping parcels "
                f"of diameter {spacing:.4g} m, but the release has {n} parcels; spread the release over a longer "
                "injection window (ScheduledInjection t_end) or enlarge the box")

        if n_sites < n:
            refuse(f"{n_sites} places")
        cell = (hi - lo) / cells
        queue = np.empty(0, np.int64)
        queue_x = np.empty((0, 3))

        def extend(size):
            nonlocal queue, queue_x
            more = rng.choice(n_sites, size=min(n_sites, size), replace=False).astype(np.int64)
            more = more[~np.isin(more, queue)]
            ijk = np.stack(np.unravel_index(more, tuple(int(c) for c in cells)), axis=1)
            jitter = rng.uniform(-0.5, 0.5, size=(more.size, 3)) * np.maximum(cell - spacing, 0.0)
            queue = np.concatenate([queue, more])
            queue_x = np.concatenate([queue_x, lo + (ijk + 0.5) * cell + jitter])

        extend(max(2 * n, 64))
        slot = np.arange(n)  # queue entry of each parcel
        next_entry = n
        todo = np.arange(n) if blocked is not None else np.empty(0, np.int64)
        while todo.size:
            flags = np.asarray(blocked(queue_x[slot[todo]].astype(np.float32), radius[todo].astype(np.float32)))
            todo = todo[flags.astype(bool)]
            while queue.size - next_entry < todo.size:
                if queue.size == n_sites:
                    refuse(f"fewer than {n} of its {n_sites} places free of the parcels already there")
                extend(2 * queue.size)
            slot[todo] = np.arange(next_entry, next_entry + todo.size)
            next_entry += todo.size
        return queue_x[slot]


@dataclass
class ParcelPool:
    """Fixed-capacity parcel state. ``particles`` holds ``capacity`` slots; ``used`` of them were filled."""

    particles: Particles
    used: int = 0
    _removed_counter: object = field(default=None, repr=False)
    _grid: object = field(default=None, repr=False)
    """Hash grid of the pool's positions for the injection overlap check (built per release)."""
    weight_placed_since: float = 0.0
    """The largest weight :meth:`place` wrote since its reader last set this to 0 (``HelSolver``'s bound of the
    live weights between two reads of the device)."""
    radius_placed_since: float = 0.0
    """The largest radius :meth:`place` wrote since its reader last set this to 0 (as ``weight_placed_since``)."""
    count_placed_since: int = 0
    """Parcels :meth:`place` wrote since its reader last set this to 0 (``HelSolver``'s bound of the live count)."""

    @classmethod
    def empty(cls, capacity: int, *, device=None) -> "ParcelPool":
        """A pool of ``capacity`` dead slots."""
        import warp as wp

        if int(capacity) != capacity or capacity < 1:
            raise ConfigError(f"parcel capacity must be a positive integer (got {capacity!r})")
        n = int(capacity)
        parts = Particles.from_numpy(np.zeros((n, 3)), 1.0, check_overlap=False, device=device)
        parts.alive.zero_()
        return cls(particles=parts, used=0,
                   _removed_counter=wp.zeros(1, dtype=wp.int32, device=parts.device))

    @property
    def capacity(self) -> int:
        return self.particles.count

    def inject(self, injection: VolumeInjection) -> int:
        """Fill the next free slots with the parcels of ``injection``; returns how many were added."""
        s = injection.sample(blocked=self._blocked_sites())
        return self.place(s["x"], s["radius"], v=s["v"], density=injection.density, weight=injection.weight,
                          stream=injection.stream)

    def place(self, x, radius, *, v=None, omega=None, density=1000.0, weight=1.0, stream=0) -> int:
        """Fill the next free slots with parcels at the given positions (n, 3), radii and velocities (the caller
        answers for overlaps); scalars apply to every parcel. Returns how many were added."""
        import warp as wp

        x = np.asarray(x, np.float64).reshape(-1, 3)
        n = x.shape[0]
        if self.used + n > self.capacity:
            raise ConfigError(f"injecting {n} parcels overflows the pool ({self.used} of {self.capacity} slots "
                              "used); create the ParcelPool with a larger capacity")
        dev = self.particles.device
        p = self.particles

        def put(dest, host, dtype):
            wp.copy(dest, wp.array(host, dtype=dtype, device=dev), dest_offset=self.used, count=n)

        def each(value, dtype):
            return np.broadcast_to(np.asarray(value, dtype), (n,)).copy()

        put(p.x, x.astype(np.float32), wp.vec3)
        put(p.v, (np.zeros((n, 3)) if v is None else np.asarray(v).reshape(n, 3)).astype(np.float32), wp.vec3)
        put(p.omega, (np.zeros((n, 3)) if omega is None else np.asarray(omega).reshape(n, 3)).astype(np.float32),
            wp.vec3)
        put(p.radius, each(radius, np.float32), wp.float32)
        put(p.density, each(density, np.float32), wp.float32)
        put(p.weight, each(weight, np.float32), wp.float32)
        if n:
            self.weight_placed_since = max(self.weight_placed_since, float(np.max(each(weight, np.float32))))
            self.radius_placed_since = max(self.radius_placed_since, float(np.max(each(radius, np.float32))))
            self.count_placed_since += int(n)
        put(p.stream, each(stream, np.int32), wp.int32)
        put(p.alive, np.ones(n, np.int32), wp.int32)
        put(p.particle_id, np.arange(self.used, self.used + n, dtype=np.int32), wp.int32)
        self.used += n
        return n

    def _blocked_sites(self):
        """``blocked`` for :meth:`VolumeInjection.sample`: flags sites a live parcel overlaps (None: pool empty)."""
        import warp as wp

        from kernels.injection import launch_flag_blocked_sites

        p = self.particles
        alive = p.alive.numpy()[:self.used].astype(bool)
        if not alive.any():
            return None
        max_radius = float(p.radius.numpy()[:self.used][alive].max())
        if self._grid is None:
            self._grid = wp.HashGrid(128, 128, 128, device=p.device)
        built = []

        def blocked(site_x, site_radius):
            if not built:  # hashed once per release, on the first call
                self._grid.build(p.x, float(max_radius + site_radius.max()))
                built.append(True)
            flags = wp.zeros(site_x.shape[0], dtype=wp.int32, device=p.device)
            launch_flag_blocked_sites(self._grid, p, max_radius, PLACEMENT_CLEARANCE,
                                      wp.array(site_x, dtype=wp.vec3, device=p.device),
                                      wp.array(site_radius, dtype=wp.float32, device=p.device), flags)
            return flags.numpy() != 0

        return blocked

    def remove_beyond_plane(self, point, normal) -> None:
        """Outlet: parcels past the plane through ``point`` with outward ``normal`` are removed (alive = 0).

        The count accumulates on the device; read it with :meth:`removed_count` (a sync) at output time.
        """
        from kernels.push import remove_beyond_plane

        require_finite("outlet point", np.asarray(point, float))
        nrm = np.asarray(normal, float)
        if nrm.shape != (3,) or not np.linalg.norm(nrm) > 0:
            raise ConfigError(f"outlet normal must be a non-zero 3-vector (got {normal!r})")
        remove_beyond_plane(tuple(point), tuple(nrm / np.linalg.norm(nrm)), self.particles.x,
                            self.particles.alive, self._removed_counter)

    def removed_count(self) -> int:
        """Parcels removed at outlets so far (host read: output intervals only)."""
        return int(self._removed_counter.numpy()[0])

    def alive_count(self) -> int:
        """Live parcels (host read: output intervals only)."""
        return int(self.particles.alive.numpy().sum())

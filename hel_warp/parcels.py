"""HEL parcels on the host side: a fixed-capacity pool of ``Particles``, volume injection, outlet removal.

A parcel stands for ``weight`` identical real particles (the paper's runs use weight 1; its
second HEL configuration uses 8). Parcels may overlap (MP-PIC), so no overlap check is made.

The pool is a ``hel_warp.particles.Particles`` of fixed capacity; unused slots have
``alive = 0``. Injected parcels fill slots ``[used, used + n)`` in order and removed parcels
are not reused, so the parcel index is stable for the whole run (deterministic output). A
run that injects more than the capacity stops with a ConfigError that names the capacity.

Volume injection (paper section 8): parcels at uniformly random positions in a box, all with
one velocity ``speed * direction``, diameters from a normal distribution truncated at
mean +- 3 sigma (and at 10 % of the mean), either a given number of parcels or as many as
carry a given mass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hel_warp.errors import ConfigError, require_finite, require_positive
from hel_warp.particles import Particles


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

    def sample(self) -> dict[str, np.ndarray]:
        """Host arrays ``x`` (n,3), ``v`` (n,3), ``radius`` (n,) of the parcels to inject."""
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
        n = d.size
        x = lo + rng.uniform(size=(n, 3)) * (hi - lo)
        direction = np.asarray(self.direction, float) / np.linalg.norm(self.direction)
        v = np.tile(self.speed * direction, (n, 1))
        return {"x": x, "v": v, "radius": 0.5 * d}


@dataclass
class ParcelPool:
    """Fixed-capacity parcel state. ``particles`` holds ``capacity`` slots; ``used`` of them were filled."""

    particles: Particles
    used: int = 0
    _removed_counter: object = field(default=None, repr=False)

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
        import warp as wp

        s = injection.sample()
        n = s["x"].shape[0]
        if self.used + n > self.capacity:
            raise ConfigError(f"injecting {n} parcels overflows the pool ({self.used} of {self.capacity} slots "
                              "used); create the ParcelPool with a larger capacity")
        dev = self.particles.device
        p = self.particles

        def put(dest, host, dtype):
            wp.copy(dest, wp.array(host, dtype=dtype, device=dev), dest_offset=self.used, count=n)

        put(p.x, s["x"].astype(np.float32), wp.vec3)
        put(p.v, s["v"].astype(np.float32), wp.vec3)
        put(p.omega, np.zeros((n, 3), np.float32), wp.vec3)
        put(p.radius, s["radius"].astype(np.float32), wp.float32)
        put(p.density, np.full(n, injection.density, np.float32), wp.float32)
        put(p.weight, np.full(n, injection.weight, np.float32), wp.float32)
        put(p.stream, np.full(n, injection.stream, np.int32), wp.int32)
        put(p.alive, np.ones(n, np.int32), wp.int32)
        put(p.particle_id, np.arange(self.used, self.used + n, dtype=np.int32), wp.int32)
        self.used += n
        return n

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

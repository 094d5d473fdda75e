"""Particle state: a structure of Warp arrays, one entry per sphere (parcel).

``Particles`` is the changing part of a DEM or HEL run (the *State* of docs/developer/conventions.md rule 3);
the material, walls and solver settings are fixed elsewhere. Every array lives on one Warp
device and stays there between steps; :meth:`Particles.to_numpy` copies a snapshot back
(output intervals only).

The particle order on the device may change (spatial sort by hash-grid cell, see
``kernels/contacts.py``); ``particle_id`` keeps each particle's original index, and
:meth:`Particles.to_numpy` returns arrays in that original order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hel_warp.errors import ConfigError

FIELDS_VEC3 = ("x", "v", "omega")
FIELDS_FLOAT = ("radius", "density", "weight")
FIELDS_INT = ("stream", "alive", "particle_id")


@dataclass
class Particles:
    """Structure of Warp arrays describing N spheres. All SI units.

    Attributes:
        x: centre position, m. ``wp.array(dtype=wp.vec3)``, shape (N,).
        v: centre velocity, m/s. vec3, (N,).
        omega: angular velocity, rad/s. vec3, (N,).
        radius: sphere radius, m. float32, (N,).
        density: material density, kg/m^3. float32, (N,).
        weight: real particles per parcel (1 in DEM), dimensionless. float32, (N,).
        stream: integer tag of the injection stream / species. int32, (N,).
        alive: 1 while the particle takes part in the run, 0 once removed. int32, (N,).
        particle_id: original index of the particle (survives spatial sorting). int32, (N,).
    """

    x: object
    v: object
    omega: object
    radius: object
    density: object
    weight: object
    stream: object
    alive: object
    particle_id: object

    @property
    def count(self) -> int:
        """Number of particles N (alive or not)."""
        return self.x.shape[0]

    @property
    def device(self):
        return self.x.device

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_numpy(cls, x, radius, *, v=None, omega=None, density=1000.0, weight=1.0, stream=0,
                   box_lo=None, box_hi=None, check_overlap: bool = True, overlap_tolerance: float = 1e-6,
                   device=None) -> "Particles":
        """Build particles from host arrays, validated once.

        Args:
            x: (N, 3) centre positions, m.
            radius: (N,) or scalar radius, m (> 0).
            v, omega: (N, 3) velocity (m/s) and angular velocity (rad/s); zero by default.
            density: (N,) or scalar, kg/m^3 (> 0).
            weight: (N,) or scalar parcel weight (> 0); 1 for DEM.
            stream: (N,) or scalar int tag.
            box_lo, box_hi: if given, every sphere must lie fully inside this box (m).
            check_overlap: refuse initial spheres overlapping by more than
                ``overlap_tolerance`` times the smaller radius (an overlapped start explodes).

        Raises:
            ConfigError: naming the offending particle and what to change.
        """
        import warp as wp

        x = np.ascontiguousarray(np.asarray(x, dtype=np.float64))
        if x.ndim != 2 or x.shape[1] != 3:
            raise ConfigError(f"particle positions must have shape (N, 3), got {x.shape}")
        n = x.shape[0]
        if n == 0:
            raise ConfigError("no particles given; pass at least one position")

        def per_particle(name, value, dtype=np.float64):
            arr = np.asarray(value, dtype=dtype)
            if arr.ndim == 0:
                arr = np.full(n, arr, dtype=dtype)
            if arr.shape != (n,):
                raise ConfigError(f"particle {name} must be a scalar or have shape ({n},), got {arr.shape}")
            return arr

        def per_particle_vec(name, value):
            if value is None:
                return np.zeros((n, 3))
            arr = np.asarray(value, dtype=np.float64)
            if arr.shape == (3,):
                arr = np.tile(arr, (n, 1))
            if arr.shape != (n, 3):
                raise ConfigError(f"particle {name} must have shape ({n}, 3), got {arr.shape}")
            return arr

        radius = per_particle("radius", radius)
        density = per_particle("density", density)
        weight = per_particle("weight", weight)
        stream = per_particle("stream", stream, np.int32)
        v = per_particle_vec("velocity", v)
        omega = per_particle_vec("angular velocity", omega)

        for name, arr in (("position", x), ("velocity", v), ("angular velocity", omega), ("radius", radius),
                          ("density", density), ("weight", weight)):
            bad = np.flatnonzero(~np.all(np.isfinite(arr.reshape(n, -1)), axis=1))
            if bad.size:
                raise ConfigError(f"particle {bad[0]} has a non-finite {name} ({arr[bad[0]]!r}); "
                                  f"{bad.size} particle(s) affected — fix the initial {name}s")
        for name, arr, unit in (("radius", radius, "m"), ("density", density, "kg/m^3"), ("weight", weight, "")):
            bad = np.flatnonzero(arr <= 0.0)
            if bad.size:
                raise ConfigError(f"particle {bad[0]} has {name} {arr[bad[0]]!r} {unit}; every {name} must be > 0")

        if box_lo is not None or box_hi is not None:
            lo = np.asarray(box_lo if box_lo is not None else [-np.inf] * 3, dtype=np.float64)
            hi = np.asarray(box_hi if box_hi is not None else [np.inf] * 3, dtype=np.float64)
            outside = np.flatnonzero(np.any((x - radius[:, None] < lo) | (x + radius[:, None] > hi), axis=1))
            if outside.size:
                k = outside[0]
                raise ConfigError(f"particle {k} at {x[k].tolist()} (radius {radius[k]:.3e} m) is not fully inside "
                                  f"the box {lo.tolist()}..{hi.tolist()}; {outside.size} particle(s) affected — "
                                  "move them inside or enlarge the box")

        if check_overlap and n > 1:
            pair = first_overlap(x, radius, overlap_tolerance)
            if pair is not None:
                i, j, depth = pair
                raise ConfigError(f"initial spheres {i} and {j} overlap by {depth:.3e} m "
                                  f"(radii {radius[i]:.3e}, {radius[j]:.3e} m); space the initial positions "
                                  "at least r_i + r_j apart (e.g. a lattice spacing >= the largest diameter)")

        def vec(a):
            return wp.array(a.astype(np.float32), dtype=wp.vec3, device=device)

        def f32(a):
            return wp.array(a.astype(np.float32), dtype=wp.float32, device=device)

        def i32(a):
            return wp.array(a.astype(np.int32), dtype=wp.int32, device=device)

        return cls(x=vec(x), v=vec(v), omega=vec(omega), radius=f32(radius), density=f32(density),
                   weight=f32(weight), stream=i32(stream), alive=i32(np.ones(n, np.int32)),
                   particle_id=i32(np.arange(n, dtype=np.int32)))

    # ------------------------------------------------------------------ read back
    def to_numpy(self, *, original_order: bool = True) -> dict[str, np.ndarray]:
        """Copy every array to the host (a sync point: call at output intervals only).

        With ``original_order`` the rows are sorted back by ``particle_id``.
        """
        out = {name: getattr(self, name).numpy().copy() for name in FIELDS_VEC3 + FIELDS_FLOAT + FIELDS_INT}
        if original_order:
            order = np.argsort(out["particle_id"], kind="stable")
            out = {k: a[order] for k, a in out.items()}
        return out

    def mass_numpy(self) -> np.ndarray:
        """Particle masses m = rho 4/3 pi r^3 (kg), host copy, in device order."""
        r = self.radius.numpy().astype(np.float64)
        return self.density.numpy().astype(np.float64) * 4.0 / 3.0 * math.pi * r**3

    def live_extremes(self) -> tuple[float, float, float, int, int]:
        """(max |v| m/s, max weight, max radius m, live count, live parcels with a non-finite |v|, weight or radius),
        reduced on the device (``kernels/interp.py`` ``live_extremes``): one launch and one 40-byte read-back (a
        sync on CUDA) instead of reading the arrays back. With no live parcel: (0, 0, 0, 0, 0). A NaN is counted in
        the last entry, not in the maxima (an atomic maximum passes it over): callers that need finite values check
        it."""
        v_max, w_max, r_max, count, bad = (float(x) for x in self.launch_live_extremes().numpy())
        return v_max, w_max, r_max, int(count), int(bad)

    def launch_live_extremes(self):
        """:meth:`live_extremes` left on the device: the (5,) float64 array (same order) it reduced into, no read
        (kernels that plan from it: ``kernels/cell_collide.py`` ``substep_plan``)."""
        import warp as wp

        from kernels.interp import launch_live_extremes

        store = getattr(self, "_extremes_store", None)
        if store is None or str(store.device) != str(self.v.device):
            store = self._extremes_store = wp.zeros(5, dtype=wp.float64, device=self.v.device)
        launch_live_extremes(self.v, self.weight, self.radius, self.alive, store)
        return store

    def clone(self) -> "Particles":
        import warp as wp

        return Particles(**{name: wp.clone(getattr(self, name)) for name in FIELDS_VEC3 + FIELDS_FLOAT + FIELDS_INT})


def first_overlap(x: np.ndarray, radius: np.ndarray, tolerance: float = 1e-6):
    """First pair (i, j, depth) of spheres overlapping by more than ``tolerance * min(r_i, r_j)``, else None."""
    from scipy.spatial import cKDTree

    tree = cKDTree(x)
    pairs = tree.query_pairs(r=2.0 * float(radius.max()), output_type="ndarray")
    if pairs.size == 0:
        return None
    i, j = pairs[:, 0], pairs[:, 1]
    dist = np.linalg.norm(x[i] - x[j], axis=1)
    depth = radius[i] + radius[j] - dist
    bad = np.flatnonzero(depth > tolerance * np.minimum(radius[i], radius[j]))
    if bad.size == 0:
        return None
    k = bad[np.lexsort((j[bad], i[bad]))[0]]
    return int(i[k]), int(j[k]), float(depth[k])


def lattice_positions(count: int, spacing: float, lo, hi, *, jitter: float = 0.0, seed: int = 0) -> np.ndarray:
    """``count`` points on a cubic lattice of ``spacing`` (m) filling the box lo..hi from the bottom (z) up.

    Points sit ``spacing/2`` inside the box; ``jitter`` (m) displaces each coordinate uniformly by at most
    ``jitter/2``, so spheres of diameter d never overlap while ``jitter <= spacing - d``.
    Raises ConfigError when the box is too small.
    """
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    n_xy = np.floor((hi[:2] - lo[:2]) / spacing).astype(int)
    n_z = np.floor((hi[2] - lo[2]) / spacing).astype(int)
    if n_xy.min() < 1 or n_xy[0] * n_xy[1] * n_z < count:
        raise ConfigError(f"{count} particles at spacing {spacing:.3e} m do not fit into the box {lo.tolist()}.."
                          f"{hi.tolist()} (room for {max(0, n_xy[0] * n_xy[1] * n_z)}); enlarge the box or "
                          "reduce the particle count")
    k = np.arange(count)
    ix = k % n_xy[0]
    iy = (k // n_xy[0]) % n_xy[1]
    iz = k // (n_xy[0] * n_xy[1])
    pts = lo + spacing * (np.stack([ix, iy, iz], axis=1) + 0.5)
    if jitter > 0.0:
        rng = np.random.default_rng(seed)
        pts = pts + rng.uniform(-0.5, 0.5, size=pts.shape) * jitter
    return pts

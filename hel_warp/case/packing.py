"""Initial fills: parcels placed at random without overlaps, or a settled bed poured by a short DEM.

Settled bed of real spheres (weight 1): the spheres start on a jittered lattice filling the region's cross-section
from its floor up, fall under gravity inside the region's walls and come to rest (``hel_warp.collisions.dem``; Hertz-Mindlin
with the species' material, its stiffness capped at ``POUR_MODULUS`` and its restitution at ``POUR_RESTITUTION``
so that the pour settles in ~1e4 steps; a packing's solids fraction depends on friction, hardly on stiffness).
The pour stops when the fastest sphere is slower than ``POUR_REST_SPEED`` or at ``POUR_MAX_TIME``.
Frictional spheres poured this way come to rest in a loose random packing (solids fraction ~0.58-0.60 in bulk,
Onoda & Liniger 1990); ``dense=True`` pours them without friction, which packs them towards random close packing
(~0.64 in bulk, Scott & Kilgour 1969), as a bed tapped or vibrated after filling: the packing of the beds from which
the minimum fluidization correlations were drawn (voidage ~0.38-0.41 for spheres, Wen & Yu 1966). The packing is
then dilated about the floor by the largest overlap left, which opens the contacts stacked along the vertical (the
bed is ~0.5 % taller than poured); contacts across the width and depth keep the soft pour's deformation under the
bed's weight (up to ~1.5 % of a diameter in a 30-layer bed, the Hertz deflection at ``POUR_MODULUS``), which spheres
of the material's own stiffness spring apart from in their first steps: a CFD-DEM bed of 9,240 spheres is back at
rest (median speed 0.3 mm/s) 0.3 s later, 0.3 % taller. Then the bed is cached: the same species, region, count,
gravity and seed load it from the cache.

Settled bed of weighted parcels: their real particles fill the region's cross-section from the floor up to the
height that holds them at ``Fill.settled_fraction``; the parcels are placed at random, without overlaps between
their own spheres, over that height (MP-PIC parcels of a dense bed are sparse clouds: their spheres fill 1 / W of
the bed).

Random fill: the parcels spread over the whole region without overlaps (``hel_warp.parcels.pool.VolumeInjection``'s
lattice placement, at most ~0.5 of the region's volume in parcel spheres).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path

import numpy as np

from hel_warp.errors import ConfigError

POUR_MODULUS = 1.0e6
"""Largest Young's modulus of the pour, Pa: the DEM step grows as E^-1/2 and the packing barely changes."""
POUR_RESTITUTION = 0.3
"""Largest restitution of the pour: a dissipative pour comes to rest sooner."""
POUR_REST_SPEED = 2.0e-3
"""The pour has settled when no sphere moves faster than this, m/s."""
POUR_MAX_TIME = 1.5
"""Longest pour, s of simulated time."""
LATTICE_PITCH = 1.05
"""Spacing of the pour's start lattice, in diameters."""


def cache_dir() -> Path:
    """Where settled packings and automatically trained models are kept: ``$HEL_WARP_CACHE`` or
    ``~/.cache/hel_warp``."""
    root = os.environ.get("HEL_WARP_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "hel_warp"


def gravity_axis(gravity) -> tuple[int, float]:
    """(axis, sign) of "up": the axis gravity points along, and +1 when up is its positive direction."""
    g = np.asarray(gravity, float)
    if not np.any(g != 0.0):
        raise ConfigError("a settled fill needs gravity (the bed settles against it); give the flow a gravity")
    axis = int(np.argmax(np.abs(g)))
    if np.count_nonzero(g) > 1:
        raise ConfigError(f"a settled fill needs gravity along one axis (got {tuple(g)})")
    return axis, -float(np.sign(g[axis]))


def random_injection(species, region, count: int, seed: int, velocity=(0.0, 0.0, 0.0)):
    """A ``VolumeInjection`` of ``count`` parcels at random in ``region`` (a Box) without overlaps (at
    ``velocity``); its ``sample()`` refuses with a ConfigError when they do not fit."""
    from hel_warp.parcels.pool import VolumeInjection

    margin = 0.5 * species.diameter * (1.0 + 1e-3) + 3.0 * species.diameter_std
    lo = np.asarray(region.lo) + margin
    hi = np.asarray(region.hi) - margin
    if np.any(hi <= lo):
        raise ConfigError(f"fill region {list(region.lo)}..{list(region.hi)} is narrower than one particle of "
                          f"{species.name!r}; enlarge it")
    speed = float(np.linalg.norm(velocity))
    direction = tuple(np.asarray(velocity, float) / speed) if speed > 0 else (1.0, 0.0, 0.0)
    return VolumeInjection(box_lo=tuple(lo), box_hi=tuple(hi), diameter_mean=species.diameter,
                           diameter_std=species.diameter_std, density=species.density, count=int(count),
                           weight=species.weight, seed=int(seed), speed=speed, direction=direction)


def settled_height(species, region, real: int, fraction: float, up: int) -> float:
    """Height of a bed of ``real`` particles packed at ``fraction`` over the region's cross-section, m."""
    extent = np.subtract(region.hi, region.lo)
    area = float(np.prod([extent[a] for a in range(3) if a != up]))
    return real * species.particle_volume / (fraction * area)


def weighted_bed(species, region, parcels: int, real: int, fraction: float, gravity, seed: int):
    """The injection that places ``parcels`` weighted parcels at random over a settled bed's height."""
    from hel_warp.gas.grid import Box

    up, sign = gravity_axis(gravity)
    height = settled_height(species, region, real, fraction, up)
    extent = region.hi[up] - region.lo[up]
    if height > extent * (1.0 + 1e-9):
        raise ConfigError(f"the settled bed of {real} particles of {species.name!r} is {height * 1e3:.1f} mm high at "
                          f"solids fraction {fraction:g}, more than its region's {extent * 1e3:.1f} mm; enlarge the "
                          "region or fill fewer particles")
    lo, hi = list(region.lo), list(region.hi)
    if sign > 0:
        hi[up] = lo[up] + height
    else:
        lo[up] = hi[up] - height
    return random_injection(species, Box(lo=tuple(lo), hi=tuple(hi)), parcels, seed)


def _pour_key(species, region, real: int, gravity, seed: int, friction: float) -> str:
    material = species.material
    payload = {"d": species.diameter, "sd": species.diameter_std, "rho": material.density,
               "E": min(material.youngs_modulus, POUR_MODULUS), "nu": material.poisson_ratio,
               "e": min(material.restitution, POUR_RESTITUTION), "mu": friction, "lo": list(region.lo),
               "hi": list(region.hi), "n": int(real), "g": list(map(float, gravity)), "seed": int(seed),
               "pitch": LATTICE_PITCH, "rest": POUR_REST_SPEED, "version": 1}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:20]


def poured_bed(species, region, real: int, gravity, seed: int, *, dense: bool = False, device="cpu",
               progress=None) -> dict:
    """A settled bed of ``real`` spheres of ``species`` poured into ``region`` (module docstring; ``dense``: poured
    without friction): dict with ``x`` (n, 3), ``radius`` (n,), ``solids_fraction`` and ``height`` of the bed,
    ``pour_time`` s. Cached."""
    from dataclasses import replace

    up, sign = gravity_axis(gravity)
    friction = 0.0 if dense else float(species.material.friction)
    key = _pour_key(species, region, real, gravity, seed, friction)
    path = cache_dir() / "packings" / f"{key}.npz"
    if path.exists():
        with np.load(path, allow_pickle=False) as data:
            return {k: (data[k] if data[k].ndim else float(data[k])) for k in data.files}
    rng = np.random.default_rng(seed)
    d, sd = species.diameter, species.diameter_std
    low = max(d - 3.0 * sd, 0.1 * d)
    diameters = np.clip(rng.normal(d, sd, real), low, d + 3.0 * sd) if sd > 0 else np.full(real, d)
    radius = 0.5 * diameters
    pitch = LATTICE_PITCH * float(diameters.max())
    lo, hi = np.asarray(region.lo, float), np.asarray(region.hi, float)
    across = [a for a in range(3) if a != up]
    per_axis = [int(math.floor((hi[a] - lo[a]) / pitch)) for a in across]
    if min(per_axis) < 1:
        raise ConfigError(f"the fill region is narrower than one sphere of {species.name!r} across; enlarge it")
    layers = int(math.ceil(real / (per_axis[0] * per_axis[1])))
    height = layers * pitch
    if height > 3.0 * (hi[up] - lo[up]):
        raise ConfigError(f"{real} spheres of {species.name!r} need a start column {height * 1e3:.0f} mm high to pour "
                          f"into a region {(hi[up] - lo[up]) * 1e3:.0f} mm high; enlarge the region or fill fewer")
    # the start lattice: layers from the floor up, each cell jittered within its clearance
    sites = np.arange(per_axis[0] * per_axis[1] * layers)[:real]
    i = sites % per_axis[0]
    j = (sites // per_axis[0]) % per_axis[1]
    k = sites // (per_axis[0] * per_axis[1])
    x = np.zeros((real, 3))
    gap = [(hi[a] - lo[a] - n * pitch) / n for a, n in zip(across, per_axis)]
    x[:, across[0]] = lo[across[0]] + (i + 0.5) * (pitch + gap[0])
    x[:, across[1]] = lo[across[1]] + (j + 0.5) * (pitch + gap[1])
    floor = lo[up] if sign > 0 else hi[up]
    x[:, up] = floor + sign * (k + 0.5) * pitch
    jitter = 0.5 * (pitch - diameters.max())
    x += rng.uniform(-1.0, 1.0, size=x.shape) * 0.9 * jitter
    box_lo, box_hi = lo.copy(), hi.copy()
    if sign > 0:
        box_hi[up] = max(hi[up], floor + height + pitch)
    else:
        box_lo[up] = min(lo[up], floor - height - pitch)
    from hel_warp.collisions.dem import DEMConfig, DEMSolver
    from hel_warp.parcels.particles import Particles

    material = replace(species.material, youngs_modulus=min(species.material.youngs_modulus, POUR_MODULUS),
                       restitution=min(species.material.restitution, POUR_RESTITUTION), friction=friction)
    particles = Particles.from_numpy(x, radius, density=material.density, box_lo=tuple(box_lo),
                                     box_hi=tuple(box_hi), device=device)
    solver = DEMSolver(DEMConfig(material=material, box_lo=tuple(box_lo), box_hi=tuple(box_hi),
                                 gravity=tuple(float(g) for g in gravity)), particles)
    chunk = max(1, int(round(0.01 / solver.dt)))
    while solver.time < POUR_MAX_TIME:
        solver.simulate(chunk)
        v = solver.particles.v.numpy()
        if progress is not None:
            progress(solver.time)
        if solver.time > 0.05 and float(np.sqrt((v.astype(np.float64) ** 2).sum(axis=1)).max()) < POUR_REST_SPEED:
            break
    data = solver.particles.to_numpy()
    x, radius = data["x"].astype(np.float64), data["radius"].astype(np.float64)
    # dilate about the floor by the deepest overlap, so that no two spheres overlap along the vertical (contacts
    # across the width and depth keep the soft pour's deformation under the weight; module docstring)
    from scipy.spatial import cKDTree

    pairs = cKDTree(x).query_pairs(r=2.0 * float(radius.max()), output_type="ndarray")
    worst = 0.0
    if pairs.size:
        dist = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1)
        worst = float(np.max((radius[pairs[:, 0]] + radius[pairs[:, 1]]) / np.maximum(dist, 1e-30)))
    scale = max(worst, 1.0) * (1.0 + 1e-4)
    x[:, up] = floor + (x[:, up] - floor) * scale
    top = float(np.max(sign * (x[:, up] - floor) + radius))
    extent = np.subtract(region.hi, region.lo)
    area = float(np.prod([extent[a] for a in across]))
    fraction = float(np.sum(4.0 / 3.0 * math.pi * radius**3) / (area * top))
    if top > (hi[up] - lo[up]) * (1.0 + 1e-9):
        raise ConfigError(f"the poured bed of {real} spheres of {species.name!r} is {top * 1e3:.1f} mm high, more "
                          f"than its region's {(hi[up] - lo[up]) * 1e3:.1f} mm; enlarge the region or fill fewer")
    # every sphere inside the region's side walls (the pour's walls are the region's)
    result = {"x": x, "radius": radius, "solids_fraction": fraction, "height": top, "pour_time": float(solver.time)}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **{k: np.asarray(v) for k, v in result.items()})
    os.replace(tmp, path)
    return result

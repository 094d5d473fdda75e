"""Homogeneous cooling of a granular gas (Haff 1983) in a periodic box: each collision model against kinetic theory.

N equal spheres (diameter D, ``Material`` density) fill a cubic, triply periodic box at solids fraction
EPS: no gas, no gravity, no walls. They start at random, non-overlapping positions (a jittered lattice above
a parcel solids fraction of 0.1; never overlapping, also across the periodic faces) with Maxwellian
velocities at Theta0 and zero total momentum, rescaled so that the initial granular temperature is exactly
Theta0. Then, per step of dt, the collision model acts and the
parcels fly on straight lines:

- ``none``: ballistic (Theta stays Theta0, no collision);
- ``ktgf``: the engine's KTGF term (``hel_warp.hel.KtgfCollision``, ``kernels/ktgf.py``) as the HEL step
  applies it, on a periodic grid of the rig's cell size (1 mm, rounded to fit the box): the parcels are
  deposited with the engine's cloud-in-cell coupling (``hel_warp.coupling.deposit_parcels``), the cells get
  g0, the algebraic Theta and p_s, and each parcel the acceleration a = -grad(p_s) / (eps_s rho_p)
  (limited to h / dt^2), then ``v += a dt``. Its collision count is 0 by construction (no binary
  collisions); in a homogeneous gas the only gradients are those of the parcels' sampling noise;
- ``surrogate`` (HELSCM ``pairwise``, contact-form ``--model``; ``--detection swept|overlap|cell``, ``cell`` the
  default with ``--particles-per-parcel`` > 1: collision cells tiling the box, ``hel_warp/cell_collisions.py``) and
  ``surrogate-paper`` (paper-form ``--model``): ``strategy.collide(particles, dt)``, the ballistic move
  ``x += v dt``, ``strategy.correct_positions(particles)`` (the swept in-step corrections), the wrap
  into [0, L);
- ``dem``: Hertz-Mindlin sub-steps at the DEM step across dt (``DemCollision.advance_free``: contacts
  only, periodic, positions wrapped); its ``collisions`` are contact onsets.

Box: the side L = (N pi D^3 / (6 EPS))^(1/3) holds N real particles; with ``--particles-per-parcel W``
they are N / W parcels of weight W (each a sphere of diameter D standing for W particles). Material: the
data set's (restitution, friction) when the model's metadata records it, else ``Material(friction=0)``
(Haff's law and the Enskog frequency are for smooth spheres).

References (``../shared/PHYSICS-NOTES.md``, "Collisions in a granular gas"):

- Enskog collision frequency per particle: omega = 24 eps g0 sqrt(Theta) / (sqrt(pi) D), Carnahan-Starling
  g0 = (1 - eps/2) / (1 - eps)^3; the reference count is N/2 times omega integrated over the measured
  Theta(t) (trapezoidal, every step), so the ratio is meaningful while the gas cools;
- Haff's law: Theta^(-1/2) grows linearly in t with slope 4 (1 - e^2) g0 eps / (D sqrt(pi)); the measured
  slope is the least-squares line through Theta^(-1/2)(t) of every step.

A binary mixture (``--diameter2 D2 --number-fraction2 F``; ``--particles`` counts both species, round(F N) of
D2): the box holds both species' volume at EPS, the start is random and non-overlapping (sum of radii) with the
species at equipartition (m_1 Theta_1 = m_2 Theta_2, T_i = m_i Theta_i) and the mass-weighted mixture Theta
exactly Theta0, each species' mean velocity removed. A parcel's ``stream`` tag is its species, so the strategies'
per-stream-pair counts are the collisions per pair type. The JSON adds ``granular_temperature_1`` / ``_2``
(Theta_i = <|c_i|^2>/3 of each species, about its own mean), their start and end values, ``temperature_ratio``
T_2/T_1 (1 = equipartition), ``collision_pair_types`` (small-small, small-large, large-large against kinetic
theory) and ``kinetic_theory`` (``hel_warp/mixture.py``: the Maxwellian rate equations of a smooth inelastic binary
mixture integrated from the measured start, with BMCSL g0_ij, and the homogeneous-cooling-state ratio T_2/T_1 of
Garzo & Dufty 1999, which differs from 1: non-equipartition). ``granular_temperature`` is then the mixture's
mass-weighted Theta, and the ``enskog_*`` / ``haff_slope`` / ``cooling_rate_ratio`` keys refer to that mixture
theory (``haff_slope``: the slope of its Theta^-1/2(t)). ``ktgf`` gets one diameter, the mixture's Sauter mean
(the mixture KTGF closures are out of scope). A surrogate model must hold both sizes and their ratios in its
training domain (``hel-warp dataset --diameters D1,D2``). ``--particles-per-parcel W1,W2`` gives each species its
own weight (W_k divides N_k; one value: both): N_k / W_k parcels of weight W_k, the same real particles, box and
references; the ``cell`` detection (the default once a weight exceeds 1) puts back the energy the heavier parcel's
partial impulse loses (``kernels/cell_collide.py``)::

    python cases/homogeneous_cooling.py --collisions surrogate --model MIXTURE_MODEL --dt 1e-3 \\
        --solids-fraction 0.01 --particles 8000 --diameter 315e-6 --diameter2 475e-6 --number-fraction2 0.3 \\
        --granular-temperature 1 --end-time 0.04 --out runs/hc_mix_1e-3 --json

Statistical size of the check: with C real collisions over the run the collision count has a relative
standard error of about 1/sqrt(C) (Poisson), and the energy lost (hence the fitted slope) about
sqrt(2/C): the loss per collision is (1 - e^2) m g_n^2 / 4 and, for collisions of a Maxwellian gas
(weighted by |g|, impact parameter uniform in b^2), E[g_n^4] / E[g_n^2]^2 = 2. Both are in the output
(``*_stderr``). Keep the run short enough that the gas stays homogeneous (a few to ~20 collisions per
particle at e = 0.9).

    python cases/homogeneous_cooling.py --collisions surrogate --model MODEL_DIR --detection swept \\
        --dt 1e-3 --solids-fraction 0.01 --particles 8000 --diameter 315e-6 --granular-temperature 1 \\
        --end-time 0.04 --out runs/hc_swept_1e-3 --json
    hel-warp run cases/homogeneous_cooling.py --collisions none --dt 1e-4 --solids-fraction 0.01 \\
        --particles 1000 --diameter 315e-6 --granular-temperature 1 --end-time 0.005 --out runs/hc_none

Writes ``OUT/summary.json`` (the object ``--json`` prints) and ``OUT/cooling.png`` (Theta(t) with Haff's
curve, and Theta^(-1/2)(t) with the fitted and Haff's lines). Bad input: one line
``homogeneous_cooling: error: ...`` and exit code 2; a failed ``check()`` (non-finite state, a parcel
outside the box, momentum not conserved by a conserving model): exit code 1.
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import os
import shutil
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

if str(Path(__file__).resolve().parents[1]) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

COLLISIONS = ("none", "ktgf", "surrogate", "surrogate-paper", "dem")
DETECTIONS = ("swept", "overlap", "cell")
KTGF_CELL = 1.0e-3
"""Target cell size of the KTGF grid, m (the colliding-streams rig's; rounded so that whole cells fill L)."""
MAX_JSON_POINTS = 2000
"""At most this many (time, Theta) points in the JSON / summary (every k-th step; the fit uses every step)."""
LATTICE_GAP = 1.0e-3
"""Smallest gap between lattice neighbours, in diameters (the jitter keeps every pair this far apart)."""
SUMMARY = "summary.json"
PICTURE = "cooling.png"
COUNT_FLAGS = ("guard", "clamp", "causal", "corrected", "overflow", "outside")
"""Substrings of the strategy's count names gathered under ``strategy_flags`` (guard corrections, domain clamps,
causality counters)."""


# ------------------------------------------------------------------------------------ kinetic-theory references
def carnahan_starling_g0(eps: float) -> float:
    """Radial distribution at contact, Carnahan & Starling (1969): g0 = (1 - eps/2) / (1 - eps)^3."""
    return (1.0 - 0.5 * eps) / (1.0 - eps) ** 3


def enskog_frequency(eps: float, diameter: float, theta):
    """Collisions per particle per second, omega = 24 eps g0 sqrt(Theta) / (sqrt(pi) d) (Chapman & Cowling)."""
    return 24.0 * eps * carnahan_starling_g0(eps) * np.sqrt(np.maximum(theta, 0.0)) / (math.sqrt(math.pi) * diameter)


def haff_slope(restitution: float, eps: float, diameter: float) -> float:
    """d(Theta^-1/2)/dt of Haff's law (1983): 4 (1 - e^2) g0 eps / (d sqrt(pi)), (m/s)^-1 s^-1."""
    return 4.0 * (1.0 - restitution**2) * carnahan_starling_g0(eps) * eps / (diameter * math.sqrt(math.pi))


def haff_theta(theta0: float, slope: float, t):
    """Theta(t) = Theta0 / (1 + slope sqrt(Theta0) t)^2 (Haff's law, the slope of Theta^-1/2)."""
    return theta0 / (1.0 + slope * math.sqrt(theta0) * np.asarray(t)) ** 2


def box_length(particles: int, diameter: float, eps: float) -> float:
    """Side of the cube holding ``particles`` real spheres of ``diameter`` at solids fraction ``eps``, m."""
    return (particles * math.pi * diameter**3 / (6.0 * eps)) ** (1.0 / 3.0)


def granular_temperature(v: np.ndarray, weight: np.ndarray) -> float:
    """Theta = <|v - <v>|^2> / 3 over real particles (weights = particles per parcel), m^2/s^2."""
    w = np.asarray(weight, np.float64)
    v = np.asarray(v, np.float64)
    mean = (w[:, None] * v).sum(axis=0) / w.sum()
    return float((w * ((v - mean) ** 2).sum(axis=1)).sum() / (3.0 * w.sum()))


def theta_from_moments(moments: np.ndarray) -> np.ndarray:
    """Theta per row of (S0, S1x, S1y, S1z, S2) (``kernels/free_flight.py``): (S2 - |S1|^2 / S0) / (3 S0)."""
    s0 = moments[:, 0]
    s1 = moments[:, 1:4]
    return (moments[:, 4] - (s1**2).sum(axis=1) / s0) / (3.0 * s0)


# ------------------------------------------------------------------------------------------------ configuration
def add_arguments(parser: argparse.ArgumentParser) -> None:
    from hel_warp.errors import finite_float

    parser.add_argument("--collisions", choices=COLLISIONS, required=True, help="collision model")
    parser.add_argument("--model", default=None,
                        help="model directory (hel-warp train --out); needed by surrogate (contact form) and "
                             "surrogate-paper (paper form); with the others it only supplies the material")
    parser.add_argument("--cell-approaching", action=argparse.BooleanOptionalAction, default=None,
                        help="cell detection: collisions go to parcel pairs whose centres approach, a receding "
                             "accepted pair handing its collision to an approaching one of its cell "
                             "(CellConfig.approaching; default: on when a parcel weighs more than 1)")
    parser.add_argument("--cell-transfer", action=argparse.BooleanOptionalAction, default=None,
                        help="cell detection: the collisional transfer, the two parcels of each collision moved "
                             "apart by their share of the contact distance (CellConfig.collisional_transfer; "
                             "default: CellConfig's)")
    parser.add_argument("--detection", choices=DETECTIONS, default=None,
                        help="surrogate only: swept (continuous), overlap (the paper's end-of-step test) or cell "
                             "(stochastic per collision cell, for parcels of many particles); default: swept, cell "
                             "when --particles-per-parcel > 1")
    parser.add_argument("--dt", type=finite_float, required=True, help="time step, s")
    parser.add_argument("--solids-fraction", type=finite_float, required=True, help="solids volume fraction eps_s")
    parser.add_argument("--particles", type=int, required=True, help="real particles N")
    parser.add_argument("--diameter", type=finite_float, required=True, help="particle diameter, m")
    parser.add_argument("--diameter2", type=finite_float, default=None,
                        help="a binary mixture: diameter of the second species, m (with --number-fraction2; "
                             "--particles counts both species)")
    parser.add_argument("--number-fraction2", type=finite_float, default=None,
                        help="number fraction of the --diameter2 species, in (0, 1)")
    parser.add_argument("--granular-temperature", type=finite_float, required=True,
                        help="initial granular temperature Theta0, m^2/s^2")
    parser.add_argument("--end-time", type=finite_float, required=True, help="simulated time, s")
    parser.add_argument("--particles-per-parcel", default="1",
                        help="real particles per parcel: W for every species (divides N; default 1), or W1,W2 "
                             "per species of a mixture (W_k divides species k's particles)")
    parser.add_argument("--particle-spin", action="store_true",
                        help="surrogate (pairwise) only: collisions at the contact point, the spins turned "
                             "(SurrogateCollision.particle_spin); with a frictional model the gas then heats up in "
                             "rotation as the dem's does (rotational_temperature in the JSON)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the start (lattice jitter, velocities)")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output directory")
    parser.add_argument("--json", action="store_true", help="print the summary as one JSON object (no progress bar)")
    parser.add_argument("--device", default="cpu", help="Warp device: cpu or cuda (default cpu)")


class CoolingConfig(SimpleNamespace):
    """The validated settings (see :func:`make_config`): collisions, model, detection, dt, eps, particles (real,
    every species), parcels, weights (real particles per parcel of each species: (W,) for one size, (W1, W2) for a
    mixture), parcel_eps (the parcels' own solids fraction, sum of parcels x one particle's volume / L^3),
    diameter, theta0, end_time, steps, seed, out, overwrite, device, box_length, material, material_source,
    model_meta, species (None, or the binary mixture of :func:`mixture_species`)."""


def _read_model_meta(model_dir: str) -> dict:
    from hel_warp.errors import ConfigError

    path = os.path.join(model_dir, "metadata.json")
    if not os.path.isdir(model_dir):
        raise ConfigError(f"--model {model_dir}: no such directory; give a directory written by `hel-warp train`")
    try:
        with open(path) as fh:
            meta = json.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"--model {model_dir}: {path} not found; give a directory written by `hel-warp train`") \
            from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"--model {model_dir}: {path} is not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise ConfigError(f"--model {model_dir}: {path} does not hold a JSON object")
    return meta


def _model_material(meta: dict | None):
    """(Material, source): the model's data-set material when its metadata records one, else friction 0."""
    from hel_warp.material import Material

    if meta:
        for where in (meta.get("material"), (meta.get("dataset") or {}).get("material"),
                      (meta.get("defaults") or {}).get("material")):
            if isinstance(where, dict):
                fields = {k: float(where[k]) for k in ("density", "youngs_modulus", "poisson_ratio", "restitution",
                                                       "friction", "rolling_friction") if k in where}
                return Material(**fields), "model metadata"
    return Material(friction=0.0), "Material(friction=0) (the model metadata records no material)" if meta else \
        "Material(friction=0)"


def make_config(args) -> CoolingConfig:
    """Validate the options once (ConfigError with what to change) and derive the box, steps and material."""
    from hel_warp.errors import ConfigError

    name = args.collisions
    if name not in COLLISIONS:
        raise ConfigError(f"--collisions must be one of {', '.join(COLLISIONS)} (got {name!r})")
    if args.detection is not None and name != "surrogate":
        raise ConfigError(f"--detection applies to --collisions surrogate only (got --collisions {name}); drop it")
    if name in ("surrogate", "surrogate-paper") and not args.model:
        raise ConfigError(f"--collisions {name} needs --model MODEL_DIR (a "
                          f"{'contact' if name == 'surrogate' else 'paper'}-form model written by hel-warp train)")
    if not args.dt > 0.0:
        raise ConfigError(f"--dt must be > 0 s (got {args.dt:g})")
    if not 0.0 < args.solids_fraction < 1.0:
        raise ConfigError(f"--solids-fraction must lie in (0, 1) (got {args.solids_fraction:g})")
    if not args.diameter > 0.0:
        raise ConfigError(f"--diameter must be > 0 m (got {args.diameter:g})")
    if not args.granular_temperature > 0.0:
        raise ConfigError(f"--granular-temperature must be > 0 m^2/s^2 (got {args.granular_temperature:g})")
    if not args.end_time > 0.0:
        raise ConfigError(f"--end-time must be > 0 s (got {args.end_time:g})")
    if args.end_time < args.dt * (1.0 - 1e-9):
        raise ConfigError(f"--end-time {args.end_time:g} s is shorter than one step (--dt {args.dt:g} s); give an "
                          "end time of at least one step")
    if args.particles < 2:
        raise ConfigError(f"--particles must be >= 2 (got {args.particles})")
    from hel_warp.mixture import species_weights

    two_sizes = getattr(args, "diameter2", None) is not None or getattr(args, "number_fraction2", None) is not None
    weights = species_weights(args.particles_per_parcel, 2 if two_sizes else 1)
    if args.seed < 0:
        raise ConfigError(f"--seed must be >= 0 (got {args.seed})")
    eps, d = float(args.solids_fraction), float(args.diameter)
    species = mixture_species(args, weights)  # None: one size
    if species is None:
        w = weights[0]
        if args.particles % w:
            raise ConfigError(f"--particles-per-parcel {w} does not divide --particles {args.particles}; choose N a "
                              "multiple of W")
        parcels = args.particles // w
        L = box_length(args.particles, d, eps)
        parcel_eps = eps / w
    else:
        parcels = sum(species.parcels)
        L = mixture_box_length(species, eps)
        parcel_eps = sum(p * math.pi * dk**3 / 6.0 for p, dk in zip(species.parcels, species.diameters)) / L**3
    if parcels < 2:
        raise ConfigError(f"--particles / --particles-per-parcel = {parcels} parcel; need at least 2")
    if max(weights) > 1 and name == "dem":
        raise ConfigError("--collisions dem resolves real spheres: use --particles-per-parcel 1")
    d_big = d if species is None else max(species.diameters)
    side = math.ceil(parcels ** (1.0 / 3.0) - 1e-9)
    if L / side < d_big * (1.0 + 2.0 * LATTICE_GAP):
        raise ConfigError(f"{parcels} parcels of {d_big:g} m do not fit on a non-overlapping lattice in the box of "
                          f"side {L:.4g} m (eps_s {eps:g} with W = {','.join(map(str, weights))}: lattice spacing "
                          f"{L / side / d_big:.3f} d < 1); lower --solids-fraction or raise --particles-per-parcel")
    meta = _read_model_meta(args.model) if args.model else None
    if meta is not None:
        defaults = meta.get("defaults") or {}
        if species is not None:
            check_model_covers(args.model, meta, species.diameters)
        elif "d1" in defaults and abs(float(defaults["d1"]) - d) > 0.10 * d:
            raise ConfigError(f"--model {args.model} was trained for d = {float(defaults['d1']) * 1e6:.0f} um, the "
                              f"run has {d * 1e6:.0f} um; train a model for this size (hel-warp dataset --diameter)")
    material, source = _model_material(meta)
    if meta is not None:
        defaults = meta.get("defaults") or {}
        if "rho1" in defaults and abs(float(defaults["rho1"]) - material.density) > 0.01 * material.density:
            raise ConfigError(f"--model {args.model} was trained for density {float(defaults['rho1']):g} kg/m^3, "
                              f"the material has {material.density:g} kg/m^3")
    steps = max(1, int(round(args.end_time / args.dt)))
    out = Path(args.out)
    if out.exists() and not args.overwrite:
        raise ConfigError(f"output directory {args.out} exists; pass --overwrite to replace it")
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / SUMMARY).exists())):
        raise ConfigError(f"{args.out} is not an output directory of this case (no {SUMMARY}); --overwrite only "
                          "replaces those")
    detection = args.detection
    particle_spin = bool(getattr(args, "particle_spin", False))
    if particle_spin and name != "surrogate":
        raise ConfigError(f"--particle-spin turns the surrogate's collisions at the contact point; --collisions {name} "
                          "does not use it (the dem's spheres spin on their own)")
    if name == "surrogate" and detection is None and max(weights) > 1:
        detection = "cell"  # the strategy's own default for parcels heavier than one particle
    cell_approaching = getattr(args, "cell_approaching", None)
    if cell_approaching is not None and not (name == "surrogate" and detection == "cell"):
        raise ConfigError("--[no-]cell-approaching is an option of the surrogate's cell detection (give --detection "
                          "cell or --particles-per-parcel > 1)")
    cell_transfer = getattr(args, "cell_transfer", None)
    if cell_transfer is not None and not (name == "surrogate" and detection == "cell"):
        raise ConfigError("--[no-]cell-transfer is an option of the surrogate's cell detection (give --detection cell "
                          "or --particles-per-parcel > 1)")
    config = CoolingConfig(collisions=name, model=args.model, detection=detection, dt=float(args.dt), eps=eps,
                           particles=int(args.particles), parcels=parcels, weights=weights, parcel_eps=parcel_eps,
                           diameter=d,
                           theta0=float(args.granular_temperature), end_time=float(args.end_time), steps=steps,
                           seed=int(args.seed), out=str(args.out), overwrite=bool(args.overwrite), device=args.device,
                           box_length=L, material=material, material_source=source, model_meta=meta, species=species,
                           particle_spin=particle_spin, cell_approaching=cell_approaching,
                           cell_transfer=cell_transfer)
    check_search(config)
    return config


def search_cell(config: CoolingConfig, speed_max: float) -> float:
    """Hash-grid cell of the model's pair search, m: 2 (r + v_max dt) for the swept surrogate (a pair within reach
    over the step), 2 r for the end-of-step overlap tests, 2 r + 0.3 r (the contact-list skin) for dem; 0 for the
    models without a pair search."""
    r = 0.5 * (config.diameter if config.species is None else max(config.species.diameters))
    if config.collisions == "surrogate" and config.detection == "cell":
        return 0.0  # collision cells tile the box; no search radius
    if config.collisions == "surrogate" and (config.detection or "swept") == "swept":
        return 2.0 * (r + speed_max * config.dt)
    if config.collisions in ("surrogate", "surrogate-paper"):
        return 2.0 * r
    if config.collisions == "dem":
        return 2.3 * r
    return 0.0


def check_search(config: CoolingConfig) -> None:
    """The pair search must stay below half the periodic box (no parcel meets its own image, minimum image is
    unique): refuse a box too small for the initial state's fastest parcel (as the strategy would, but here, before
    anything is built)."""
    from hel_warp.errors import ConfigError

    _, v = initial_state(config)
    speed = float(np.linalg.norm(v, axis=1).max())
    cell = search_cell(config, speed)
    if cell > 0.5 * config.box_length:
        raise ConfigError(f"the box side L = {config.box_length:.4g} m is too small for the pair search of "
                          f"{config.collisions} at dt = {config.dt:g} s: it spans {cell:.4g} m (fastest parcel "
                          f"{speed:.3g} m/s) and must stay below L/2; raise --particles, or lower --dt or "
                          "--solids-fraction")


# ------------------------------------------------------------------------------------------------ initial state
RANDOM_START_MAX_EPS = 0.1
"""Up to this solids fraction the parcels start at uniformly random, non-overlapping positions; above, on a jittered
lattice (a random start would take too many redraws)."""
REDRAW_ROUNDS = 200
"""Rounds of redrawing overlapping parcels before the random start gives way to the lattice."""


def random_positions(n: int, box: float, diameter: float, rng) -> np.ndarray | None:
    """``n`` uniformly random centres in the periodic box with no two closer than ``diameter (1 + gap)``: draw all,
    then redraw the higher-index parcel of every overlapping pair until none is left (None after REDRAW_ROUNDS).
    Unlike a lattice, this start already has the pair distribution of a dilute gas near contact (a lattice start
    collides too rarely for the first ~d / sqrt(Theta0))."""
    from scipy.spatial import cKDTree

    x = rng.uniform(0.0, box, size=(n, 3))
    for _ in range(REDRAW_ROUNDS):
        pairs = cKDTree(x, boxsize=box).query_pairs(r=diameter * (1.0 + LATTICE_GAP), output_type="ndarray")
        if pairs.size == 0:
            return x
        redraw = np.unique(pairs.max(axis=1))
        x[redraw] = rng.uniform(0.0, box, size=(redraw.size, 3))
    return None


def lattice_positions(n: int, box: float, diameter: float, rng) -> np.ndarray:
    """Random sites of a side^3 lattice of spacing a = L / side, each point moved by at most (a - d (1 + gap)) / 2
    per axis: no two spheres overlap, across the periodic faces too."""
    side = math.ceil(n ** (1.0 / 3.0) - 1e-9)
    a = box / side
    sites = np.sort(rng.choice(side**3, size=n, replace=False))
    ijk = np.stack([sites % side, (sites // side) % side, sites // (side * side)], axis=1).astype(np.float64)
    jitter = max(0.0, a - diameter * (1.0 + LATTICE_GAP))
    return np.mod((ijk + 0.5) * a + rng.uniform(-0.5, 0.5, size=(n, 3)) * jitter, box)


def initial_state(config: CoolingConfig) -> tuple[np.ndarray, np.ndarray]:
    """(x, v) of the parcels: non-overlapping positions (random up to eps_s RANDOM_START_MAX_EPS of parcels, else a
    jittered lattice) and Maxwellian velocities, weighted mean removed, scaled to Theta0 exactly."""
    if config.species is not None:
        return mixture_initial_state(config)
    rng = np.random.default_rng(config.seed)
    n, L, d = config.parcels, config.box_length, config.diameter
    x = None
    if config.parcel_eps <= RANDOM_START_MAX_EPS:
        x = random_positions(n, L, d, np.random.default_rng([config.seed, 1]))
    if x is None:
        x = lattice_positions(n, L, d, np.random.default_rng([config.seed, 2]))
    v = rng.normal(0.0, math.sqrt(config.theta0), size=(n, 3))
    v -= v.mean(axis=0)  # equal weights: the weighted mean is the plain mean
    v *= math.sqrt(config.theta0 / granular_temperature(v, np.full(n, config.weights[0])))
    return x, v


# ------------------------------------------------------------------------------------------------ binary mixture
def mixture_species(args, weights: tuple):
    """The species of a binary mixture (--diameter2 with --number-fraction2), or None for one size.

    ``diameters`` (d1, d2), ``counts`` (N1, N2) of real particles (N2 = round(F N)), ``weights`` (W1, W2) real
    particles per parcel, ``parcels`` per species N_k / W_k (W_k must divide N_k), ``number_fractions``.
    Species 1 is --diameter."""
    from hel_warp.errors import ConfigError

    from hel_warp.mixture import second_size

    sizes = second_size(getattr(args, "diameter2", None), getattr(args, "number_fraction2", None),
                        float(args.diameter), "--number-fraction2", "0.3")
    if sizes is None:
        return None
    d2, f2 = sizes
    n2 = int(round(f2 * args.particles))
    n1 = int(args.particles) - n2
    if n1 < 1 or n2 < 1:
        raise ConfigError(f"--number-fraction2 {f2:g} of --particles {args.particles} leaves a species empty "
                          f"({n1} + {n2}); raise --particles")
    for k, (n, w) in enumerate(zip((n1, n2), weights)):
        if n % w:
            raise ConfigError(f"--particles-per-parcel {','.join(map(str, weights))}: W{k + 1} = {w} does not divide "
                              f"the {n} particles of species {k + 1} ({n1} + {n2}); choose --particles (and "
                              "--number-fraction2) so that every weight divides its species")
    from hel_warp.mixture import sauter_mean

    fractions = (n1 / args.particles, n2 / args.particles)
    diameters = (float(args.diameter), float(d2))
    return SimpleNamespace(diameters=diameters, counts=(n1, n2), weights=tuple(weights),
                           parcels=(n1 // weights[0], n2 // weights[1]),
                           number_fraction2=float(f2), number_fractions=fractions,
                           sauter_mean=sauter_mean(fractions, diameters, (0.0, 0.0)))


def weights_output(weights: tuple):
    """``particles_per_parcel`` of the summary: the one weight W when every species has it, else [W1, W2]."""
    return int(weights[0]) if len(set(weights)) == 1 else [int(w) for w in weights]


def mixture_box_length(species, eps: float) -> float:
    """Side of the cube holding both species at solids fraction ``eps``: L^3 = pi sum N_i d_i^3 / (6 eps), m."""
    volume = sum(n * math.pi * d**3 / 6.0 for n, d in zip(species.counts, species.diameters))
    return (volume / eps) ** (1.0 / 3.0)


def check_model_covers(model_dir: str, meta: dict, diameters) -> None:
    """A mixture run needs a model whose training domain holds every size and size ratio
    (``hel_warp.mixture.model_domain_problem``); a ConfigError says which one it lacks."""
    from hel_warp.errors import ConfigError
    from hel_warp.mixture import model_domain_problem

    problem = model_domain_problem(meta, diameters)
    if problem:
        raise ConfigError(f"--model {model_dir}: {problem}; train on a mixture set (hel-warp dataset --diameters "
                          "D1,D2)")


def mixture_labels(config) -> np.ndarray:
    """Species (0 = --diameter, 1 = --diameter2) of each parcel, shuffled (a lattice start fills sites in order)."""
    labels = np.repeat([0, 1], config.species.parcels)
    return np.random.default_rng([config.seed, 3]).permutation(labels)


def species_masses(config) -> np.ndarray:
    """Mass of one particle of each species, kg."""
    return config.material.density * math.pi / 6.0 * np.asarray(config.species.diameters) ** 3


def random_positions_sized(radius: np.ndarray, box: float, rng) -> np.ndarray | None:
    """As :func:`random_positions` for spheres of their own ``radius`` (no two closer than (r_i + r_j)(1 + gap))."""
    from scipy.spatial import cKDTree

    n = radius.size
    reach = 2.0 * float(radius.max()) * (1.0 + LATTICE_GAP)
    x = rng.uniform(0.0, box, size=(n, 3))
    for _ in range(REDRAW_ROUNDS):
        pairs = cKDTree(x, boxsize=box).query_pairs(r=reach, output_type="ndarray")
        if pairs.size:
            s = x[pairs[:, 0]] - x[pairs[:, 1]]
            s -= box * np.round(s / box)
            close = np.linalg.norm(s, axis=1) < (radius[pairs[:, 0]] + radius[pairs[:, 1]]) * (1.0 + LATTICE_GAP)
            pairs = pairs[close]
        if pairs.size == 0:
            return x
        redraw = np.unique(pairs.max(axis=1))
        x[redraw] = rng.uniform(0.0, box, size=(redraw.size, 3))
    return None


def mixture_initial_state(config) -> tuple[np.ndarray, np.ndarray]:
    """(x, v) of a binary mixture: non-overlapping positions (random, else the lattice of the larger size) and
    Maxwellian velocities at equipartition, m_1 Theta_1 = m_2 Theta_2 (equal temperatures T_i = m_i Theta_i), with
    the mixture's mass-weighted Theta = Theta0; each species' mean removed (total momentum 0) and its Theta exact.
    Inelastic collisions then drive the species away from equipartition (Garzo & Dufty 1999)."""
    labels = mixture_labels(config)
    d = np.asarray(config.species.diameters)[labels]
    n, L = config.parcels, config.box_length
    x = None
    if config.parcel_eps <= RANDOM_START_MAX_EPS:
        x = random_positions_sized(0.5 * d, L, np.random.default_rng([config.seed, 1]))
    if x is None:
        x = lattice_positions(n, L, float(d.max()), np.random.default_rng([config.seed, 2]))
    masses = species_masses(config)
    counts = np.asarray(config.species.counts, float)
    theta_species = config.theta0 * (counts * masses).sum() / (counts.sum() * masses)
    rng = np.random.default_rng(config.seed)
    v = rng.normal(0.0, 1.0, size=(n, 3))
    for k in (0, 1):
        own = labels == k
        v[own] -= v[own].mean(axis=0)
        v[own] *= math.sqrt(theta_species[k] / granular_temperature(v[own], np.ones(int(own.sum()))))
    return x, v


def mixture_references(config, t: np.ndarray, theta_species: np.ndarray) -> dict:
    """Kinetic theory of the binary mixture (``hel_warp.mixture``): the Maxwellian rate equations from the measured
    start, the homogeneous-cooling temperature ratio, and the collisions per pair type over the measured
    Theta_i(t) (BMCSL g0_ij)."""
    from scipy.optimize import brentq

    from hel_warp import mixture as mx

    volume = config.box_length**3
    n = np.asarray(config.species.counts, float) / volume
    d = np.asarray(config.species.diameters, float)
    m = species_masses(config)
    e = config.material.restitution
    g0 = mx.contact_g0(n, d)
    kt = mx.cool_mixture(n, d, m, theta_species[0], e, t)
    rates = np.array([mx.collision_rates(n, d, m, th, g0) for th in theta_species])  # (steps+1, 2, 2)
    trapz = np.trapezoid if hasattr(np, "trapezoid") else np.trapz
    expected = trapz(rates, t, axis=0) * volume

    def log_rate_gap(r):  # d ln Theta_2/dt - d ln Theta_1/dt at Theta_2/Theta_1 = r
        rate = mx.temperature_rates(n, d, m, np.array([1.0, r]), e, g0)
        return rate[1] / r - rate[0]

    r_hcs = brentq(log_rate_gap, 1e-3 * m[0] / m[1], 1e3 * m[0] / m[1]) if e < 1.0 else m[0] / m[1]
    return {"g0": g0, "theta": kt, "expected": expected, "temperature_ratio_hcs": float(r_hcs * m[1] / m[0]),
            "number_densities": n, "masses": m}


def mixture_summary(case, t: np.ndarray, theta: np.ndarray, idx: np.ndarray, counts: dict) -> dict:
    """Keys of a binary-mixture run: the species temperatures (``granular_temperature_1``, ``_2``: Theta_i =
    <|c_i|^2>/3 of each species about its own mean, m^2/s^2) and their ratio T_2/T_1 = m_2 Theta_2 / (m_1 Theta_1)
    (1 = equipartition), the kinetic-theory references (module ``hel_warp.mixture``) and the collisions per pair
    type (the strategies count per stream pair; a parcel's stream is its species). Replaces the one-size
    Enskog / Haff keys by the mixture's: ``haff_slope`` is the slope of the kinetic-theory mixture Theta^-1/2(t)."""
    from hel_warp import mixture as mx

    cfg = case.config
    sp = case.theta_species()
    ref = mixture_references(cfg, t, sp)
    m = ref["masses"]
    ratio = sp[:, 1] * m[1] / (sp[:, 0] * m[0])
    kt_mix = mx.mixture_theta(ref["theta"], ref["number_densities"], m)
    kt_slope = float(np.polyfit(t, 1.0 / np.sqrt(kt_mix), 1)[0]) if len(t) >= 2 else float("nan")
    fitted = float(np.polyfit(t, 1.0 / np.sqrt(np.maximum(theta, 1e-300)), 1)[0]) if len(t) >= 2 else float("nan")
    expected = ref["expected"]
    total_expected = float(np.triu(expected).sum())
    measured_total = float(counts.get("collisions", 0.0))
    pair_types = {}
    events = 0.0  # parcel events: one of an (i, j) pair stands for min(W_i, W_j) real collisions
    for i, j, name in mx.pair_type_names(2):
        measured = counts.get(f"collisions_{i}_{j}", counts.get(f"collisions_{j}_{i}"))
        exp_ij = float(expected[i, j])
        events_ij = exp_ij / min(cfg.weights[i], cfg.weights[j])
        events += events_ij
        pair_types[name] = {"collisions": measured, "kinetic_theory_collisions": exp_ij,
                            "ratio": (float(measured) / exp_ij) if measured is not None and exp_ij > 0 else None,
                            "ratio_stderr": 1.0 / math.sqrt(events_ij) if exp_ij > 0 else None}
    T = float(t[-1])
    return {
        "mixture": True,
        "species": {"diameters": list(cfg.species.diameters), "particles": list(cfg.species.counts),
                    "particles_per_parcel": list(cfg.weights), "parcels": list(cfg.species.parcels),
                    "number_fraction2": cfg.species.number_fraction2, "masses": m.tolist(),
                    "sauter_mean_diameter": cfg.species.sauter_mean,
                    "start": "equipartition (m_1 Theta_1 = m_2 Theta_2), mass-weighted Theta = Theta0"},
        "granular_temperature_definition": "mixture: mass-weighted sum n_i m_i Theta_i / sum n_i m_i; species: "
                                           "Theta_i = <|c_i|^2>/3 about the species mean",
        "granular_temperature_1": sp[idx, 0].tolist(), "granular_temperature_2": sp[idx, 1].tolist(),
        "granular_temperature_1_initial": float(sp[0, 0]), "granular_temperature_2_initial": float(sp[0, 1]),
        "granular_temperature_1_final": float(sp[-1, 0]), "granular_temperature_2_final": float(sp[-1, 1]),
        "temperature_ratio": ratio[idx].tolist(), "temperature_ratio_final": float(ratio[-1]),
        "kinetic_theory": {
            "reference": "Maxwellian rate equations of a smooth inelastic binary mixture (hel_warp/mixture.py; "
                         "Garzo & Dufty 1999 zeroth order), BMCSL g0_ij, from the measured start",
            "granular_temperature_1_final": float(ref["theta"][-1, 0]),
            "granular_temperature_2_final": float(ref["theta"][-1, 1]),
            "temperature_ratio_final": float(ref["theta"][-1, 1] * m[1] / (ref["theta"][-1, 0] * m[0])),
            "temperature_ratio_hcs": ref["temperature_ratio_hcs"], "g0": ref["g0"].tolist(),
            "granular_temperature_final": float(kt_mix[-1])},
        "collision_pair_types": pair_types,
        "g0_carnahan_starling": None,
        "enskog_collisions": total_expected, "enskog_collision_frequency": 2.0 * total_expected / (cfg.particles * T),
        "collision_frequency_ratio": measured_total / total_expected if total_expected > 0 else None,
        "collision_frequency_ratio_stderr": 1.0 / math.sqrt(events) if events > 0 else None,
        "haff_slope": kt_slope, "fitted_slope": fitted,
        "cooling_rate_ratio": fitted / kt_slope if kt_slope > 0 else None,
        "cooling_rate_ratio_stderr": math.sqrt(2.0 / events) if events > 0 else None,
    }


def first_periodic_overlap(x: np.ndarray, diameter: float, box: float, tolerance: float = 1e-6):
    """First pair (i, j, depth) of equal spheres overlapping by more than ``tolerance d`` in the periodic box, else
    None (minimum-image distances, ``scipy.spatial.cKDTree(boxsize=L)``)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(np.mod(x, box), boxsize=box)
    pairs = tree.query_pairs(r=diameter * (1.0 - tolerance), output_type="ndarray")
    if pairs.size == 0:
        return None
    i, j = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))[0]]
    s = x[i] - x[j]
    s -= box * np.round(s / box)
    return int(i), int(j), float(diameter - np.linalg.norm(s))


# ------------------------------------------------------------------------------------------------ the flights
class BallisticFlight:
    """``none``: x += v dt, wrapped."""

    name = "none"

    def __init__(self, config: CoolingConfig):
        self.box = (config.box_length,) * 3
        self.notes = []

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

    def __init__(self, config: CoolingConfig):
        from hel_warp.coupling import CouplingFields, GridSpec
        from hel_warp.hel import KtgfCollision

        super().__init__(config)
        L = config.box_length
        cells = max(3, int(round(L / KTGF_CELL)))
        self.grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=L / cells, shape=(cells,) * 3,
                             periodic=(True, True, True))
        self.fields = CouplingFields.allocate(self.grid, config.parcels, device=config.device)
        self.ktgf_diameter = config.diameter if config.species is None else config.species.sauter_mean
        self.strategy = KtgfCollision(particle_diameter=self.ktgf_diameter, particle_density=config.material.density,
                                      restitution=config.material.restitution)
        self.dt = config.dt
        if config.species is not None:
            self.notes.append(f"ktgf: one diameter, the mixture's Sauter mean d_32 = {self.ktgf_diameter * 1e6:.1f} um "
                              "(the mixture KTGF closures are out of scope)")
        self.notes = self.notes + [f"ktgf: the engine's KtgfCollision on a periodic {cells}^3 grid of h = {L / cells:.4g} m "
                      f"({config.parcels / cells**3:.3g} parcels per cell), deposited with the engine's cloud-in-cell "
                      "coupling, no gas (no drag, K_sg = 0); it has no binary collisions (count 0); what it does "
                      "to Theta comes from the sampling-noise gradients of p_s only"]

    def step(self, particles, dt: float) -> None:
        from hel_warp.coupling import deposit_parcels
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


def _accepts(func, name: str) -> bool:
    try:
        return name in inspect.signature(func).parameters
    except (TypeError, ValueError):
        return False


class SurrogateFlight(BallisticFlight):
    """``surrogate`` / ``surrogate-paper``: collide (swept: the coming step's collisions; overlap: the current
    positions), x += v dt, the strategy's in-step position corrections, wrap."""

    def __init__(self, config: CoolingConfig):
        from hel_warp.errors import ConfigError
        import hel_warp.collision_models as cm

        super().__init__(config)
        self.name = config.collisions
        cls = cm.SurrogateCollision if config.collisions == "surrogate" else cm.SurrogatePaperCollision
        kwargs = {"model_dir": config.model}
        if _accepts(cls.__init__, "periodic_box"):
            kwargs["periodic_box"] = self.box
        else:
            self.notes.append("the strategy has no periodic_box: its pair search does not see across the periodic "
                              "faces, so collisions of pairs straddling a face are missed")
        if config.detection is not None:
            if not _accepts(cls.__init__, "detection"):
                raise ConfigError(f"--detection {config.detection}: SurrogateCollision in this checkout takes no "
                                  "detection argument (only its own end-of-step overlap test); drop --detection")
            kwargs["detection"] = config.detection
        if config.detection == "cell":
            kwargs["seed"] = config.seed  # the collision cells' random numbers
            cell = {}
            if getattr(config, "cell_approaching", None) is not None:
                cell["approaching"] = bool(config.cell_approaching)
            if getattr(config, "cell_transfer", None) is not None:
                cell["collisional_transfer"] = bool(config.cell_transfer)
            if cell:
                from hel_warp.cell_collisions import CellConfig

                kwargs["cell"] = CellConfig(**cell)
        if getattr(config, "particle_spin", False):
            kwargs["particle_spin"] = True
        self.strategy = cls(**kwargs)
        self.detection = getattr(self.strategy, "detection", config.detection or "overlap")
        self._collide_takes_dt = _accepts(self.strategy.collide, "dt")
        if not self._collide_takes_dt:
            self.notes.append("the strategy's collide() takes no dt: it resolves the pairs overlapping at the current "
                              "positions (end-of-step test)")
        self._correct = getattr(self.strategy, "correct_positions", None)
        self.weight = min(config.weights)
        self._warned_count = False

    def step(self, particles, dt: float) -> None:
        from kernels.free_flight import drift, wrap_periodic

        if self._collide_takes_dt:
            self.strategy.collide(particles, dt)
        else:
            self.strategy.collide(particles)
        drift(particles.x, particles.v, particles.alive, dt)
        if self._correct is not None:
            self._correct(particles)
        wrap_periodic(particles.x, particles.alive, self.box)

    def counts(self) -> dict:
        c = dict(self.strategy.counts())
        if "collisions" not in c:  # before the weight-aware count: every resolved pair counts min(W_k)
            c["collisions"] = c.get("surrogate_calls", 0) * self.weight
            if not self._warned_count:
                self.notes.append("the strategy reports no 'collisions' count: used surrogate_calls x W")
                self._warned_count = True
        return c


class DemFlight(BallisticFlight):
    """``dem``: ``DemCollision(periodic_box=...).advance_free(particles, dt)`` (contacts only, wraps positions)."""

    name = "dem"

    def __init__(self, config: CoolingConfig):
        from hel_warp.errors import ConfigError
        from hel_warp.cfd_dem import DemCollision

        super().__init__(config)
        if not hasattr(DemCollision, "advance_free") or not _accepts(DemCollision.__init__, "periodic_box"):
            raise ConfigError("--collisions dem needs DemCollision(periodic_box=...).advance_free(particles, dt) "
                              "(gas-free, periodic DEM sub-steps), which this checkout does not have yet")
        self.strategy = DemCollision(material=config.material, periodic_box=self.box)

    def step(self, particles, dt: float) -> None:
        self.strategy.advance_free(particles, dt)

    def counts(self) -> dict:
        return dict(self.strategy.counts())


FLIGHTS = {"none": BallisticFlight, "ktgf": KtgfFlight, "surrogate": SurrogateFlight,
           "surrogate-paper": SurrogateFlight, "dem": DemFlight}


# ------------------------------------------------------------------------------------------------ the case
class HomogeneousCooling:
    """The case: ``step()`` advances one dt with the chosen model and records the velocity moments on the device;
    ``theta()`` reads the Theta history once."""

    def __init__(self, config: CoolingConfig):
        import warp as wp

        from hel_warp.particles import Particles

        self.config = config
        x, v = initial_state(config)
        self.x0, self.v0 = x, v
        radius, stream = 0.5 * config.diameter, 0
        weight = np.full(config.parcels, float(config.weights[0]))
        if config.species is not None:  # the stream tag is the species: the strategies count per stream pair
            stream = mixture_labels(config)
            radius = 0.5 * np.asarray(config.species.diameters)[stream]
            weight = np.asarray(config.weights, np.float64)[stream]  # each species its own weight
        self.particles = Particles.from_numpy(x, radius, v=v, density=config.material.density, weight=weight,
                                              stream=stream, check_overlap=False, device=config.device)
        self._moment_weight = self.particles.weight  # one size: the parcel weights
        self._species_weight = []
        if config.species is not None:  # mass-weighted moments (w mass / m_1) and one set per species
            rel_mass = (species_masses(config) / species_masses(config)[0])[stream]
            self._moment_weight = wp.array((weight * rel_mass).astype(np.float32), dtype=wp.float32,
                                           device=config.device)
            self._species_weight = [wp.array((weight * (stream == k)).astype(np.float32), dtype=wp.float32,
                                             device=config.device) for k in (0, 1)]
        self.species_moments = [wp.zeros((config.steps + 1, 5), dtype=wp.float64, device=config.device)
                                for _ in self._species_weight]
        self.flight = FLIGHTS[config.collisions](config)
        self.moments = wp.zeros((config.steps + 1, 5), dtype=wp.float64, device=config.device)
        self.steps_done = 0
        self.count_totals: dict[str, float] = {}
        self.collisions_per_step = np.zeros(config.steps, np.float64)
        self.spin_square = np.zeros(config.steps + 1, np.float64)
        """Per recorded step: the mean of I |omega|^2 / (3 m) over the parcels (weights), m^2/s^2."""
        self._record()

    def _record(self) -> None:
        from kernels.free_flight import velocity_moments

        p = self.particles
        velocity_moments(p.v, self._moment_weight, p.alive, self.moments, self.steps_done)
        for weight, moments in zip(self._species_weight, self.species_moments):
            velocity_moments(p.v, weight, p.alive, moments, self.steps_done)
        # the others never turn a spin (the surrogate only with --particle-spin): their rows stay 0, with no read-back
        if self.config.collisions == "dem" or (self.config.collisions == "surrogate"
                                               and getattr(self.config, "particle_spin", False)):
            w = p.omega.numpy().astype(np.float64)
            r = p.radius.numpy().astype(np.float64)
            weight = np.asarray(self._moment_weight.numpy(), np.float64)
            self.spin_square[self.steps_done] = float(np.sum(weight * 0.4 * r**2 * (w**2).sum(axis=1)) /
                                                      (3.0 * weight.sum()))

    def step(self) -> None:
        self.flight.step(self.particles, self.config.dt)
        counts = self.flight.counts()
        for k, c in counts.items():
            if isinstance(c, (int, float, np.integer, np.floating)) and not isinstance(c, bool):
                self.count_totals[k] = self.count_totals.get(k, 0) + c
        self.collisions_per_step[self.steps_done] = float(counts.get("collisions", 0))
        self.steps_done += 1
        self._record()

    def time(self) -> np.ndarray:
        return np.arange(self.steps_done + 1) * self.config.dt

    def theta(self) -> np.ndarray:
        return theta_from_moments(self.moments.numpy()[: self.steps_done + 1])

    def rotational_temperature(self) -> np.ndarray:
        """(steps+1,) Theta_rot = I <|omega|^2> / (3 m) (mass-weighted), m^2/s^2: 0 throughout unless the collisions
        turn the spins (``dem``, ``surrogate --particle-spin``)."""
        return self.spin_square[: self.steps_done + 1].copy()

    def theta_species(self) -> np.ndarray:
        """(steps+1, 2) Theta of each species of a mixture about its own mean velocity, m^2/s^2."""
        return np.stack([theta_from_moments(m.numpy()[: self.steps_done + 1]) for m in self.species_moments], axis=1)

    def momentum(self) -> np.ndarray:
        """Total momentum per row, kg m/s (S1 times the particle mass)."""
        m = self.config.material.density * math.pi * self.config.diameter**3 / 6.0
        return self.moments.numpy()[: self.steps_done + 1, 1:4] * m


MOMENTUM_CONSERVING = ("none", "surrogate", "dem")
"""Models whose collisions are equal and opposite impulses: ``ktgf`` (-grad p_s / (eps_s rho_p) per parcel) and
``surrogate-paper`` (each parcel's new velocity from its averaged partners, sec. 4.3) do not conserve momentum."""


def momentum_drift(case: HomogeneousCooling) -> float:
    """max |P(T) - P(0)| over the axes, in units of N m sqrt(Theta0) (the momentum scale of the thermal motion)."""
    m = case.config.material.density * math.pi * case.config.diameter**3 / 6.0
    p = case.momentum()
    return float(np.abs(p[-1] - p[0]).max()) / (m * case.config.particles * math.sqrt(case.config.theta0))


def check(case: HomogeneousCooling, theta: np.ndarray) -> list[str]:
    """Physical facts at the end: finite state, every parcel in [0, L)^3, total momentum conserved (to 1e-4 of
    N m sqrt(Theta0), float32 velocities) by the models of MOMENTUM_CONSERVING."""
    errors = []
    x = case.particles.x.numpy()
    v = case.particles.v.numpy()
    L = case.config.box_length
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v)) and np.all(np.isfinite(theta))):
        errors.append("non-finite positions, velocities or Theta")
    elif np.any(x < 0.0) or np.any(x >= L):
        errors.append(f"{int(np.sum(np.any((x < 0.0) | (x >= L), axis=1)))} parcels outside the periodic box [0, L)")
    drift = momentum_drift(case)
    if case.config.collisions in MOMENTUM_CONSERVING and not drift <= 1e-4:
        errors.append(f"total momentum drifted by {drift:.2e} of N m sqrt(Theta0)")
    return errors


def analyse(case: HomogeneousCooling, wall_s: float, kernel_load_s: float) -> dict:
    """The summary: Theta(t), collisions, the Enskog and Haff references, their ratios and the statistics."""
    cfg = case.config
    cells = getattr(getattr(case.flight, "strategy", None), "cells", None)  # the cell detection's, if it runs
    t = case.time()
    theta = case.theta()
    T = float(t[-1])
    collisions = float(case.count_totals.get("collisions", 0.0))
    freq = 2.0 * collisions / (cfg.particles * T)
    g0 = carnahan_starling_g0(cfg.eps)
    omega = enskog_frequency(cfg.eps, cfg.diameter, theta)
    expected_per_particle = float(np.trapezoid(omega, t)) if hasattr(np, "trapezoid") else float(np.trapz(omega, t))
    enskog_mean = expected_per_particle / T
    e = cfg.material.restitution
    slope_haff = haff_slope(e, cfg.eps, cfg.diameter)
    y = 1.0 / np.sqrt(np.maximum(theta, 1e-300))
    fitted = float(np.polyfit(t, y, 1)[0]) if len(t) >= 2 else float("nan")
    stride = max(1, math.ceil(len(t) / MAX_JSON_POINTS))
    idx = np.arange(0, len(t), stride)
    if idx[-1] != len(t) - 1:
        idx = np.append(idx, len(t) - 1)
    counts = {k: (int(v) if float(v).is_integer() else float(v)) for k, v in sorted(case.count_totals.items())}
    flags = {k: v for k, v in counts.items() if any(f in k for f in COUNT_FLAGS)}
    enskog_collisions = 0.5 * cfg.particles * expected_per_particle
    # the statistics are those of the parcel events: a parcel collision of weight W stands for W real ones
    events = enskog_collisions / cfg.weights[0]
    notes = list(case.flight.notes)
    if max(cfg.weights) > 1:
        notes.append(f"parcels of weight {','.join(map(str, cfg.weights))}: the references are those of the N real "
                     "particles")
    summary = {
        "case": "homogeneous_cooling", "collision_model": cfg.collisions,
        "detection": getattr(case.flight, "detection", None), "model": cfg.model,
        "time": t[idx].tolist(), "granular_temperature": theta[idx].tolist(), "output_every_steps": int(stride),
        "collisions": collisions, "collision_frequency": freq,
        "solids_fraction": cfg.eps, "particles": cfg.particles, "parcels": cfg.parcels,
        "particles_per_parcel": weights_output(cfg.weights), "diameter": cfg.diameter, "dt": cfg.dt, "steps": case.steps_done,
        "end_time": T, "granular_temperature_initial": float(theta[0]), "granular_temperature_final": float(theta[-1]),
        "box_length": cfg.box_length, "restitution": e, "friction": cfg.material.friction,
        "density": cfg.material.density, "material_source": cfg.material_source, "g0_carnahan_starling": g0,
        "enskog_collision_frequency": enskog_mean, "enskog_collisions": enskog_collisions,
        "collision_frequency_ratio": freq / enskog_mean if enskog_mean > 0 else None,
        "collision_frequency_ratio_stderr": (1.0 / math.sqrt(events)) if events > 0 else None,
        "collisions_per_particle": 2.0 * collisions / cfg.particles,
        "haff_slope": slope_haff, "fitted_slope": fitted,
        "cooling_rate_ratio": fitted / slope_haff if slope_haff > 0 else None,
        "cooling_rate_ratio_stderr": (math.sqrt(2.0 / events)) if events > 0 else None,
        "collisions_per_step_max": float(case.collisions_per_step[: case.steps_done].max(initial=0.0)),
        "wall_clock_s": wall_s, "wall_clock_per_step_s": wall_s / max(case.steps_done, 1),
        "kernel_load_s": kernel_load_s,
        "rotational_temperature": case.rotational_temperature()[idx].tolist(),
        "rotational_temperature_final": float(case.rotational_temperature()[-1]),
        "particle_spin": bool(getattr(cfg, "particle_spin", False)),
        "cell_approaching": None if cells is None else bool(cells.approaching),  # the last step's, resolved
        "cell_transfer": None if cells is None else bool(cells.config.transfer),
        "momentum_drift": momentum_drift(case), "strategy_counts": counts, "strategy_flags": flags,
        "diagnostics": case.flight.diagnostics(case.particles),
        "seed": cfg.seed, "device": str(cfg.device), "notes": notes,
    }
    if cfg.species is not None:  # the mixture's references replace the one-size Enskog / Haff ones
        summary.update(mixture_summary(case, t, theta, idx, counts))
    return summary


def plot(summary: dict, path: str) -> None:
    """Theta(t) with Haff's curve (left), Theta^-1/2(t) with the fitted and Haff's lines (right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(summary["time"])
    theta = np.asarray(summary["granular_temperature"])
    theta0 = summary["granular_temperature_initial"]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    tt = np.linspace(0.0, t[-1], 200)
    ax1.plot(t * 1e3, theta, "-", color="C0", label=f"{summary['collision_model']}"
             + (f" ({summary['detection']})" if summary.get("detection") else ""))
    if summary.get("mixture"):
        d1, d2 = (1e6 * d for d in summary["species"]["diameters"])
        ax1.plot(t * 1e3, summary["granular_temperature_1"], "-", color="C1", lw=1, label=f"{d1:.0f} um")
        ax1.plot(t * 1e3, summary["granular_temperature_2"], "-", color="C2", lw=1, label=f"{d2:.0f} um")
    ax1.plot(tt * 1e3, haff_theta(theta0, summary["haff_slope"], tt), "--", color="k",
             label="kinetic theory (mixture)" if summary.get("mixture") else "Haff's law")
    ax1.set_xlabel("t, ms")
    ax1.set_ylabel(r"$\Theta$, m$^2$/s$^2$")
    ax1.set_ylim(bottom=0.0)
    ax1.legend()
    ratio = summary["cooling_rate_ratio"]
    fratio = summary["collision_frequency_ratio"]
    ax1.set_title(f"eps_s = {summary['solids_fraction']:g}, N = {summary['particles']}, dt = {summary['dt']:g} s, "
                  f"e = {summary['restitution']:g}", fontsize=9)
    y = 1.0 / np.sqrt(theta)
    ax2.plot(t * 1e3, y, "-", color="C0", label="measured")
    ax2.plot(tt * 1e3, 1.0 / math.sqrt(theta0) + summary["haff_slope"] * tt, "--", color="k",
             label=f"Haff slope {summary['haff_slope']:.4g}")
    fit0 = float(np.mean(y) - summary["fitted_slope"] * np.mean(t))
    ax2.plot(tt * 1e3, fit0 + summary["fitted_slope"] * tt, ":", color="C3",
             label=f"fit slope {summary['fitted_slope']:.4g}")
    ax2.set_xlabel("t, ms")
    ax2.set_ylabel(r"$\Theta^{-1/2}$, s/m")
    ax2.legend()
    ax2.set_title(f"cooling / Haff = {ratio:.3f}, collision frequency / Enskog = "
                  f"{fratio if fratio is None else round(fratio, 3)}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ------------------------------------------------------------------------------------------------ running
def run(args, *, progress: bool = True) -> int:
    from hel_warp._warp import init_warp
    from hel_warp.run import check_device, load_kernels

    config = make_config(args)
    check_device(config.device)
    init_warp(config.device)
    import kernels.free_flight  # noqa: F401  (compiled with the rest before the timed loop)

    kernel_load_s = load_kernels(config.device)
    case = HomogeneousCooling(config)
    bar = None
    if progress and not args.json:
        from tqdm import tqdm

        bar = tqdm(total=config.steps, unit="step", mininterval=0.5,
                   desc=f"homogeneous_cooling {config.collisions} dt={config.dt:g}")
    start = time.perf_counter()
    for _ in range(config.steps):
        case.step()
        if bar is not None:
            bar.update(1)
    wall_s = time.perf_counter() - start
    if bar is not None:
        bar.close()
    summary = analyse(case, wall_s, kernel_load_s)
    errors = check(case, case.theta())
    summary["check_errors"] = errors
    out = Path(config.out)
    if out.exists() and config.overwrite:
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    plot(summary, str(out / PICTURE))
    summary["picture"] = str(out / PICTURE)
    with open(out / SUMMARY, "w") as fh:
        json.dump(summary, fh, indent=1)
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"homogeneous_cooling [{config.collisions}"
              f"{'/' + summary['detection'] if summary['detection'] else ''}]: N = {config.particles} "
              f"({config.parcels} parcels, W = {','.join(map(str, config.weights))}), eps_s = {config.eps:g}, dt = {config.dt:g} s, {case.steps_done} steps: "
              f"Theta {summary['granular_temperature_initial']:.4g} -> {summary['granular_temperature_final']:.4g} "
              f"m^2/s^2, {summary['collisions']:g} collisions ({summary['collisions_per_particle']:.3g} per particle); "
              f"collision frequency / Enskog = {summary['collision_frequency_ratio']:.4f} "
              f"(+- {summary['collision_frequency_ratio_stderr'] or 0:.3f}), cooling rate / Haff = "
              f"{summary['cooling_rate_ratio']:.4f} (+- {summary['cooling_rate_ratio_stderr'] or 0:.3f}); "
              f"wall clock {wall_s:.2f} s -> {config.out}")
        if summary.get("mixture"):
            kt = summary["kinetic_theory"]
            print(f"  mixture: Theta_1 {summary['granular_temperature_1_initial']:.4g} -> "
                  f"{summary['granular_temperature_1_final']:.4g}, Theta_2 {summary['granular_temperature_2_initial']:.4g}"
                  f" -> {summary['granular_temperature_2_final']:.4g} m^2/s^2, T_2/T_1 = "
                  f"{summary['temperature_ratio_final']:.4f} (kinetic theory {kt['temperature_ratio_final']:.4f}, "
                  f"homogeneous cooling state {kt['temperature_ratio_hcs']:.4f}); the ratios above are to the "
                  "mixture's kinetic theory")
    for e in errors:
        print(f"homogeneous_cooling: check failed: {e}", file=sys.stderr)
    return 1 if errors else 0


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit code 2 (as the hel-warp command line)
        self.exit(2, f"{self.prog}: error: {message}\n")


def main(argv=None) -> int:
    from hel_warp.errors import HelWarpError

    parser = _Parser(prog="homogeneous_cooling", description=__doc__.split("\n\n")[0])
    add_arguments(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        return run(args, progress=not args.no_progress)
    except HelWarpError as exc:
        print(f"homogeneous_cooling: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

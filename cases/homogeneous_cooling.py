"""Homogeneous cooling of a granular gas (Haff 1983) in a periodic box: each collision model against kinetic theory.

N equal spheres (diameter D, the material's density) fill a cubic, triply periodic box at solids fraction EPS: no
gas, no gravity, no walls (a gas-free flow of the case API, ``hel_warp.case.granular``). They start at random,
non-overlapping positions (a jittered lattice above a parcel solids fraction of 0.1; never overlapping, also across
the periodic faces) with Maxwellian velocities at Theta0 and zero total momentum, rescaled so that the initial
granular temperature is exactly Theta0. Then, per step of dt, the collision model acts and the parcels fly on
straight lines (``none``: ballistic; ``ktgf``: the engine's KTGF acceleration on a periodic grid of the rig's cell
size, from the noise of a homogeneous gas only; ``surrogate`` with ``--detection swept|overlap|cell`` and
``surrogate-paper``; ``dem``: Hertz-Mindlin sub-steps). A swept search wider than half the box takes the step in
sub-steps that fit.

Box: the side L = (N pi D^3 / (6 EPS))^(1/3) holds N real particles; with ``--particles-per-parcel W`` they are
N / W parcels of weight W (each a sphere of diameter D standing for W particles). Material: the data set's
(restitution, friction) when the model's metadata records it, else ``Material(friction=0)`` (Haff's law and the
Enskog frequency are for smooth spheres).

References (``docs/physics.md``, "Collisions in a granular gas"):

- Enskog collision frequency per particle: omega = 24 eps g0 sqrt(Theta) / (sqrt(pi) D), Carnahan-Starling
  g0 = (1 - eps/2) / (1 - eps)^3; the reference count is N/2 times omega integrated over the measured
  Theta(t) (trapezoidal, every step), so the ratio is meaningful while the gas cools;
- Haff's law: Theta^(-1/2) grows linearly in t with slope 4 (1 - e^2) g0 eps / (D sqrt(pi)); the measured
  slope is the least-squares line through Theta^(-1/2)(t) of every step.

A binary mixture (``--diameter2 D2 --number-fraction2 F``; ``--particles`` counts both species, round(F N) of
D2): the box holds both species' volume at EPS, the start is random and non-overlapping (sum of radii) with the
species at equipartition (m_1 Theta_1 = m_2 Theta_2) and the mass-weighted mixture Theta exactly Theta0, each
species' mean velocity removed. A parcel's ``stream`` tag is its species, so the strategies' per-stream-pair counts
are the collisions per pair type. The JSON adds ``granular_temperature_1`` / ``_2``, ``temperature_ratio`` T_2/T_1,
``collision_pair_types`` and ``kinetic_theory`` (``hel_warp/collisions/mixture.py``: the Maxwellian rate equations of a smooth
inelastic binary mixture, BMCSL g0_ij, and the homogeneous-cooling-state ratio of Garzo & Dufty 1999).
``--particles-per-parcel W1,W2`` gives each species its own weight (W_k divides N_k)::

    python cases/homogeneous_cooling.py --collisions surrogate --model MIXTURE_MODEL --dt 1e-3 \\
        --solids-fraction 0.01 --particles 8000 --diameter 315e-6 --diameter2 475e-6 --number-fraction2 0.3 \\
        --granular-temperature 1 --end-time 0.04 --out runs/hc_mix_1e-3 --json

Statistical size of the check: with C real collisions the count has a relative standard error of about 1/sqrt(C)
(Poisson), and the energy lost (hence the fitted slope) about sqrt(2/C): the loss per collision is (1 - e^2) m
g_n^2 / 4 and, for collisions of a Maxwellian gas, E[g_n^4] / E[g_n^2]^2 = 2. Both are in the output
(``*_stderr``). Keep the run short enough that the gas stays homogeneous (a few to ~20 collisions per particle at
e = 0.9).

    python cases/homogeneous_cooling.py --collisions surrogate --detection swept --dt 1e-3 --solids-fraction 0.01 \\
        --particles 8000 --diameter 315e-6 --granular-temperature 1 --end-time 0.04 --out runs/hc_swept --json
    hel-warp run cases/homogeneous_cooling.py --collisions none --dt 1e-4 --solids-fraction 0.01 \\
        --particles 1000 --diameter 315e-6 --granular-temperature 1 --end-time 0.005 --out runs/hc_none

Writes the run directory of every case (``run.zarr``, VTK, checkpoints: ``--resume`` continues bit for bit) with
``summary.json`` (the object ``--json`` prints) and ``cooling.png`` (Theta(t) with Haff's curve, and
Theta^(-1/2)(t) with the fitted and Haff's lines). A failed ``check()`` (non-finite state, a parcel outside the
box, momentum not conserved by a conserving model): exit code 1.
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

if str(Path(__file__).resolve().parents[1]) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hel_warp import case as hc  # noqa: E402

COLLISIONS = ("none", "ktgf", "surrogate", "surrogate-paper", "dem")
MAX_JSON_POINTS = 2000
"""At most this many (time, Theta) points in the JSON / summary (every k-th step; the fit uses every step)."""
LATTICE_GAP = 1.0e-3
"""Smallest gap between lattice neighbours, in diameters (the jitter keeps every pair this far apart)."""
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
def options(groups) -> None:
    """The case's own options (the shared ones come from ``hel_warp.case.Case``)."""
    from hel_warp.errors import finite_float

    g = groups.case
    g.add_argument("--solids-fraction", type=finite_float, required=True, help="solids volume fraction eps_s")
    g.add_argument("--particles", type=int, required=True, help="real particles N")
    g.add_argument("--diameter", type=finite_float, required=True, help="particle diameter, m")
    g.add_argument("--diameter2", type=finite_float, default=None,
                   help="a binary mixture: diameter of the second species, m (with --number-fraction2; --particles "
                        "counts both species)")
    g.add_argument("--number-fraction2", type=finite_float, default=None,
                   help="number fraction of the --diameter2 species, in (0, 1)")
    g.add_argument("--granular-temperature", type=finite_float, required=True,
                   help="initial granular temperature Theta0, m^2/s^2")


def add_arguments(parser) -> None:
    """Every option of the case on ``parser`` (its own and the shared ones)."""
    CASE.add_arguments(parser)


class CoolingConfig(SimpleNamespace):
    """The validated settings (see :func:`make_config`): collisions, model, detection, dt, eps, particles (real,
    every species), parcels, weights (real particles per parcel of each species: (W,) for one size, (W1, W2) for a
    mixture), parcel_eps (the parcels' own solids fraction), diameter, theta0, end_time, steps, seed, device,
    box_length, material, material_source, model_meta, species (None, or the binary mixture of
    :func:`mixture_species`)."""


def _model_material(meta: dict | None):
    """(Material, source): the model's data-set material when its metadata records one, else friction 0."""
    from hel_warp.case.models import model_material
    from hel_warp.material import Material

    recorded = model_material(meta) if meta else None
    if recorded:
        fields = {k: float(recorded[k]) for k in ("density", "youngs_modulus", "poisson_ratio", "restitution",
                                                  "friction", "rolling_friction") if k in recorded}
        return Material(**fields), "model metadata"
    return Material(friction=0.0), "Material(friction=0) (the model metadata records no material)" if meta else \
        "Material(friction=0)"


def make_config(args) -> CoolingConfig:
    """Validate the case's options once (ConfigError with what to change) and derive the box, steps and material."""
    from hel_warp.case.models import read_metadata
    from hel_warp.errors import ConfigError
    from hel_warp.collisions.mixture import species_weights

    name = args.collisions
    if not 0.0 < args.solids_fraction < 1.0:
        raise ConfigError(f"--solids-fraction must lie in (0, 1) (got {args.solids_fraction:g})")
    if not args.diameter > 0.0:
        raise ConfigError(f"--diameter must be > 0 m (got {args.diameter:g})")
    if not args.granular_temperature > 0.0:
        raise ConfigError(f"--granular-temperature must be > 0 m^2/s^2 (got {args.granular_temperature:g})")
    if args.particles < 2:
        raise ConfigError(f"--particles must be >= 2 (got {args.particles})")
    if not args.dt > 0.0:
        raise ConfigError(f"--dt must be > 0 s (got {args.dt:g})")
    two_sizes = getattr(args, "diameter2", None) is not None or getattr(args, "number_fraction2", None) is not None
    weights = species_weights(args.particles_per_parcel, 2 if two_sizes else 1)
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
    meta = read_metadata(args.model) if args.model else None
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
    detection = args.detection
    if name == "surrogate" and detection is None and max(weights) > 1:
        detection = "cell"  # the strategy's own default for parcels heavier than one particle
    return CoolingConfig(collisions=name, model=args.model, detection=detection, dt=float(args.dt), eps=eps,
                         particles=int(args.particles), parcels=parcels, weights=weights, parcel_eps=parcel_eps,
                         diameter=d, theta0=float(args.granular_temperature), end_time=float(args.end_time),
                         steps=steps, seed=int(args.seed), device=args.device, box_length=L, material=material,
                         material_source=source, model_meta=meta, species=species,
                         particle_spin=bool(getattr(args, "particle_spin", False)),
                         cell_approaching=getattr(args, "cell_approaching", None))

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

    from hel_warp.collisions.mixture import second_size

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
    from hel_warp.collisions.mixture import sauter_mean

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
    (``hel_warp.collisions.mixture.model_domain_problem``); a ConfigError says which one it lacks."""
    from hel_warp.errors import ConfigError
    from hel_warp.collisions.mixture import model_domain_problem

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
    """Kinetic theory of the binary mixture (``hel_warp.collisions.mixture``): the Maxwellian rate equations from the measured
    start, the homogeneous-cooling temperature ratio, and the collisions per pair type over the measured
    Theta_i(t) (BMCSL g0_ij)."""
    from scipy.optimize import brentq

    from hel_warp.collisions import mixture as mx

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
    (1 = equipartition), the kinetic-theory references (module ``hel_warp.collisions.mixture``) and the collisions per pair
    type (the strategies count per stream pair; a parcel's stream is its species). Replaces the one-size
    Enskog / Haff keys by the mixture's: ``haff_slope`` is the slope of the kinetic-theory mixture Theta^-1/2(t)."""
    from hel_warp.collisions import mixture as mx

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
            "reference": "Maxwellian rate equations of a smooth inelastic binary mixture (hel_warp/collisions/mixture.py; "
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



# ------------------------------------------------------------------------------------------------ the record
class CoolingRecorder:
    """Observer of the box (after every step): the velocity moments (S0, S1, S2) of the parcels on the device, per
    species for a mixture, and the rotational temperature when the collisions turn spins; the collision counts of
    each step. All of it goes into the checkpoints, so a resumed run analyses the whole history."""

    def __init__(self, config: CoolingConfig):
        self.config = config
        self.count_totals: dict[str, float] = {}
        self.collisions_per_step = np.zeros(config.steps, np.float64)
        self.spin_square = np.zeros(config.steps + 1, np.float64)
        """Per recorded step: the mean of I |omega|^2 / (3 m) over the parcels (weights), m^2/s^2."""
        self.steps_done = 0
        self.moments = None

    def bind(self, sim) -> None:
        """Allocate the device records for the simulation's parcels and record the start (row 0)."""
        import warp as wp

        cfg = self.config
        particles = sim.solver.particles
        self.particles = particles
        self._moment_weight = particles.weight  # one size: the parcel weights
        self._species_weight = []
        if cfg.species is not None:  # mass-weighted moments (w mass / m_1) and one set per species
            stream = particles.stream.numpy()
            weight = particles.weight.numpy().astype(np.float64)
            rel_mass = (species_masses(cfg) / species_masses(cfg)[0])[stream]
            self._moment_weight = wp.array((weight * rel_mass).astype(np.float32), dtype=wp.float32,
                                           device=cfg.device)
            self._species_weight = [wp.array((weight * (stream == k)).astype(np.float32), dtype=wp.float32,
                                             device=cfg.device) for k in (0, 1)]
        self.moments = wp.zeros((cfg.steps + 1, 5), dtype=wp.float64, device=cfg.device)
        self.species_moments = [wp.zeros((cfg.steps + 1, 5), dtype=wp.float64, device=cfg.device)
                                for _ in self._species_weight]
        self._record()

    def _spins(self) -> bool:
        return self.config.collisions == "dem" or (self.config.collisions == "surrogate"
                                                   and self.config.particle_spin)

    def _record(self) -> None:
        from kernels.free_flight import velocity_moments

        p = self.particles
        velocity_moments(p.v, self._moment_weight, p.alive, self.moments, self.steps_done)
        for weight, moments in zip(self._species_weight, self.species_moments):
            velocity_moments(p.v, weight, p.alive, moments, self.steps_done)
        if self._spins():  # the others never turn a spin: their rows stay 0, with no read-back
            w = p.omega.numpy().astype(np.float64)
            r = p.radius.numpy().astype(np.float64)
            weight = np.asarray(self._moment_weight.numpy(), np.float64)
            self.spin_square[self.steps_done] = float(np.sum(weight * 0.4 * r**2 * (w**2).sum(axis=1)) /
                                                      (3.0 * weight.sum()))

    def after_step(self, sim) -> None:
        counts = sim.last_counts
        for k, c in counts.items():
            if isinstance(c, (int, float, np.integer, np.floating)) and not isinstance(c, bool):
                self.count_totals[k] = self.count_totals.get(k, 0) + c
        if self.steps_done < len(self.collisions_per_step):
            self.collisions_per_step[self.steps_done] = float(counts.get("collisions", 0))
        self.steps_done += 1
        if self.steps_done <= self.config.steps:
            self._record()

    def state(self) -> dict:
        names = sorted(self.count_totals)
        out = {"moments": self.moments.numpy(), "steps_done": np.array(self.steps_done),
               "collisions_per_step": self.collisions_per_step, "spin_square": self.spin_square,
               "count_names": np.array(names, dtype=str),
               "count_values": np.array([float(self.count_totals[k]) for k in names], np.float64)}
        for k, m in enumerate(self.species_moments):
            out[f"species_moments{k}"] = m.numpy()
        return out

    def set_state(self, state: dict) -> None:
        import warp as wp

        def grow(old, rows):
            new = np.zeros((rows,) + np.asarray(old).shape[1:], np.asarray(old).dtype)
            n = min(rows, len(old))
            new[:n] = np.asarray(old)[:n]
            return new

        rows = self.config.steps + 1
        self.steps_done = int(state["steps_done"])
        self.moments = wp.array(grow(state["moments"], rows), dtype=wp.float64, device=self.config.device)
        self.species_moments = [wp.array(grow(state[f"species_moments{k}"], rows), dtype=wp.float64,
                                         device=self.config.device) for k in range(len(self.species_moments))]
        self.collisions_per_step = grow(state["collisions_per_step"], rows - 1)
        self.spin_square = grow(state["spin_square"], rows)
        self.count_totals = {str(k): float(v) for k, v in zip(state["count_names"], state["count_values"])}
        for k, v in list(self.count_totals.items()):
            if v.is_integer():
                self.count_totals[k] = int(v)

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


def momentum_drift(record: CoolingRecorder) -> float:
    """max |P(T) - P(0)| over the axes, in units of N m sqrt(Theta0) (the momentum scale of the thermal motion)."""
    cfg = record.config
    m = cfg.material.density * math.pi * cfg.diameter**3 / 6.0
    p = record.momentum()
    return float(np.abs(p[-1] - p[0]).max()) / (m * cfg.particles * math.sqrt(cfg.theta0))


# ------------------------------------------------------------------------------------------------ the case
def build(args):
    """The flow: the periodic box without gas, the Maxwellian start placed parcel by parcel."""
    config = make_config(args)
    args._cooling = config
    L = config.box_length
    flow = hc.Flow("homogeneous_cooling", lo=(0.0, 0.0, 0.0), hi=(L, L, L), spacing=L, periodic=(True, True, True),
                   gas=None)
    x, v = initial_state(config)
    if config.species is None:
        flow.species("gas", config.diameter, material=config.material, weight=config.weights[0])
        flow.place("gas", x, v=v, weight=np.full(config.parcels, float(config.weights[0])), check_overlap=False)
    else:  # the stream tag is the species: the strategies count per stream pair
        stream = mixture_labels(config)
        for k, dk in enumerate(config.species.diameters):
            flow.species(f"species{k + 1}", dk, material=config.material, weight=config.weights[k])
        flow.place("species1", x, v=v, radius=0.5 * np.asarray(config.species.diameters)[stream],
                   weight=np.asarray(config.weights, np.float64)[stream], stream=stream, check_overlap=False)
    if config.species is not None:  # KTGF's one diameter: the mixture's Sauter mean
        flow.collision_defaults["ktgf"] = {"ktgf_diameter": config.species.sauter_mean}
    cell = {}
    if config.cell_approaching is not None:
        cell["approaching"] = bool(config.cell_approaching)
    if config.detection is not None:
        flow.collision_defaults["surrogate"] = {"detection": config.detection, **({"cell": cell} if cell else {})}
    return flow


def observers(args, flow) -> list:
    return [CoolingRecorder(args._cooling)]


def _record_of(run) -> CoolingRecorder:
    record = run.solver.observers[0]
    return record


def analyse(run) -> dict:
    """The summary: Theta(t), collisions, the Enskog and Haff references, their ratios and the statistics."""
    record = _record_of(run)
    cfg = record.config
    flight = run.solver.flight
    cells = getattr(flight.strategy, "cells", None)  # the cell detection's, if it runs
    t = record.time()
    theta = record.theta()
    T = float(t[-1])
    collisions = float(record.count_totals.get("collisions", 0.0))
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
    counts = {k: (int(v) if float(v).is_integer() else float(v)) for k, v in sorted(record.count_totals.items())}
    flags = {k: v for k, v in counts.items() if any(f in k for f in COUNT_FLAGS)}
    enskog_collisions = 0.5 * cfg.particles * expected_per_particle
    # the statistics are those of the parcel events: a parcel collision of weight W stands for W real ones
    events = enskog_collisions / cfg.weights[0]
    notes = list(flight.notes)
    if cfg.species is not None and cfg.collisions == "ktgf":
        notes.append(f"ktgf: one diameter, the mixture's Sauter mean d_32 = {flight.ktgf_diameter * 1e6:.1f} um "
                     "(the mixture KTGF closures are out of scope)")
    if max(cfg.weights) > 1:
        notes.append(f"parcels of weight {','.join(map(str, cfg.weights))}: the references are those of the N real "
                     "particles")
    summary = {
        "case": "homogeneous_cooling", "collision_model": cfg.collisions,
        "detection": getattr(flight, "detection", None), "model": cfg.model,
        "time": t[idx].tolist(), "granular_temperature": theta[idx].tolist(), "output_every_steps": int(stride),
        "collisions": collisions, "collision_frequency": freq,
        "solids_fraction": cfg.eps, "particles": cfg.particles, "parcels": cfg.parcels,
        "particles_per_parcel": weights_output(cfg.weights), "diameter": cfg.diameter, "dt": cfg.dt,
        "steps": record.steps_done,
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
        "collisions_per_step_max": float(record.collisions_per_step[: record.steps_done].max(initial=0.0)),
        "wall_clock_per_step_s": None,
        "rotational_temperature": record.rotational_temperature()[idx].tolist(),
        "rotational_temperature_final": float(record.rotational_temperature()[-1]),
        "particle_spin": bool(cfg.particle_spin),
        "cell_approaching": None if cells is None else bool(cells.approaching),  # the last step's, resolved
        "cell_transfer": None if cells is None else bool(cells.config.transfer),
        "momentum_drift": momentum_drift(record), "strategy_counts": counts, "strategy_flags": flags,
        "diagnostics": flight.diagnostics(run.solver.particles), "notes": notes,
        "swept_substeps": getattr(flight, "last_substeps", 1),
    }
    if cfg.species is not None:  # the mixture's references replace the one-size Enskog / Haff ones
        summary.update(mixture_summary(record, t, theta, idx, counts))
    return summary


def summary(run) -> dict:
    out = analyse(run)
    wall = run.series("timing_step")
    out["wall_clock_s"] = float(np.sum(wall)) if wall is not None else 0.0
    out["wall_clock_per_step_s"] = out["wall_clock_s"] / max(out["steps"], 1)
    return out


def check(run) -> list[str]:
    """Physical facts at the end: finite state, every parcel in [0, L)^3, total momentum conserved (to 1e-4 of
    N m sqrt(Theta0), float32 velocities) by the models of MOMENTUM_CONSERVING."""
    record = _record_of(run)
    theta = record.theta()
    errors = []
    x = run.solver.particles.x.numpy()
    v = run.solver.particles.v.numpy()
    L = record.config.box_length
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v)) and np.all(np.isfinite(theta))):
        errors.append("non-finite positions, velocities or Theta")
    elif np.any(x < 0.0) or np.any(x >= L):
        errors.append(f"{int(np.sum(np.any((x < 0.0) | (x >= L), axis=1)))} parcels outside the periodic box [0, L)")
    drift = momentum_drift(record)
    if record.config.collisions in MOMENTUM_CONSERVING and not drift <= 1e-4:
        errors.append(f"total momentum drifted by {drift:.2e} of N m sqrt(Theta0)")
    return errors


def finish(run, summary: dict) -> None:
    plot(summary, str(run.out / PICTURE))
    summary["picture"] = str(run.out / PICTURE)


def report(run, summary: dict) -> str:
    cfg = _record_of(run).config
    text = (f"homogeneous_cooling [{cfg.collisions}{'/' + summary['detection'] if summary['detection'] else ''}]: "
            f"N = {cfg.particles} ({cfg.parcels} parcels, W = {','.join(map(str, cfg.weights))}), eps_s = "
            f"{cfg.eps:g}, dt = {cfg.dt:g} s, {summary['steps']} steps: Theta "
            f"{summary['granular_temperature_initial']:.4g} -> {summary['granular_temperature_final']:.4g} m^2/s^2, "
            f"{summary['collisions']:g} collisions ({summary['collisions_per_particle']:.3g} per particle); "
            f"collision frequency / Enskog = {summary['collision_frequency_ratio']:.4f} "
            f"(+- {summary['collision_frequency_ratio_stderr'] or 0:.3f}), cooling rate / Haff = "
            f"{summary['cooling_rate_ratio']:.4f} (+- {summary['cooling_rate_ratio_stderr'] or 0:.3f}); "
            f"wall clock {summary['wall_clock_s']:.2f} s -> {run.out}")
    if summary.get("mixture"):
        kt = summary["kinetic_theory"]
        text += (f"\n  mixture: Theta_1 {summary['granular_temperature_1_initial']:.4g} -> "
                 f"{summary['granular_temperature_1_final']:.4g}, Theta_2 "
                 f"{summary['granular_temperature_2_initial']:.4g} -> {summary['granular_temperature_2_final']:.4g} "
                 f"m^2/s^2, T_2/T_1 = {summary['temperature_ratio_final']:.4f} (kinetic theory "
                 f"{kt['temperature_ratio_final']:.4f}, homogeneous cooling state {kt['temperature_ratio_hcs']:.4f}); "
                 "the ratios above are to the mixture's kinetic theory")
    return text


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


CASE = hc.Case("homogeneous_cooling", build, doc=__doc__, options=options, summary=summary, check=check,
               observers=observers, report=report, finish=finish, models=COLLISIONS, gas_snapshots=False)


def main(argv=None) -> int:
    return CASE.main(argv)


if __name__ == "__main__":
    sys.exit(main())

"""A pseudo-2D bubbling fluidized bed: the CFD-DEM benchmark of CFDEMcoupling's ``bubblingFluidizedBed`` tutorial
(after Khawaja 2015, case B), and its fluidization curve against Ergun's law and the bed's weight.

A box 43.2 mm wide (x) x 10 mm deep (y) x 124.8 mm tall (z) holds 9,240 spheres of 1.2 mm, rho_p = 1000 kg/m^3, in
a gas of rho_f = 1.13 kg/m^3 with air's viscosity. The gas enters through a uniform distributor on the floor (a
velocity inlet on ``z-``, superficial velocity U) and leaves through a pressure outlet on the roof. The particles
start as a dense bed 33 mm high, poured by a short DEM without friction and cached (``--packing settled``: poured
with the material's friction, 35 mm). The gas grid has cubic cells of
``--width / nx``: by default 18 x 4 x 52 cells of 2.4 mm, so the depth is 4 cells = 9.6 mm (the nearest whole
number of cells to 10 mm; the summary gives the box used).

``--velocity U1,U2,...`` with ``--hold T`` and ``--ramp T``: each level ramps in over ``--ramp`` and is held
``--hold`` s; every figure of a level is averaged over the second half of its hold. That is a fluidization curve
in one run: pressure drop against velocity, below minimum fluidization on Ergun's line, above it on the bed's weight
per area.

Models: ``dem`` (CFD-DEM: every sphere a parcel with Hertz-Mindlin contacts of the tutorial's material, E = 1.2e8
Pa, nu = 0.3, e = 0.986, mu = 0.1), ``ktgf`` (MP-PIC with the kinetic-theory collision term), ``surrogate``
(HELSCM: the learned binary collisions, with the cell detection that suits a dense bed), ``none`` (drag only). The
HEL models carry the enduring contacts of a packed bed with the MP-PIC packing stress (``hel_warp.hel.
PackingStress``: a stress that holds the bed's weight where the parcels touch, zero below the onset fraction of
enduring contacts) and contact damping; the binary models (KTGF, the surrogate) act on top of it where the bed is
loose. ``dem`` carries its contacts itself.

    python cases/bubbling_bed.py --collisions ktgf --velocity 0.2,0.4,0.6,0.8 --hold 0.5 --out runs/bed_ktgf
    hel-warp run cases/bubbling_bed.py --collisions dem --velocity 0.6 --end-time 1 --out runs/bed_dem

``--json`` prints one object: per level the velocity, the pressure drop (mean and standard deviation over the
level's second half), the bed height, the solids-fraction profiles across the bed at 10, 20 and 40 mm above the
distributor, the dominant frequency of the pressure-drop fluctuations, the standard error of the mean pressure drop
(``pressure_drop_error``: its fluctuations are correlated over a bubble's period), Ergun's pressure drop through the
level's own bed (its law integrated over the time-averaged voidage of each cell layer); the bed's weight per area,
Ergun's pressure drop per level at the settled bed's voidage, the Wen-Yu minimum fluidization velocity. ``OUT/``
holds the run directory of every case and the pictures ``bed_snapshots.png`` (parcels coloured by speed at a few
instants), ``bed_solids_fraction.png`` (the time-averaged map), ``bed_history.png`` (pressure drop and bed height
over time) and ``bed_fluidization.png`` (the curve with Ergun's line and the weight). ``scripts/bed_report.py``
draws several runs (models) side by side on one colour scale.
"""

from __future__ import annotations

import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

if str(Path(__file__).resolve().parents[1]) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hel_warp import case as hc  # noqa: E402
from hel_warp.errors import ConfigError  # noqa: E402

G = 9.80665
WIDTH, DEPTH, HEIGHT = 43.2e-3, 10.0e-3, 124.8e-3
"""The tutorial's box, m."""
PARTICLES = 9240
DIAMETER = 1.2e-3
DENSITY = 1000.0
GAS_DENSITY = 1.13
GAS_VISCOSITY = 1.81e-5
"""Air's viscosity at 20 C, Pa s."""
NX = 18
"""Cells across the width by default (2.4 mm cells: two particle diameters)."""
PROFILE_HEIGHTS = (0.010, 0.020, 0.040)
"""Heights above the distributor of the solids-fraction profiles, m."""
PROBE_EVERY = 2.0e-3
"""Sampling interval of the pressure drop and bed height, s (Nyquist 250 Hz; bubbling is a few Hz)."""
PROFILE_EVERY = 1.0e-2
"""Sampling interval of the solids-fraction profiles, s."""


def material():
    """The tutorial's Hertz-Mindlin material (walls alike)."""
    return hc.Material(density=DENSITY, youngs_modulus=1.2e8, poisson_ratio=0.3, restitution=0.986, friction=0.1,
                       wall_restitution_normal=0.986, wall_restitution_tangential=1.0)


def packing_stress(args=None):
    """The enduring contacts of the HEL models' packed parcels (``hel_warp.hel.PackingStress``).

    Snider's (2001) stress P_s (eps_s - onset)^2 / (eps_cp - eps_s) with a threshold: no stress below the onset
    0.615, the poured bed's own packing (the dense pour's 0.614: its particles touch there; looser parcels have no
    enduring contacts, so bubbles and the freeboard are free of it), diverging at eps_cp = 0.66. P_s = 30,000 Pa
    makes the packed bed nearly rigid, as a bed of stiff spheres is: its ~190 Pa weight compresses it by about
    0.015 in eps_s at the distributor, and as the gas takes the weight below minimum fluidization the bed keeps its
    voidage, so the pressure drop follows Ergun's line at the settled voidage (1.00 / 0.99 / 0.96 of it at 0.1 /
    0.2 / 0.3 m/s) up to the weight. An onset below the pour's packing lifts the bed at rest (0.61: 0.96 of Ergun
    at 0.1 m/s), one above it compacts the bed (0.62: 1.04). A soft stress (P_s = 300 Pa from an onset of 0.50)
    lets the compressed bed spring back as the gas unloads it: the bed at rest is denser than poured (1.22x Ergun at
    0.1 m/s in the loose pour), expands before it fluidizes (0.89x at 0.4 m/s) and meets the weight late (U_mf 0.49
    m/s against the CFD-DEM's 0.40). Its stiffness stays under ``PackingStress.stiffness_limit`` (3.6e4 Pa per unit
    eps_s on 2.4 mm cells at dt = 2e-4 s; above it the stress goes on along its tangent). Contact damping removes the
    parcels' velocity relative to the local solids velocity where contacts endure (O'Rourke & Snider
    2010), so a bed at rest stays at rest instead of ringing on the stress: 0.2 of it per step at the bed's dt of
    2e-4 s; 0.9 lifts the fluidized emulsion in slugs across the whole width (+- 13 Pa against the CFD-DEM's +- 7
    Pa at 0.66 m/s); without damping the
    packed emulsion boils as a granular gas."""
    from hel_warp.hel import PackingStress

    if args is not None and args.no_enduring_contacts:
        return None
    d = {"pressure": PACKING[0], "packed": PACKING[1], "onset": PACKING[2], "damping": PACKING[3]}
    if args is not None:
        for key in d:
            value = getattr(args, f"packing_{key}")
            if value is not None:
                d[key] = value
    return PackingStress(beta=2.0, **d)


PACKING = (30000.0, 0.66, 0.615, 0.2)
"""Default packing stress: P_s (Pa), eps_cp, onset, contact damping (``packing_stress``)."""


KTGF_COLLISIONAL_LIMIT = 0.1
"""Largest solids fraction of KTGF's radial distribution g0 in the bed (``hel_warp.hel.KtgfCollision``)."""
KTGF_RESTITUTION = 0.9
"""e_ss of the KTGF closure in the bed: the paper's Table 1 value, not the DEM material's 0.986. The algebraic
Theta of a compressing cell grows as (d tr(D) / (1 - e))^2: at e = 0.986 the slow compaction of a settled bed heats
it to Theta ~ 0.06 m^2/s^2, whose granular pressure throws the bed out of the box within 3 ms (measured, g0 up to
0.63, and within 0.1 s with g0 up to 0.5, 0.3 or 0.2). At e = 0.9 with g0 up to 0.1 a 3,000-particle bed holds
at rest at 0.15 m/s and carries its weight at 0.6 m/s (181 +- 24 Pa against 193 Pa); with g0 up to 0.3 it holds at
rest but is blown out within 0.2 s at 0.6 m/s, up to 0.5 sooner. Kinetic theory is the collisional regime; the
packing stress carries the enduring contacts."""


KTGF_DILUTE_LIMIT = 1.0
"""Smallest solids fraction of KTGF's solids phase in the bed, in particles per cell (``hel_warp.hel.KtgfCollision.
dilute_limit``: 0.066 on the 2.4 mm cells; elsewhere 1e-8). Kinetic theory is a continuum; in a cell with less than
one particle the algebraic Theta grows as 1 / eps_s and its granular pressure kicks the parcels at the cell's edge
by up to h / dt per step (12 m/s here). Without the limit the splash of each erupting bubble is so kicked: from the
settled bed at 0.66 m/s 27 % of the particles leave through the outlet within 0.8 s (speeds up to 80 m/s; the
rigid packed bed of the stiff packing stress erupts harder than a soft one); with it none leave at 0.8 m/s."""


SURROGATE_EPS_CAP = 0.1
"""Largest solids fraction of the Enskog factor g0 in the surrogate's collision cells in the bed
(``hel_warp.collisions.cells.CellConfig.eps_cap``; 0.55 elsewhere). Binary collisions are the collisional regime:
with g0 up to 0.55 the cells' collisions keep a bed at rest below U_mf boiling (3,000 particles at 0.44 U_mf: 53 mm
high instead of 34, pressure drop 32 +- 142 Pa); with 0.1 it holds (36 mm, 48 +- 41 Pa; with contact damping
0.9: 33.6 mm, 54 +- 12 Pa against Ergun's 49 Pa)."""

SURROGATE_TRANSFER = False
"""The surrogate's collisional transfer in the bed (``CellConfig.collisional_transfer``): off. The transfer
displaces each colliding pair apart along its normal so that a dense gas carries Enskog's collisional pressure
(the consistent Boltzmann algorithm); in the bed the packing stress already carries the dense regime, and the
displacements of the capped-rate collisions keep agitating the packed emulsion: with them a bed at rest jitters
(0.1 m/s: 40.0 +- 11.7 Pa against 41.5 +- 0.2 without) and at 0.66 m/s the particle pressure they add holds the
bed homogeneously expanded (190 +- 1 Pa, the bed still) where the CFD-DEM bubbles (194.5 +- 7.0 Pa)."""


def options(groups) -> None:
    c, p, n = groups.case, groups.physics, groups.numerics
    c.add_argument("--velocity", type=hc.floats, default=[0.6],
                   help="superficial gas velocity at the distributor, m/s: U, or U1,U2,... held in turn (default 0.6)")
    c.add_argument("--hold", type=float, default=None,
                   help="seconds each velocity level is held (default: --end-time shared among the levels)")
    c.add_argument("--ramp", type=float, default=0.0, help="seconds of linear ramp into each level (default 0)")
    c.add_argument("--distributor-noise", type=float, default=0.0,
                   help="frozen random nonuniformity of the distributor: each face's speed times 1 + A u, u uniform "
                        "in [-1, 1] (mean removed, so the superficial velocity stays), seeded by --seed; default 0: "
                        "uniform, as the CFDEM tutorial")
    c.add_argument("--particles", type=int, default=PARTICLES, help=f"real particles (default {PARTICLES})")
    c.add_argument("--packing", choices=("dense", "settled"), default="dense",
                   help="the bed at rest: 'dense' (poured without friction: a dense random packing, as a bed "
                        "tapped after filling; default) or 'settled' (poured with the material's friction: a loose "
                        "random packing)")
    p.add_argument("--diameter", type=float, default=DIAMETER, help=f"particle diameter, m (default {DIAMETER})")
    p.add_argument("--density", type=float, default=DENSITY, help=f"particle density, kg/m^3 (default {DENSITY:g})")
    c.add_argument("--width", type=float, default=WIDTH, help=f"box width (x), m (default {WIDTH})")
    c.add_argument("--depth", type=float, default=DEPTH,
                   help=f"box depth (y), m, rounded to whole cells (default {DEPTH})")
    c.add_argument("--height", type=float, default=HEIGHT,
                   help=f"box height (z), m, rounded to whole cells (default {HEIGHT})")
    a = groups.advanced
    a.add_argument("--packing-pressure", type=float, default=None,
                   help=f"HEL models: P_s of the packing stress, Pa (default {PACKING[0]:g})")
    a.add_argument("--packing-packed", type=float, default=None,
                   help=f"HEL models: close-packed solids fraction where the stress diverges (default {PACKING[1]:g})")
    a.add_argument("--packing-onset", type=float, default=None,
                   help=f"HEL models: solids fraction of the onset of enduring contacts (default {PACKING[2]:g})")
    a.add_argument("--packing-damping", type=float, default=None,
                   help=f"HEL models: contact damping per step where contacts endure, 0-1 (default {PACKING[3]:g})")
    a.add_argument("--no-enduring-contacts", action="store_true",
                   help="HEL models: no packing stress (binary collisions only; a bed then collapses)")
    n.add_argument("--cells", type=hc.ints, default=None,
                   help=f"gas cells NX,NY,NZ (cubic cells of width/NX; default {NX} across, the depth and height "
                        "in whole cells)")


def grid(args):
    """(cells, spacing, box hi) from the options: cubic cells, the box rounded to whole cells."""
    for name in ("width", "depth", "height", "diameter", "density"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"--{name} must be a positive number (got {value})")
    if args.cells is not None:
        if len(args.cells) != 3 or min(args.cells) < 1:
            raise ConfigError(f"--cells takes three positive integers NX,NY,NZ (got {args.cells})")
        cells = tuple(args.cells)
        spacing = args.width / cells[0]
    else:
        spacing = args.width / NX
        cells = (NX, max(1, round(args.depth / spacing)), max(1, round(args.height / spacing)))
    if spacing < args.diameter:
        raise ConfigError(f"cells of {spacing * 1e3:.2f} mm are smaller than a particle ({args.diameter * 1e3:.2f} mm); "
                          "use fewer cells")
    return cells, spacing, tuple(n * spacing for n in cells)


def schedule(args):
    """The distributor's velocity schedule (``hc.Levels``) and the run's end time."""
    levels = list(args.velocity)
    for u in levels:
        if not (math.isfinite(u) and u >= 0):
            raise ConfigError(f"--velocity levels must be finite and >= 0 m/s (got {u})")
    if args.hold is None:
        if args.end_time is None:
            raise ConfigError("give --end-time or --hold (seconds per velocity level)")
        args.hold = args.end_time / len(levels) - args.ramp
        if not args.hold > 0:
            raise ConfigError(f"--end-time {args.end_time:g} s leaves no hold after the ramps of {len(levels)} levels")
    sched = hc.Levels(levels, hold=args.hold, ramp=args.ramp)
    if args.end_time is None:
        args.end_time = sched.duration
    elif args.end_time < sched.duration * (1 - 1e-9):
        raise ConfigError(f"--end-time {args.end_time:g} s is shorter than the levels need ({len(levels)} x "
                          f"({args.ramp:g} + {args.hold:g}) = {sched.duration:g} s); raise it or drop --end-time")
    return sched


def distributor_noise(amplitude: float, seed: int):
    """The profile of ``--distributor-noise``: factors 1 + A (u - mean u), u uniform in [-1, 1] per face, fixed by
    ``seed``; their mean is 1, so the superficial velocity is the schedule's."""
    def factors(points):
        u = np.random.default_rng([int(seed), 0xD157]).uniform(-1.0, 1.0, len(points))
        return 1.0 + amplitude * (u - u.mean())
    return factors


def build(args):
    """The box, the distributor and outlet, the settled bed, the probes."""
    cells, spacing, hi = grid(args)
    sched = schedule(args)
    if args.particles < 1:
        raise ConfigError(f"--particles must be >= 1 (got {args.particles})")
    weights = hc.weights_of(args)
    flow = hc.Flow("bubbling_bed", lo=(0.0, 0.0, 0.0), hi=hi, cells=cells, gravity=(0.0, 0.0, -G),
                   gas=hc.Gas(density=GAS_DENSITY, viscosity=GAS_VISCOSITY),
                   walls=hc.Walls(friction=0.1, contact="surface"), packing_stress=packing_stress(args))
    if not (math.isfinite(args.distributor_noise) and 0.0 <= args.distributor_noise < 1.0):
        raise ConfigError(f"--distributor-noise must be in [0, 1) (got {args.distributor_noise})")
    if args.distributor_noise > 0.0:
        flow.inlet("distributor", "z-", sched, profile=hc.Profile(distributor_noise(args.distributor_noise, args.seed)))
    else:
        flow.inlet("distributor", "z-", sched)
    flow.outlet("top", "z+")
    mat = replace(material(), density=float(args.density))
    flow.species("bed", float(args.diameter), material=mat, weight=weights[0])
    # the region the bed is poured into: the whole width and depth, up to twice the height it fills at 0.6
    solids = args.particles * math.pi / 6.0 * args.diameter**3
    top = min(hi[2], 2.0 * solids / (0.6 * hi[0] * hi[1]) + 2 * args.diameter)
    if solids / (hi[0] * hi[1] * hi[2]) > 0.6:
        raise ConfigError(f"{args.particles} particles of {args.diameter * 1e3:g} mm fill more than 0.6 of the box; "
                          "use fewer particles or a taller box")
    # weighted parcels are placed over the height the bed holds at the packing stress's onset (a DEM pour is for
    # single particles): a bed placed denser is thrown apart by the stress in its first steps
    onset = max(0.3, flow.packing_stress.onset) if flow.packing_stress is not None else 0.6
    flow.fill("bed", ((0.0, 0.0, 0.0), (hi[0], hi[1], top)), count=args.particles, packing=args.packing,
              settled_fraction=onset)
    # surrogate: the cell detection (collisions per collision cell among the parcels in it) suits a dense bed,
    # where the swept search's binary events are not what carries the weight
    flow.collision_defaults["surrogate"] = {"detection": "cell", "cell": {"eps_cap": SURROGATE_EPS_CAP,
                                                                         "collisional_transfer": SURROGATE_TRANSFER}}
    # KTGF: kinetic theory is the collisional regime; above the onset of enduring contacts the packing stress
    # carries the bed (``hel_warp.hel.KtgfCollision``'s collisional_limit)
    if flow.packing_stress is not None:
        flow.collision_defaults["ktgf"] = {"collisional_limit": KTGF_COLLISIONAL_LIMIT, "restitution": KTGF_RESTITUTION,
                                           "dilute_limit": KTGF_DILUTE_LIMIT * math.pi / 6.0 * float(args.diameter) ** 3
                                           / spacing**3}
    # from the distributor to the outlet (the probes extend the pressure to the boundary faces): the whole bed, whose
    # weight per area the drop of a fluidized bed must equal
    flow.probe(hc.PressureDrop("bed_pressure_drop", axis="z", low=0.0, high=hi[2], every=PROBE_EVERY))
    flow.probe(hc.BedHeight("bed_height", floor=0.0, threshold=0.1, every=PROBE_EVERY))
    for h in PROFILE_HEIGHTS:
        if h < hi[2]:
            flow.probe(hc.Plane(f"profile_{h * 1e3:g}mm", axis="z", position=h, along="x", every=PROFILE_EVERY))
    flow.attrs.update({"levels": list(sched.values()), "hold": sched.hold, "ramp": sched.ramp,
                       "box": list(hi), "cells": list(cells)})
    return flow


# ---------------------------------------------------------------------------------------------- correlations
def archimedes(d: float, rho_p: float, rho_f: float = GAS_DENSITY, mu: float = GAS_VISCOSITY) -> float:
    return rho_f * (rho_p - rho_f) * G * d**3 / mu**2


def wen_yu_umf(d: float, rho_p: float, rho_f: float = GAS_DENSITY, mu: float = GAS_VISCOSITY) -> float:
    """Minimum fluidization velocity of Wen & Yu (1966): Re_mf = sqrt(33.7^2 + 0.0408 Ar) - 33.7, m/s."""
    re = math.sqrt(33.7**2 + 0.0408 * archimedes(d, rho_p, rho_f, mu)) - 33.7
    return re * mu / (rho_f * d)


def ergun(u: float, height: float, voidage: float, d: float, rho_f: float = GAS_DENSITY,
          mu: float = GAS_VISCOSITY) -> float:
    """Ergun's (1952) pressure drop across a fixed bed of ``height`` at ``voidage``, Pa."""
    e = voidage
    return height * (150.0 * mu * u * (1 - e) ** 2 / (e**3 * d**2) + 1.75 * rho_f * u**2 * (1 - e) / (e**3 * d))


FLUIDIZED_FRACTION = 0.9
"""A level whose pressure drop reaches this fraction of the bed weight per area counts as fluidized."""


def measured_umf(velocities, pressure_drops, weight_per_area: float) -> float | None:
    """The minimum fluidization velocity of a measured curve, m/s: where the fixed bed's branch meets the fluidized
    plateau, as read off a fluidization curve (Kunii & Levenspiel 1991, ch. 3).

    Fixed branch: the levels below ``FLUIDIZED_FRACTION`` of the weight per area, fitted by least squares with
    Ergun's form a U + b U^2 (a line through the origin with one level); plateau: the median pressure drop of the
    other levels (a slug that hits the top of the box sends one level's mean to several times the weight; the
    median keeps the plateau the fluidized levels share). None without a level on each branch."""
    u = np.asarray(velocities, float)
    dp = np.asarray([np.nan if p is None else p for p in pressure_drops], float)
    ok = np.isfinite(dp)
    u, dp = u[ok], dp[ok]
    fixed = dp < FLUIDIZED_FRACTION * weight_per_area
    if not fixed.any() or fixed.all():
        return None
    plateau = float(np.median(dp[~fixed]))
    uf, pf = u[fixed], dp[fixed]
    if len(uf) >= 2:
        (a, b), *_ = np.linalg.lstsq(np.column_stack([uf, uf**2]), pf, rcond=None)
    else:
        a, b = float(pf[0] / uf[0]), 0.0
    if abs(b) < 1e-12 * max(abs(a), 1e-300):
        return plateau / a if a > 0 else None
    disc = a * a + 4.0 * b * plateau
    if disc < 0:
        return None
    root = (-a + math.sqrt(disc)) / (2.0 * b)
    return float(root) if root > 0 else None


def dominant_frequency(t: np.ndarray, signal: np.ndarray) -> float:
    """The frequency of the largest peak of the fluctuations' spectrum, Hz (0 without samples enough)."""
    if len(signal) < 8:
        return 0.0
    dt = float(np.median(np.diff(t)))
    x = signal - signal.mean()
    spectrum = np.abs(np.fft.rfft(x * np.hanning(len(x))))
    freq = np.fft.rfftfreq(len(x), dt)
    if len(spectrum) < 2 or not np.any(spectrum[1:]):
        return 0.0
    return float(freq[1 + int(np.argmax(spectrum[1:]))])


def mean_error(signal) -> float | None:
    """Standard error of the mean of a correlated series (None below two samples): sigma sqrt(2 tau / n), with
    tau = 1/2 + sum of the normalised autocorrelation up to its first zero (Sokal's integrated autocorrelation time,
    in samples; 1/2 for white noise, which gives sigma / sqrt(n)). A bed's pressure drop is dominated by its bubbles:
    a 0.2 s window of a 5 Hz signal holds about three independent samples, so its mean is uncertain by about half
    its standard deviation, not by sigma / sqrt(100)."""
    x = np.asarray(signal, np.float64)
    n = x.size
    if n < 2:
        return None
    d = x - x.mean()
    var = float(d.var())
    if var == 0.0:
        return 0.0
    f = np.fft.rfft(d, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[:n] / (n * var)
    zero = np.flatnonzero(acf <= 0.0)
    tau = 0.5 + float(acf[1:zero[0] if zero.size else n].sum())
    return math.sqrt(var * 2.0 * tau / n) if 2.0 * tau < n else math.sqrt(var)


# ---------------------------------------------------------------------------------------------- results
def settled(run) -> dict:
    """The bed at t = 0 (the first snapshot of run.zarr): height (twice the mean particle height above the
    distributor, exact for a uniform bed) and solids fraction."""
    import zarr

    first = zarr.open_group(str(run.out / "run.zarr"), mode="r")["snapshots"]["000000"]
    z = np.asarray(first["x"][...], np.float64)[:, 2]
    w = np.asarray(first["weight"][...], np.float64) * np.asarray(first["radius"][...], np.float64) ** 3
    height = 2.0 * float(np.sum(w * z) / np.sum(w))
    args = run.args
    box = run.sim.flow.attrs["box"]
    solids = args.particles * math.pi / 6.0 * args.diameter**3
    return {"height": height, "solids_fraction": solids / (box[0] * box[1] * height)}


def levels_summary(run) -> list:
    flow = run.sim.flow
    probes = run.probes
    rec = probes.arrays() if probes is not None else {}
    out = []
    if "bed_pressure_drop" not in rec or "bed_height" not in rec:  # a run shorter than one probe interval
        return out
    windows = hc.Levels(flow.attrs["levels"], hold=flow.attrs["hold"], ramp=flow.attrs["ramp"]).windows()
    for u, (start, end) in zip(flow.attrs["levels"], windows):
        half = 0.5 * (start + end)
        if run.solver.time < end - 1e-9:  # a level the run has not finished
            break
        t = rec["bed_pressure_drop"]["time"]
        # samples of the level's own steps: the step ending at ``end`` already runs at the next level's speed
        sel = (t >= half - 1e-12) & (t < end - 0.5 * run.sim.settings.dt)
        dp = rec["bed_pressure_drop"]["pressure_drop"][sel]
        profiles = {}
        for h in PROFILE_HEIGHTS:
            name = f"profile_{h * 1e3:g}mm"
            if name in rec:
                avg = probes.time_average(name, "solids_fraction", half, end)
                x = flow.lo[0] + (np.arange(flow.cells[0]) + 0.5) * flow.spacing
                profiles[f"{h:g}"] = [[float(a), float(b)] for a, b in zip(x, avg)] if avg is not None else []
        layers = probes.time_average("bed_height", "layer_solids_fraction", half, end)
        ergun_layers = None
        if layers is not None:
            # Ergun's law through the bed the level holds: its gradient at each cell layer's time-averaged voidage
            eps_s = np.clip(np.nan_to_num(np.asarray(layers, np.float64)), 0.0, 0.99)
            ergun_layers = float(np.sum(ergun(u, run.sim.flow.spacing, 1.0 - eps_s, run.args.diameter)))
        out.append({"velocity": float(u), "pressure_drop": float(dp.mean()) if dp.size else None,
                    "pressure_drop_std": float(dp.std()) if dp.size else None,
                    "pressure_drop_error": mean_error(dp),
                    "bed_height": float(probes.time_average("bed_height", "bed_height", half, end)),
                    "mean_height_x2": float(probes.time_average("bed_height", "mean_height_x2", half, end)),
                    "solids_fraction_profiles": profiles, "ergun_pressure_drop_layers": ergun_layers,
                    "pressure_frequency": dominant_frequency(t[sel], dp), "window": [half, end]})
    return out


def summary(run) -> dict:
    args = run.args
    box = run.sim.flow.attrs["box"]
    area = box[0] * box[1]
    mass = args.particles * args.density * math.pi / 6.0 * args.diameter**3
    bed = settled(run)
    levels = levels_summary(run)
    p = run.solver.pool.particles
    alive = p.alive.numpy().astype(bool)
    weight = mass * G / area
    return {"levels": levels, "bed_weight_per_area": weight,
            "minimum_fluidization_velocity": measured_umf([lv["velocity"] for lv in levels],
                                                          [lv["pressure_drop"] for lv in levels], weight),
            "ergun_pressure_drop": [ergun(u, bed["height"], 1 - bed["solids_fraction"], args.diameter)
                                    for u in run.sim.flow.attrs["levels"]],
            "minimum_fluidization_velocity_wen_yu": wen_yu_umf(args.diameter, args.density),
            "settled_height": bed["height"], "settled_solids_fraction": bed["solids_fraction"],
            "diameter": float(args.diameter), "density": float(args.density),
            "particles": int(args.particles), "parcels": int(alive.sum()),
            "particles_left": float(np.sum(p.weight.numpy()[alive])), "box": box, "cells": run.sim.flow.attrs["cells"],
            "wall_clock_s": run.loop_s}


def check(run) -> list:
    """Physical facts every bed must keep: no particle lost through the distributor, none at NaN."""
    errors = []
    x = run.solver.pool.particles.x.numpy()
    alive = run.solver.pool.particles.alive.numpy().astype(bool)
    if not np.all(np.isfinite(x[alive])):
        errors.append("a parcel position is not finite")
    return errors


def report(run, summary) -> str:
    lines = [f"bubbling_bed {run.args.collisions}: {summary['particles']} particles, {summary['parcels']} parcels, "
             f"settled {summary['settled_height'] * 1e3:.1f} mm at eps_s {summary['settled_solids_fraction']:.3f}; "
             f"weight/area {summary['bed_weight_per_area']:.1f} Pa, U_mf (Wen-Yu) "
             f"{summary['minimum_fluidization_velocity_wen_yu']:.3f} m/s"]
    if summary.get("minimum_fluidization_velocity") is not None:
        lines[0] += f", measured {summary['minimum_fluidization_velocity']:.3f} m/s"
    for lv, erg in zip(summary["levels"], summary["ergun_pressure_drop"]):
        layered = lv.get("ergun_pressure_drop_layers")
        error = lv.get("pressure_drop_error")
        lines.append(f"  U = {lv['velocity']:.3f} m/s: dp = {lv['pressure_drop']:.1f} +- {lv['pressure_drop_std']:.1f} "
                     + (f"(mean +- {error:.1f}) " if error is not None else "")
                     + f"Pa (Ergun {erg:.1f} at the settled voidage"
                     + (f", {layered:.1f} through the level's layers" if layered is not None else "")
                     + f"), bed {lv['bed_height'] * 1e3:.1f} mm, {lv['pressure_frequency']:.1f} Hz")
    lines.append(f"  {summary['wall_clock_s']:.1f} s of steps; {run.out}")
    return "\n".join(lines)


def finish(run, summary) -> None:
    """The run's pictures (``scripts/bed_report.py`` draws several runs together)."""
    try:
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
        from bed_report import draw_run
    except ImportError:  # the scripts folder is not beside the case (an installed copy)
        return
    draw_run(run.out, summary)


CASE = hc.Case("bubbling_bed", build, doc=__doc__, options=options, summary=summary, check=check, report=report,
               finish=finish, defaults={"collisions": "ktgf", "dt": 2.0e-4, "end_time": None},
               models=("none", "ktgf", "surrogate", "dem"))


def main(argv=None) -> int:
    return CASE.main(argv)


if __name__ == "__main__":
    sys.exit(main())

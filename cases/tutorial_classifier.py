"""An air classifier in a small column: the tutorial flow of the case API (README, docs/case-api.md).

A column of air 20 mm wide and 100 mm tall (z up, 2 mm cells), a 10 mm slice of a deeper one (periodic in y),
starts with 300 coarse polyethylene beads of 400 um at rest on its floor; from 20 ms to 1 s, fines of 100 um are fed at
``--feed`` kg/s into the layer 10-20 mm above the floor. Air enters through the floor (a velocity inlet, ramped from 0 to ``--velocity`` over
20 ms; the beads bounce on it as on a distributor plate) and leaves at the top (a pressure outlet that removes the
beads reaching it). Between the two terminal velocities (0.25 and 1.6 m/s in still air) the air carries the fines
out and leaves the coarse beads behind.

The summary says which share of each species left through the top, and compares the fines' slip through the plane
at 85 mm (gas speed minus bead speed, weighted by the solids fraction, over the run's last third) with their
terminal velocity in still air (Schiller-Naumann drag)::

    python cases/tutorial_classifier.py --out runs/classifier
    python cases/tutorial_classifier.py --velocity 0.2 --out runs/classifier_slow
    hel-warp run tutorial_classifier --collisions none --out runs/classifier_none
"""

import math
import sys
from pathlib import Path

import numpy as np

if str(Path(__file__).resolve().parents[1]) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hel_warp import case as hc  # noqa: E402

WIDTH, DEPTH, HEIGHT = 20e-3, 10e-3, 100e-3
PLANE = 85e-3
"""Height of the measuring plane, m."""


def options(groups):
    groups.case.add_argument("--velocity", type=float, default=0.8, help="gas speed at the inlet, m/s (default 0.8)")
    groups.case.add_argument("--feed", type=float, default=1e-5, help="feed of fines, kg/s (default 1e-5)")
    groups.case.add_argument("--coarse", type=int, default=300, help="400 um beads on the floor (default 300)")


def build(args):
    flow = hc.Flow("tutorial_classifier", lo=(0, 0, 0), hi=(WIDTH, DEPTH, HEIGHT), spacing=2e-3,
                   periodic=(False, True, False), gravity=(0, 0, -9.81), gas=hc.Gas(density=1.205, viscosity=1.81e-5))
    flow.inlet("floor", "z-", velocity=hc.Ramp(value=args.velocity, duration=0.02))
    flow.outlet("top", "z+", pressure=0.0)
    flow.species("fines", 100e-6, material=hc.Material(density=1000.0))
    flow.species("coarse", 400e-6, material=hc.Material(density=1000.0))
    flow.fill("coarse", hc.Box(lo=(0, 0, 0), hi=(WIDTH, DEPTH, 4e-3)), count=args.coarse)
    feed = hc.Box(lo=(1e-3, 1e-3, 10e-3), hi=(WIDTH - 1e-3, DEPTH - 1e-3, 20e-3))  # inside the walls
    flow.inject("fines", feed, mass_flow=args.feed, start=0.02, end=1.0)
    flow.probe(hc.Plane("plane", axis="z", position=PLANE, along="x", every=2e-3))
    flow.probe(hc.PressureDrop("column", axis="z", low=1e-3, high=HEIGHT - 1e-3, every=2e-3))
    return flow


def terminal_velocity(d, rho_p, rho_f=1.205, mu=1.81e-5, g=9.81):
    """Still-air terminal velocity with Schiller-Naumann drag, m/s (fixed point on the force balance)."""
    v = rho_p * d**2 * g / (18 * mu)
    for _ in range(200):
        re = rho_f * v * d / mu
        v = math.sqrt(4 * (rho_p - rho_f) * g * d / (3 * rho_f * 24 / re * (1 + 0.15 * re**0.687)))
    return v


def summary(run):
    p = run.solver.pool.particles
    alive, stream = p.alive.numpy().astype(bool), p.stream.numpy()
    fed = run.solver.injected()[-1]["count"]  # the feed (the fill comes first)
    plane = run.probes.arrays()["plane"]
    last = plane["time"] >= 2 / 3 * run.args.end_time
    w = plane["solids_fraction"][last]  # (samples, cells along x)
    slip = plane["gas_velocity"][last][..., 2] - np.nan_to_num(plane["solids_velocity"][last][..., 2])
    return {"fines_fed": fed, "left_fines": 1 - np.sum(alive & (stream == 0)) / max(fed, 1),
            "left_coarse": 1 - np.sum(alive & (stream == 1)) / run.args.coarse,
            "fines_slip": float(np.sum(w * slip) / np.sum(w)) if np.sum(w) > 0 else None,
            "fines_terminal_velocity": terminal_velocity(100e-6, 1000.0),
            "pressure_drop": float(np.mean(run.probes.arrays()["column"]["pressure_drop"][-10:]))}


def report(run, s):
    slip = "no fines crossed it" if s["fines_slip"] is None else f"fines slip {s['fines_slip']:.3f} m/s"
    return (f"tutorial_classifier: U = {run.args.velocity} m/s: {s['left_fines']:.0%} of {s['fines_fed']} fines and "
            f"{s['left_coarse']:.0%} of the coarse beads left; at z = {PLANE * 1e3:.0f} mm {slip} (terminal velocity "
            f"{s['fines_terminal_velocity']:.3f} m/s); {s['steps']} steps in {s['wall_clock_s']:.1f} s -> {run.out}")


def check(run):
    """Physical facts, each failure a line (exit code 1): below their terminal velocity no coarse bead leaves."""
    p = run.solver.pool.particles
    coarse_alive = int(np.sum(p.alive.numpy().astype(bool) & (p.stream.numpy() == 1)))
    if run.args.velocity < terminal_velocity(400e-6, 1000.0) and coarse_alive < run.args.coarse:
        return [f"{run.args.coarse - coarse_alive} coarse beads left below their terminal velocity"]
    return []


CASE = hc.Case("tutorial_classifier", build, doc=__doc__, options=options, summary=summary, report=report,
               check=check, weights=False, defaults={"collisions": "ktgf", "dt": 5e-4, "end_time": 0.3})


def main(argv=None):
    return CASE.main(argv)


if __name__ == "__main__":
    sys.exit(main())

"""Cost of the surrogate's pair detection per parcel and step: swept (continuous, event-driven) beside overlap.

A periodic granular gas (315 um spheres, Maxwellian at Theta = 1 m^2/s^2, zero momentum, random non-overlapping
start) at each solids fraction and step; every case steps both detections round robin (a ballistic move between
collide calls, as ``cases/homogeneous_cooling.py``), after an untimed first step that loads the Warp kernels.
Prints the median wall clock of ``SurrogateCollision.collide`` per step and per parcel, collisions per parcel and
step, event rounds per step, and the swept / overlap ratio, side by side; ``--json`` prints one object.

    python scripts/bench_swept.py --model /work/models/contact_mu0_315 [--particles 8000] [--eps 0.01,0.05]
                                  [--dt 1e-3,1e-4] [--steps 5] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

D = 315e-6


def gas(n: int, eps: float, seed: int = 0):
    """Positions (random sequential addition, no overlap), velocities (Maxwellian, Theta = 1, zero momentum), box."""
    import numpy as np

    side = (n * math.pi * D**3 / 6.0 / eps) ** (1.0 / 3.0)
    rng = np.random.default_rng(seed)
    cells = max(1, int(side / D))
    x = np.empty((n, 3))
    grid: dict = {}
    k = 0
    while k < n:
        p = rng.uniform(0.0, side, 3)
        c = tuple((p / side * cells).astype(int) % cells)
        ok = True
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dz in (-1, 0, 1):
                    for q in grid.get(((c[0] + dx) % cells, (c[1] + dy) % cells, (c[2] + dz) % cells), ()):
                        d = p - x[q]
                        d -= side * np.round(d / side)
                        if d @ d < (1.001 * D) ** 2:
                            ok = False
        if ok:
            x[k] = p
            grid.setdefault(c, []).append(k)
            k += 1
    v = rng.normal(0.0, 1.0, (n, 3))
    v -= v.mean(axis=0)
    v *= math.sqrt(3.0 / float(np.mean(np.sum(v**2, axis=1))))
    return x, v, side


def bench_case(model: str, n: int, eps: float, dt: float, steps: int) -> dict:
    import numpy as np

    from hel_warp.collisions.models import SurrogateCollision
    from hel_warp.parcels.particles import Particles

    x, v, side = gas(n, eps)
    runs = {}
    for detection in ("swept", "overlap"):
        p = Particles.from_numpy(x, 0.5 * D, v=v, density=1000.0, check_overlap=False, device="cpu")
        s = SurrogateCollision(model_dir=model, detection=detection, periodic_box=(side,) * 3)
        runs[detection] = {"particles": p, "strategy": s, "times": [], "collisions": 0, "rounds": 0}
    for step in range(steps + 1):
        for detection, r in runs.items():  # round robin: machine load falls on both alike
            p, s = r["particles"], r["strategy"]
            t0 = time.perf_counter()
            s.collide(p, dt)
            c = s.counts()  # the host read that ends the step's device work
            wall = time.perf_counter() - t0
            p.x.assign(p.x.numpy() + p.v.numpy() * dt)
            s.correct_positions(p)
            p.x.assign(np.mod(p.x.numpy(), side))
            if step > 0:  # step 0 loads (compiles) the kernels
                r["times"].append(wall)
                r["collisions"] += c["collisions"]
                r["rounds"] += c["rounds"]
    out = {"particles": n, "solids_fraction": eps, "dt": dt, "steps": steps, "box": side}
    for detection, r in runs.items():
        med = statistics.median(r["times"])
        out[detection] = {"median_step_s": med, "per_parcel_us": med / n * 1e6,
                          "collisions_per_parcel_step": r["collisions"] / (n * steps),
                          "rounds_per_step": r["rounds"] / steps}
    out["swept_over_overlap"] = out["swept"]["median_step_s"] / out["overlap"]["median_step_s"]
    return out


def main(argv=None) -> int:
    from hel_warp.errors import HelWarpError

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True, help="contact-form surrogate model directory")
    ap.add_argument("--particles", type=int, default=8000)
    ap.add_argument("--eps", default="0.01,0.05", help="solids fractions, comma-separated")
    ap.add_argument("--dt", default="1e-3,1e-4", help="steps, s, comma-separated")
    ap.add_argument("--steps", type=int, default=5, help="timed steps per case (median)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    try:
        eps_list = [float(e) for e in args.eps.split(",")]
        dt_list = [float(d) for d in args.dt.split(",")]
        if args.particles < 2 or args.steps < 1 or not all(0 < e < 0.5 for e in eps_list) \
                or not all(d > 0 for d in dt_list):
            raise ValueError
    except ValueError:
        print("bench_swept: error: need --particles >= 2, --steps >= 1, 0 < eps < 0.5, dt > 0", file=sys.stderr)
        return 2
    from hel_warp._warp import init_warp

    init_warp()
    results = []
    try:
        for eps in eps_list:
            for dt in dt_list:
                results.append(bench_case(args.model, args.particles, eps, dt, args.steps))
    except HelWarpError as exc:
        print(f"bench_swept: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({"cases": results}, indent=1))
        return 0
    print(f"surrogate pair detection, periodic gas of {args.particles} spheres of 315 um, median of {args.steps} steps")
    print(f"{'eps':>6} {'dt, s':>8} | {'swept us/parcel':>15} {'coll/parcel':>11} {'rounds':>6} | "
          f"{'overlap us/parcel':>17} {'coll/parcel':>11} | {'swept/overlap':>13}")
    for r in results:
        s, o = r["swept"], r["overlap"]
        print(f"{r['solids_fraction']:>6.3f} {r['dt']:>8.1e} | {s['per_parcel_us']:>15.2f} "
              f"{s['collisions_per_parcel_step']:>11.4f} {s['rounds_per_step']:>6.1f} | {o['per_parcel_us']:>17.2f} "
              f"{o['collisions_per_parcel_step']:>11.4f} | {r['swept_over_overlap']:>13.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Throughput of the batched binary DEM (``hel_warp.collisions.impact.simulate_pairs``, what ``hel-warp dataset`` runs).

N random pairs of 315 um polyethylene spheres (radii 0.7-1.3 R, velocities uniform in [-20, 20] m/s per component,
head-on along their relative velocity, Hertz contact, e = 0.9, mu = 0.3), each at its own eq. (12) stable step, run
to separation in one batch after an untimed warm-up batch that loads the Warp kernels. Prints the wall clock, pairs
per second and how many pairs touched and separated; ``--json`` prints one object. The data set's budget: 60,000
pairs within a minute on two CPU cores.

    python scripts/bench_pairs.py [--pairs 60000] [--device cpu] [--repeats 1] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

R = 157.5e-6  # the paper's 315 um polyethylene sphere
RHO, E_MOD, NU = 1000.0, 5e8, 0.4


def random_pairs(n: int, seed: int = 1) -> dict:
    """``simulate_pairs`` keyword arguments for ``n`` random head-on pairs placed just apart."""
    import numpy as np

    from hel_warp.collisions.impact import place_just_apart, stable_time_step

    rng = np.random.default_rng(seed)
    r1, r2 = (R * rng.uniform(0.7, 1.3, n) for _ in range(2))
    v1, v2 = rng.uniform(-20, 20, (n, 3)), rng.uniform(-20, 20, (n, 3))
    g = v1 - v2
    normal = g / np.linalg.norm(g, axis=1)[:, None]
    dt = np.minimum(stable_time_step(r1, RHO, E_MOD, NU), stable_time_step(r2, RHO, E_MOD, NU))
    x1, x2 = place_just_apart(normal=normal, velocity1=v1, velocity2=v2, radius1=r1, radius2=r2, dt=dt)
    return dict(x1=x1, x2=x2, v1=v1, v2=v2, radius1=r1, radius2=r2, density1=RHO, youngs1=E_MOD, poisson1=NU,
                restitution=0.9, friction=0.3)


def bench(pairs: int, device: str, repeats: int) -> dict:
    from hel_warp.collisions.impact import simulate_pairs

    simulate_pairs(**random_pairs(16), device=device)  # kernel loading, not timed
    args = random_pairs(pairs)
    times, res = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = simulate_pairs(**args, device=device)
        times.append(time.perf_counter() - t0)
    wall = statistics.median(times)
    return {"pairs": pairs, "device": device, "repeats": repeats, "wall_s": round(wall, 4),
            "pairs_per_s": round(pairs / wall, 1), "touched": int(res.touched.sum()),
            "separated": int(res.separated.sum()), "load_average": list(os.getloadavg())}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--pairs", type=int, default=60_000, help="pairs in the batch (default 60000)")
    p.add_argument("--device", default="cpu", help="Warp device (default cpu)")
    p.add_argument("--repeats", type=int, default=1, help="timed batches; the median is reported (default 1)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)
    if args.pairs < 1 or args.repeats < 1:
        print("bench_pairs: error: --pairs and --repeats must be >= 1", file=sys.stderr)
        return 2
    from hel_warp._warp import init_warp

    init_warp(args.device)
    out = bench(args.pairs, args.device, args.repeats)
    if args.json:
        print(json.dumps(out))
    else:
        print(f"{out['pairs']} pairs on {out['device']}: {out['wall_s']:.2f} s ({out['pairs_per_s']:.0f} pairs/s), "
              f"{out['touched']} touched, {out['separated']} separated; load average "
              f"{', '.join(f'{x:.2f}' for x in out['load_average'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

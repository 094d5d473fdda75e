"""How far the rig's stream metrics move when a run's parcels are thinned to 1/k (each kept parcel weighted k).

A run of W particles per parcel carries the real particles of a weight-1 run in 1/W of the parcels; the report's
per-section crossing and transverse rms then rest on W times fewer samples. Thinning a weight-1 run (every k-th
``particle_id``, weights times k) gives the sampling noise of the metrics at that parcel count without any change of
physics:

    python scripts/rig_metric_subsample.py --reference runs/i10/dem_1e-3 runs/i10/dem_1e-3 runs/i10/none_1e-3 \\
        --keep 1 8 64
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np


def thinned(run, k: int):
    """``run`` with every k-th parcel (by particle_id) kept in each snapshot, its weight times k."""
    snaps = []
    for s in run.snapshots:
        ids = np.asarray(s["particle_id"]) if "particle_id" in s else np.arange(len(s["x"]))
        keep = ids % k == 0
        t = {n: (a[keep] if isinstance(a, np.ndarray) and a.shape[:1] == keep.shape else a) for n, a in s.items()}
        t["weight"] = np.asarray(t["weight"]) * k
        snaps.append(t)
    return dataclasses.replace(run, snapshots=snaps)


def main(argv=None) -> int:
    from hel_warp.runs.report import DEFAULT_BOXES, load_run, stream_metrics, stream_metrics_vs

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="run directories (cases/colliding_streams.py --out)")
    p.add_argument("--reference", required=True, help="the reference run (dem), not thinned")
    p.add_argument("--keep", type=int, nargs="+", default=[1, 8, 64], help="thinning factors k")
    p.add_argument("--min-samples", type=int, default=10, help="as hel-warp report --min-samples")
    args = p.parse_args(argv)
    ref = stream_metrics(load_run(args.reference), DEFAULT_BOXES, min_samples=args.min_samples)
    print("| run | keep | crossing | crossing vs reference | v_y rms, m/s | v_y rms vs reference |")
    print("|---|---|---|---|---|---|")
    for path in args.runs:
        run = load_run(path)
        for k in args.keep:
            m = stream_metrics(thinned(run, k), DEFAULT_BOXES, min_samples=args.min_samples)
            vs = stream_metrics_vs(m, ref, DEFAULT_BOXES, min_samples=args.min_samples)
            rel = vs["transverse_velocity_rms_vs_dem"]["relative_difference"]  # over the sections both have
            print(f"| {run.label} | 1/{k} | {m['stream_crossing']:.3f} | "
                  f"{vs['stream_crossing_vs_dem']['difference']:+.3f} | {m['transverse_velocity_rms']:.3f} | "
                  f"{100 * rel:+.1f} % |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

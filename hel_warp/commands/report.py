"""``hel-warp report``: velocity profiles, dispersion pictures, wall clock and collision rates of runs.

Reads one or more run directories written by ``cases/colliding_streams.py`` and writes
``REPORT_DIR/report.json`` (a ``runs`` list: collisions, dt, diameter, end_time, wall_clock_s,
collision_rate, profiles per sub-box count and section, profile_rms_vs_dem where a dem run is
present) and PNG figures (see ``hel_warp/report.py``). Several runs are compared side by side.
"""

from __future__ import annotations

from hel_warp.commands._common import finite_float


def add_parser(subparsers):
    p = subparsers.add_parser("report", help="profiles, pictures, wall clock and collision rates of runs",
                              description=__doc__)
    p.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run directories (cases/colliding_streams.py --out)")
    p.add_argument("--out", required=True, metavar="REPORT_DIR", help="directory for report.json and the PNGs")
    p.add_argument("--downstream-only", action="store_true",
                   help="average only particles moving downstream (as the experimental tracking did)")
    p.add_argument("--boxes", type=int, nargs="+", default=[20, 88, 126], metavar="N",
                   help="sub-boxes per section (default 20 88 126)")
    p.add_argument("--from-time", type=finite_float, default=0.0,
                   help="average snapshots from this simulated time on, s (default 0: all)")
    p.add_argument("--min-samples", type=int, default=10, metavar="N",
                   help="leave sub-boxes with fewer samples than N in either run out of the RMS vs dem (default 10)")
    p.add_argument("--no-figures", action="store_true", help="write report.json only")
    return p


def run(args) -> int:
    from hel_warp.report import write_report

    report = write_report(args.runs, args.out, boxes=args.boxes, downstream_only=args.downstream_only,
                          from_time=args.from_time, figures=not args.no_figures, min_samples=args.min_samples)
    for entry in report["runs"]:
        rate = entry["collision_rate"]
        rms = entry.get("profile_rms_vs_dem")
        rms_text = "" if not rms else "  rms vs dem " + ", ".join(
            f"{b}: {'-' if v is None else f'{v:.3f}'} m/s" for b, v in rms.items())
        bar = entry.get("paper_experimental_uncertainty")
        if rms and bar is not None:
            rms_text += f" (paper's uncertainty {bar} m/s)"
        wall = entry["wall_clock_s"]
        print(f"{entry['label']}: {entry['collisions']} dt={entry['dt']:g} s d={entry['diameter'] * 1e6:.0f} um "
              f"t={entry['end_time']:g} s  wall {'-' if wall is None else f'{wall:.2f}'} s  "
              f"collisions {'-' if rate is None else f'{rate:.4g}'} 1/s{rms_text}")
    print(f"wrote {args.out}/report.json and {len(report['figures'])} figures")
    return 0

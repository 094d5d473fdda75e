"""``hel-warp report``: what tells collision models apart on the colliding-streams rig, for one or more runs.

Reads run directories written by ``cases/colliding_streams.py`` and writes ``REPORT_DIR/report.json``,
``REPORT_DIR/summary.md`` and PNG figures (see ``hel_warp/runs/report.py``): per run the time-averaged axial velocity
profiles (20/88/126 sub-boxes) and their RMS from a ``dem`` run of the same size; the stream metrics per section
(stream composition per sub-box, stream crossing, transverse spread, transverse velocity profiles and rms), each
against dem (``*_vs_dem``); the real collision rate and its per-stream-pair rates beside the rate of pairs
overlapping at step ends; the like-with-like list of what still differs from dem and, given a ``none`` run and a
``dem --no-particle-contacts`` run, the gap the walls alone make. It prints the summary table: per step,
crossing, transverse rms, collision rate and axial RMS of every model.
"""

from __future__ import annotations

from hel_warp.errors import finite_float


def add_parser(subparsers):
    p = subparsers.add_parser("report", help="profiles, stream metrics, collision rates and pictures of rig runs",
                              description=__doc__)
    p.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run directories (cases/colliding_streams.py --out)")
    p.add_argument("--out", required=True, metavar="REPORT_DIR", help="directory for report.json and the PNGs")
    p.add_argument("--downstream-only", action="store_true",
                   help="average only particles moving downstream (as the experimental tracking did)")
    p.add_argument("--boxes", type=int, nargs="+", default=[20, 88, 126], metavar="N",
                   help="sub-boxes per section (default 20 88 126)")
    p.add_argument("--from-time", type=finite_float, default=0.0,
                   help="average the axial profiles over snapshots from this simulated time on, s (default 0: all)")
    p.add_argument("--stream-window", type=finite_float, nargs=2, default=[0.5, 1.0], metavar=("FROM", "TO"),
                   help="stream metrics over the snapshots between these fractions of each run's simulated time "
                        "(default 0.5 1: the second half)")
    p.add_argument("--composition-section", default="S5", metavar="NAME",
                   help="section whose stream composition is drawn as stacked bars (default S5)")
    p.add_argument("--min-samples", type=int, default=10, metavar="N",
                   help="leave sub-boxes (streams in a section) with fewer samples than N out of the comparisons "
                        "(default 10)")
    p.add_argument("--no-figures", action="store_true", help="write report.json and summary.md only")
    return p


def _number(value, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


def run(args) -> int:
    from hel_warp.runs.report import format_summary_table, write_report

    report = write_report(args.runs, args.out, boxes=args.boxes, downstream_only=args.downstream_only,
                          from_time=args.from_time, figures=not args.no_figures, min_samples=args.min_samples,
                          stream_window=args.stream_window, composition_section=args.composition_section)
    for entry in report["runs"]:
        rms = entry.get("profile_rms_vs_dem")
        rms_text = "" if not rms else "  axial rms vs dem " + ", ".join(
            f"{b}: {_number(v, '.3f')} m/s" for b, v in rms.items())
        bar = entry.get("paper_experimental_uncertainty")
        if rms and bar is not None:
            rms_text += f" (paper's uncertainty {bar} m/s)"
        note = f" ({entry['collision_rate_note']})" if entry.get("collision_rate_note") else ""
        sizes = entry.get("sizes") or f"{entry['diameter'] * 1e6:.0f} um"
        print(f"{entry['label']}: {entry['model']} dt={entry['dt']:g} s d={sizes} "
              f"t={entry['end_time']:g} s  wall {_number(entry['wall_clock_s'], '.2f')} s "
              f"(+ kernel loading {_number(entry['kernel_load_s'], '.2f')} s)  collisions "
              f"{_number(entry['collision_rate'], '.4g')} 1/s{note}, overlapping pairs "
              f"{_number(entry['overlap_pair_rate'], '.4g')} 1/s{rms_text}")
    print()
    print(format_summary_table(report["summary_table"], boxes=report["boxes"][0]))
    print(f"wrote {args.out}/report.json, {args.out}/summary.md and {len(report['figures'])} figures")
    return 0

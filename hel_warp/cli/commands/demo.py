"""``hel-warp demo``: the main job on an embedded default, end to end.

The whole HELSCM pipeline, each stage cached so a rerun continues where it stopped:

1. collision data set of DEM binary impacts (315 um polyethylene; resumable zarr);
2. surrogate training, ``contact`` form (a quick Optuna search; skipped when the model exists);
3. the three-particle streams of the paper's Fig. 13 with ``ktgf``, ``dem`` and ``surrogate``;
4. the colliding-streams rig at 315 um with ``none``, ``ktgf``, ``surrogate`` and a ``dem`` reference at every
   ``--dt``, and ``dem`` with the particle contacts off (the walls-only gap beside ``none``; ``--no-wall-effect``
   skips it);
5. ``hel-warp report`` over the rig runs (profiles, stream metrics, collision rates, pictures), then the table per
   step of stream crossing, transverse rms velocity, collision rate and axial RMS of each model against dem.

Every stage shows its own progress; the defaults take 3-4 minutes on two cores (about 50 MB of output), about 8
the first time, when Warp compiles the kernels into its cache. The
full-size versions of each stage are the commands printed in README.md.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from hel_warp.cli.commands._common import finite_float

REPO = Path(__file__).resolve().parents[3]


def add_parser(subparsers):
    p = subparsers.add_parser("demo", help="the main job: data set -> training -> three streams -> rig -> report",
                              description=__doc__)
    p.add_argument("--out", default="demo_out", help="output directory (default demo_out); reruns reuse it")
    p.add_argument("--samples", type=int, default=20000, help="collision data-set size (default 20000)")
    p.add_argument("--trials", type=int, default=4, help="Optuna trials per target (default 4)")
    p.add_argument("--diameter", type=finite_float, default=315e-6, help="particle diameter, m (default 315e-6)")
    p.add_argument("--dt", type=finite_float, nargs="+", default=[1e-3], metavar="DT",
                   help="HEL time step(s) of the rig, s (default 1e-3); every model runs at each")
    p.add_argument("--end-time", type=finite_float, default=0.02,
                   help="rig simulated time after release, s (default 0.02, as the paper's runs: the parcels "
                        "reach the downstream sections, so the profiles can be compared with dem)")
    p.add_argument("--dem-end-time", type=finite_float, default=None,
                   help="simulated time of the dem reference, s (default: --end-time)")
    p.add_argument("--cells", type=int, default=None, help="shrink the rig grid to about N cells")
    p.add_argument("--max-particles", type=int, default=4000,
                   help="cap the rig's parcels (default 4000 so the dem reference fits the demo; 0: the paper's "
                        "12,000)")
    p.add_argument("--device", default="cpu", help="Warp device: cpu or cuda (default cpu)")
    p.add_argument("--skip-rig", action="store_true", help="stop after the three-streams case")
    p.add_argument("--no-wall-effect", action="store_true",
                   help="skip the dem run without particle contacts (the walls-only gap beside none)")
    return p


def _load_case(name: str):
    from hel_warp.cli.commands._common import load_case_module

    return load_case_module(name)


class _Stages:
    """Numbered stage headings with their wall-clock times (the summary of the run)."""

    def __init__(self, total: int):
        self.total, self.index, self.times = total, 0, {}

    def run(self, name: str, func):
        self.index += 1
        print(f"\n[{self.index}/{self.total}] {name}", flush=True)
        start = time.perf_counter()
        result = func()
        self.times[name] = round(time.perf_counter() - start, 2)
        print(f"    done in {self.times[name]:.1f} s", flush=True)
        return result


def _dem_has_contact_switch() -> bool:
    """Whether this engine's ``dem`` can switch the particle contacts off (``DemCollision(particle_contacts=...)``)."""
    import inspect

    from hel_warp.hel import COLLISION_MODELS

    return "particle_contacts" in inspect.signature(COLLISION_MODELS["dem"].__init__).parameters


def _names(models) -> list:
    return ["dem without contacts" if "--no-particle-contacts" in extra else model for model, extra in models]


def _print_table(report_path: Path) -> None:
    """Print the report's table per step (crossing, transverse rms, collision rate, axial RMS per model) and the
    walls-only gap."""
    from hel_warp.runs.report import format_summary_table

    report = json.loads(report_path.read_text())
    print("\nCollision models on the rig against dem, per time step (report: "
          f"{report_path.parent}/summary.md, summary_table.png):\n")
    print(format_summary_table(report["summary_table"], boxes=report["boxes"][0]))
    for effect in report["like_with_like"]["wall_effect"]:
        crossing, rms = effect["stream_crossing_difference"], effect["transverse_velocity_rms_relative_difference"]
        print(f"walls alone at dt = {effect['dt']:g} s (none minus dem without particle contacts): crossing "
              f"{'-' if crossing is None else f'{crossing:+.3f}'}, transverse rms "
              f"{'-' if rms is None else f'{rms:+.1%}'}")
    if report["like_with_like"]["wall_effect_note"]:
        print(report["like_with_like"]["wall_effect_note"])


def _check(code, what: str) -> None:
    from hel_warp.errors import HelWarpError

    if code:
        raise HelWarpError(f"demo stage '{what}' failed (exit code {code}); see the message above")


def run(args) -> int:
    from hel_warp.cli import main as cli_main
    from hel_warp.runs.run import check_device

    check_device(args.device)  # before the first stage: a GPU asked for on a machine without one is one line
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    data_dir, model_dir = out / "dataset", out / "model_contact"
    stages = _Stages(5 if not args.skip_rig else 3)
    start = time.perf_counter()

    stages.run("collision data set (DEM binary impacts)", lambda: _check(cli_main([
        "dataset", "--out", str(data_dir), "--samples", str(args.samples), "--diameter", repr(args.diameter),
        "--seed", "0"]), "dataset"))

    def train():
        if (model_dir / "metrics.json").exists():
            from surrogate.artifact import load_artifact

            load_artifact(str(model_dir))  # validates hashes; a corrupt model is an error, not reused
            print(f"    model exists: {model_dir} (delete it to retrain)")
            return
        # --jobs 1: the same data set gives the same model every time (two trials side by side steer the sampler
        # by the order they finish in, so the demo's model, and whether it passes the guard check, varied by run)
        _check(cli_main(["train", "--data", str(data_dir), "--out", str(model_dir), "--form", "contact",
                         "--trials", str(args.trials), "--jobs", "1"]), "train")

    stages.run("surrogate training (contact form, XGBoost + Optuna)", train)
    metrics = json.loads((model_dir / "metrics.json").read_text())

    three = _load_case("three_streams")
    outcomes = {}

    def three_streams():
        for model in ("ktgf", "dem", "surrogate"):
            argv = ["--collisions", model, "--out", str(out / "three_streams" / model), "--device", args.device,
                    "--overwrite"]  # a rerun of the demo runs these seconds-long cases again
            if model == "surrogate":
                argv += ["--model", str(model_dir)]
            _check(three.main(argv), f"three streams {model}")
            summary = json.loads((out / "three_streams" / model / "summary.json").read_text())
            outcomes[model] = summary["outcome"]

    stages.run("three-particle streams, Fig. 13 (ktgf / dem / surrogate)", three_streams)

    rig_runs = []
    table = None
    if not args.skip_rig:
        rig = _load_case("colliding_streams")
        models = [("none", []), ("ktgf", []), ("surrogate", ["--model", str(model_dir)]), ("dem", [])]
        if not args.no_wall_effect and _dem_has_contact_switch():
            models.append(("dem", ["--no-particle-contacts"]))

        def rig_stage():
            for dt in args.dt:
                for model, extra in models:
                    end = args.end_time if model != "dem" or args.dem_end_time is None else args.dem_end_time
                    name = "dem_no_contacts" if "--no-particle-contacts" in extra else model
                    run_dir = out / "rig" / f"{name}_dt{dt:g}"
                    # the report reads the particle snapshots and series of run.zarr only: no VTK, no gas fields
                    argv = ["--diameter", repr(args.diameter), "--dt", repr(dt), "--collisions", model,
                            "--end-time", repr(end), "--out", str(run_dir), "--device", args.device, "--overwrite",
                            "--no-vtk", "--no-gas-snapshots", *extra]
                    if args.cells:
                        argv += ["--cells", str(args.cells)]
                    if args.max_particles and args.max_particles > 0:
                        argv += ["--max-particles", str(args.max_particles)]
                    print(f"    rig: {name}, dt = {dt:g} s", flush=True)
                    _check(rig.main(argv), f"rig {name} dt={dt:g}")
                    for checkpoint in run_dir.glob("checkpoint*.npz"):  # for --resume; a rerun here overwrites
                        checkpoint.unlink()
                    rig_runs.append(str(run_dir))

        stages.run(f"colliding-streams rig ({' / '.join(_names(models))}) at dt = "
                   f"{', '.join(f'{dt:g}' for dt in args.dt)} s", rig_stage)
        def report_stage():
            from hel_warp.runs.report import write_report

            written = write_report(rig_runs, str(out / "report"))
            print(f"    wrote {out / 'report'}/report.json, summary.md and {len(written['figures'])} figures")
            return written["summary_table"]

        table = stages.run("report", report_stage)

    summary = {
        "out": str(out),
        "stage_seconds": stages.times,
        "total_seconds": round(time.perf_counter() - start, 2),
        "surrogate_mae": metrics.get("mae"),
        "three_streams": outcomes,
        "report": str(out / "report" / "report.json") if rig_runs else None,
        "summary_table": table,
    }
    (out / "demo_summary.json").write_text(json.dumps(summary, indent=2))
    print("\n" + json.dumps({k: v for k, v in summary.items() if k != "summary_table"}, indent=2))
    if rig_runs:
        _print_table(out / "report" / "report.json")
    return 0


if __name__ == "__main__":  # pragma: no cover
    from hel_warp.cli import main

    sys.exit(main(["demo", *sys.argv[1:]]))

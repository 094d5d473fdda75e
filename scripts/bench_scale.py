"""The periodic riser at K = 0, 1, 2, ... tiles per collision model: cost per parcel-step and memory per particle.

Each size runs ``cases/periodic_riser.py`` in a process of its own (``--json``: the kernels are loaded before
the steps and never timed), ``--steps`` steps of ``--dt``; the cost is the median of the per-step wall clock
(``run.zarr`` series ``timing_step``) past the first ``--skip`` steps (they record launches), divided by the
parcels. A model goes on to the next K while its last run took less than ``--budget`` seconds of wall clock
and K <= ``--max-tiles``. Writes ``OUT/bench_scale.json`` (per device, model and K: parcels, fluid cells, parcel-
steps per second, seconds per parcel-step, bytes per particle, launches and reads per step) and
``OUT/bench_scale.png`` (log-log: parcel-steps per second against parcels, one line per device and model).

    python scripts/bench_scale.py --out runs/bench_scale                       # CPU, every model
    python scripts/bench_scale.py --device cuda --max-tiles 6 --out runs/bench_scale_gpu
    python scripts/bench_scale.py --dry-run --out /tmp/bench_scale_dry         # K = 0, 3 steps, each model

``surrogate`` needs ``--model DIR`` (a contact-form model for 100 um, 2000 kg/m^3 spheres; ``--force`` passes a
model of other particles for a cost-only measurement) or builds one on first use (``hel_warp.case.models``);
``--weights W`` adds ``surrogate`` and ``ktgf`` at W particles per parcel (the cell detection).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
MODELS = ("none", "ktgf", "surrogate", "dem")


def parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    p.add_argument("--models", default=",".join(MODELS), help="comma-separated collision models")
    p.add_argument("--max-tiles", type=int, default=4, help="largest K (default 4)")
    p.add_argument("--budget", type=float, default=60.0, help="go to the next K while a run took < this, s")
    p.add_argument("--steps", type=int, default=12, help="steps per run (default 12)")
    p.add_argument("--skip", type=int, default=3, help="first steps left out of the median (default 3)")
    p.add_argument("--dt", type=float, default=1e-4, help="time step, s (default 1e-4)")
    p.add_argument("--model", default=None, help="surrogate model directory")
    p.add_argument("--force", action="store_true", help="pass --force to the surrogate runs (cost only)")
    p.add_argument("--weights", type=int, default=None, help="also ktgf and surrogate at W particles per parcel")
    p.add_argument("--dry-run", action="store_true", help="K = 0, 3 steps per model: the pipeline, no figures")
    args = p.parse_args(argv)
    bad = [m for m in args.models.split(",") if m not in MODELS]
    if bad or args.steps <= args.skip or args.max_tiles < 0:
        p.exit(2, f"hel-warp: error: bench_scale: bad --models {bad} or --steps <= --skip or --max-tiles < 0\n")
    return args


def run_one(args, model: str, tiles: int, weight: int, out: Path) -> dict:
    steps = 3 if args.dry_run else args.steps
    run_dir = out / "runs" / f"{args.device}_{model}_w{weight}_K{tiles}"
    cmd = [sys.executable, str(REPO / "cases" / "periodic_riser.py"), "--collisions", model, "--tiles", str(tiles),
           "--dt", repr(args.dt), "--end-time", repr(steps * args.dt), "--particles-per-parcel", str(weight),
           "--device", args.device, "--out", str(run_dir), "--overwrite", "--json", "--no-vtk", "--no-progress",
           "--no-gas-snapshots", "--output-interval", repr(steps * args.dt), "--samples", "1"]
    if model == "surrogate" and args.model:
        cmd += ["--model", args.model] + (["--force"] if args.force else [])
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=str(REPO))
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        return {"model": model, "tiles": tiles, "weight": weight, "error": proc.stderr.strip().splitlines()[-1:],
                "process_s": wall}
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    import zarr

    series = np.asarray(zarr.open_group(str(run_dir / "run.zarr"), mode="r")["series"]["timing_step"][...])
    skip = min(args.skip, len(series) - 1)
    step_s = float(np.median(series[skip:]))
    parcels = int(summary["parcels"])
    return {"model": model, "tiles": tiles, "weight": weight, "device": args.device, "parcels": parcels,
            "particles": summary["particles"], "fluid_cells": summary["fluid_cells"], "steps": summary["steps"],
            "step_s": step_s, "seconds_per_parcel_step": step_s / parcels, "parcel_steps_per_second": parcels / step_s,
            "particle_steps_per_second": summary["particles"] / step_s,
            "bytes_per_particle": summary["bytes_per_particle"],
            "device_bytes": summary["device_bytes"], "launches_per_step": summary["launches_per_step"],
            "graph_launches_per_step": summary.get("graph_launches_per_step"),
            "device_reads_per_step": summary["device_reads_per_step"], "dem_step": summary.get("dem_step"),
            "kernel_load_s": summary["kernel_load_s"], "process_s": wall}


def plot(rows: list, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5))
    keys = sorted({(r["device"], r["model"], r["weight"]) for r in rows if not r.get("error")})
    for device, model, weight in keys:
        sel = sorted((r for r in rows if not r.get("error") and (r["device"], r["model"], r["weight"]) ==
                      (device, model, weight)), key=lambda r: r["parcels"])
        label = f"{device} {model}" + (f" W={weight}" if weight > 1 else "")
        ax.loglog([r["parcels"] for r in sel], [r["parcel_steps_per_second"] for r in sel], "o-", label=label)
    ax.set_xlabel("parcels (224 x 4^K / W)")
    ax.set_ylabel("parcel-steps per second (median step, s^-1)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bed_report import stamp  # commit and date in the corner

    stamp(fig)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(path: Path, rows: list) -> None:
    machine = f"{os.uname().sysname} {os.uname().machine}"
    path.write_text(json.dumps({"machine": machine, "cpus": os.cpu_count(), "runs": rows}, indent=1))


def main(argv=None) -> int:
    args = parse(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plan = [(m, 1) for m in args.models.split(",")]
    if args.weights and args.weights > 1:
        plan += [(m, args.weights) for m in ("ktgf", "surrogate") if m in args.models.split(",")]
    rows = []
    path = out / "bench_scale.json"
    if path.exists() and not args.dry_run:
        rows = [r for r in json.loads(path.read_text())["runs"] if r.get("device") != args.device]
    for model, weight in plan:
        for tiles in range(0, 1 if args.dry_run else args.max_tiles + 1):
            row = run_one(args, model, tiles, weight, out)
            row.setdefault("device", args.device)
            rows.append(row)
            print(json.dumps({k: row.get(k) for k in ("device", "model", "weight", "tiles", "parcels",
                                                        "seconds_per_parcel_step", "bytes_per_particle",
                                                        "launches_per_step", "device_reads_per_step", "error",
                                                        "process_s")}), flush=True)
            if "error" in row or row["process_s"] > args.budget:
                break
            write(path, rows)
    write(path, rows)
    plot(rows, out / "bench_scale.png", "Periodic riser: parcel-steps per second against size")
    failed = [r for r in rows if "error" in r and r.get("device") == args.device]
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

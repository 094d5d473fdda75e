"""The summary of ``scripts/gpu_check_cells.sh``: one JSON object on stdout from the steps' files in OUT.

    python scripts/gpu_check_cells.py OUT

- ``steps``: each step's exit code and seconds (steps.tsv);
- ``device`` / ``kernel_load_s`` / ``tests``: what ran the check, the compilation, the tests' counts;
- ``cooling``: per weight the collision frequency / Enskog and the cooling rate / Haff (each with its standard error),
  the momentum drift and the wall clock;
- ``determinism``: the weight-8 box run twice with one seed — the Theta(t) series, the collision count and every
  strategy counter compared for equality;
- ``box``: the particle-dominated box, wall clock per simulated second of the DEM and of HELSCM at each weight and
  their ratio (target >= 100);
- ``rig``: ``scripts/bench_rig.py``'s DEM / HELSCM ratios at weights 1, 8, 64;
- ``profile``: ``scripts/profile_step.py``'s box (per weight) and rig step: wall clock, device busy time, read-backs.

Exit code 1 when the determinism comparison fails (or cannot be made because a run is missing), else 0.
"""

from __future__ import annotations

import json
import os
import sys


def _load(out: str, name: str):
    path = os.path.join(out, name)
    try:
        with open(path) as fh:
            return json.load(fh)
    except (OSError, ValueError):
        return None


def _cool_row(doc: dict) -> dict:
    keys = ("collision_frequency_ratio", "collision_frequency_ratio_stderr", "cooling_rate_ratio",
            "cooling_rate_ratio_stderr", "collisions", "momentum_drift", "wall_clock_s", "wall_clock_per_step_s",
            "parcels", "particles_per_parcel", "device", "check_errors")
    return {k: doc.get(k) for k in keys}


def summarise(out: str) -> tuple[dict, bool]:
    doc: dict = {"steps": {}}
    try:
        with open(os.path.join(out, "steps.tsv")) as fh:
            for line in fh:
                name, rc, seconds = line.rstrip("\n").split("\t")[:3]
                doc["steps"][name] = {"rc": int(rc), "seconds": float(seconds)}
    except OSError:
        pass
    dev = _load(out, "device.json") or {}
    doc["device"] = {k: dev.get(k) for k in ("device", "name", "is_cuda", "warp", "driver", "nvidia_smi") if k in dev}
    kern = _load(out, "kernels.json") or {}
    doc["kernel_load_s"] = kern.get("kernel_load_s")
    tests = _load(out, "tests.json") or {}
    doc["tests"] = {k: v for k, v in tests.items() if not isinstance(v, (dict, list))}
    if isinstance(tests.get("failures"), list):
        doc["tests"]["failures"] = tests["failures"]

    doc["cooling"] = {}
    for w in (1, 8, 64):
        run = _load(out, f"cool_w{w}.json")
        if run:
            doc["cooling"][f"w{w}"] = _cool_row(run)

    a, b = _load(out, "cool_w8.json"), _load(out, "cool_w8_again.json")
    ok = False
    if a and b:
        same_theta = a.get("granular_temperature") == b.get("granular_temperature")
        same_count = a.get("collisions") == b.get("collisions")
        same_counters = a.get("strategy_counts") == b.get("strategy_counts")
        ok = bool(same_theta and same_count and same_counters)
        doc["determinism"] = {"identical": ok, "theta_series": same_theta, "collisions": [a.get("collisions"),
                              b.get("collisions")], "strategy_counts": same_counters}
    else:
        doc["determinism"] = {"identical": None, "reason": "a weight-8 cooling run is missing"}

    box = {}
    dem = _load(out, "box_dem.json")
    dem_rate = dem["wall_clock_s"] / dem["end_time"] if dem and dem.get("end_time") else None
    if dem:
        box["dem"] = {"wall_clock_s": dem.get("wall_clock_s"), "simulated_s": dem.get("end_time"),
                      "wall_per_simulated_s": dem_rate,
                      "collision_frequency_ratio": dem.get("collision_frequency_ratio")}
    for w in (1, 8, 64):
        run = _load(out, f"box_w{w}.json")
        if not run:
            continue
        rate = run["wall_clock_s"] / run["end_time"]
        row = _cool_row(run)
        row["wall_per_simulated_s"] = rate
        if dem_rate:
            row["dem_over_helscm"] = dem_rate / rate
        box[f"w{w}"] = row
    doc["box"] = box

    rig = _load(out, "rig_bench.json")
    if rig:
        doc["rig"] = {k: rig.get(k) for k in ("device", "end_time", "dt", "ratios")}
        doc["rig"]["models"] = [{k: row.get(k) for k in ("model", "steps", "total_s", "median_step_s", "parcels",
                                                          "phase_median_s")} for row in rig.get("models") or []]
    doc["profile"] = {}
    for case in ("box", "rig", "rig_loop"):
        prof = _load(out, f"profile_{case}.json")
        if prof:
            doc["profile"][case] = [{k: run.get(k) for k in ("weight", "model", "linear_solver", "pcg_loop",
                                                              "median_step_s", "median_busy_s",
                                                              "d2h_copies_per_step")}
                                    for run in prof.get("runs") or []]
    return doc, ok


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv in (["-h"], ["--help"]):
        print(__doc__)
        return 0
    if len(argv) != 1 or argv[0].startswith("-"):
        print("usage: python scripts/gpu_check_cells.py OUT", file=sys.stderr)
        return 2
    if not os.path.isdir(argv[0]):
        print(f"gpu_check_cells: error: {argv[0]} is not a directory; give the --out of scripts/gpu_check_cells.sh",
              file=sys.stderr)
        return 2
    doc, ok = summarise(argv[0])
    print(json.dumps(doc, indent=1))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

"""The steps of ``scripts/gpu_check.sh`` written in Python: the device report, the kernel compilation, test and rig
summaries, the final ``summary.json`` — each writes one JSON file.

    python scripts/gpu_check.py device --device cuda --out OUT/device.json
    python scripts/gpu_check.py kernels --device cuda --out OUT/kernels.json
    python scripts/gpu_check.py models OUT/models --out OUT/models.json
    python scripts/gpu_check.py junit OUT/tests.xml --out OUT/tests.json
    python scripts/gpu_check.py rig OUT/rig_ktgf --out OUT/rig_ktgf.json
    python scripts/gpu_check.py summary OUT
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))


def _write(path: str, doc: dict) -> None:
    with open(path, "w") as fh:
        json.dump(doc, fh, indent=1)
    print(json.dumps({k: v for k, v in doc.items() if not isinstance(v, (dict, list))}))


def device_report(device: str) -> dict:
    """What ran the check: Warp's device (name, architecture, memory), the driver, XGBoost's CUDA build."""
    from hel_warp._warp import init_warp

    import warp as wp
    import xgboost as xgb

    dev = init_warp(device)
    doc = {"requested": device, "device": str(dev), "name": dev.name, "is_cuda": bool(dev.is_cuda),
           "warp": wp.__version__, "python": platform.python_version(), "platform": platform.platform(),
           "cpu_count": os.cpu_count(), "xgboost": xgb.__version__,
           "xgboost_cuda_build": bool(xgb.build_info().get("USE_CUDA", False)),
           "cuda_available": bool(wp.is_cuda_available()), "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    if dev.is_cuda:
        doc.update(arch=int(dev.arch), sm_count=int(dev.sm_count), memory_gib=round(dev.total_memory / 2**30, 2),
                   driver=".".join(map(str, wp.get_cuda_driver_version() or ())),
                   toolkit=".".join(map(str, wp.get_cuda_toolkit_version() or ())),
                   conditional_graph_nodes=bool(wp.is_conditional_graph_supported()))
    if shutil.which("nvidia-smi"):
        smi = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total,mig.mode.current",
                              "--format=csv,noheader"], capture_output=True, text=True)
        doc["nvidia_smi"] = smi.stdout.strip() or smi.stderr.strip()
    return doc


def kernel_report(device: str) -> dict:
    """Compile (or load from Warp's cache) every kernel module of the engine on ``device``, one worker thread per
    core: on a fresh machine this is the compiler's first contact with the code, and the later steps then time the
    work, not the compiler. On CUDA the CPU variants follow (the tests and the training also run CPU kernels),
    unless HEL_GPU_CHECK_CPU_KERNELS=0 (they then compile at first use)."""
    import importlib

    from hel_warp._warp import init_warp
    from hel_warp.runs.run import load_kernels

    import warp as wp

    dev = init_warp(device)
    wp.config.load_module_max_workers = os.cpu_count() or 1
    for name in ("hel_warp.collisions.dem", "hel_warp.gas.solver", "hel_warp.gas.multigrid", "hel_warp.collisions.forest", "hel_warp.collisions.models",
                 "hel_warp.collisions.cells", "hel_warp.collisions.cfd_dem", "hel_warp.hel", "hel_warp.collisions.impact"):
        try:
            importlib.import_module(name)
        except ModuleNotFoundError as exc:  # a module renamed or moved: its kernels still load at first use
            if exc.name != name:
                raise
    doc = {"device": str(dev), "kernel_load_s": load_kernels(dev), "workers": wp.config.load_module_max_workers,
           "kernel_cache": wp.config.kernel_cache_dir}
    if dev.is_cuda and os.environ.get("HEL_GPU_CHECK_CPU_KERNELS", "1") != "0":
        doc["cpu_kernel_load_s"] = load_kernels(wp.get_device("cpu"))
    return doc


def models_report(root: str) -> dict:
    """The tests' tiny contact- and paper-form models (tests/test_collision_models.py ``train_tiny_models``: 3000
    frictionless DEM impacts, one Optuna trial of 100-150 trees), trained once into ``root`` for the tests
    (HEL_WARP_TINY_MODELS) and the rig runs."""
    from pathlib import Path

    from hel_warp._warp import init_warp

    init_warp()
    from tests.test_collision_models import train_tiny_models

    start = time.perf_counter()
    dirs = train_tiny_models(Path(root))
    doc = {"models": dirs, "seconds": time.perf_counter() - start}
    for form, path in dirs.items():
        with open(os.path.join(path, "metadata.json")) as fh:
            meta = json.load(fh)
        doc[f"{form}_test_mae"] = meta.get("metrics", {}).get("mae")
    return doc


def junit_report(path: str) -> dict:
    """Counts and the slowest tests of a pytest ``--junitxml`` file."""
    import xml.etree.ElementTree as ET

    root = ET.parse(path).getroot()
    suites = [root] if root.tag == "testsuite" else list(root.iter("testsuite"))
    doc = {key: sum(int(s.get(key, 0)) for s in suites) for key in ("tests", "failures", "errors", "skipped")}
    doc["time_s"] = sum(float(s.get("time", 0.0)) for s in suites)
    cases = [(float(c.get("time", 0.0)), f"{c.get('classname')}::{c.get('name')}") for c in root.iter("testcase")]
    doc["slowest"] = [{"test": name, "s": round(t, 3)} for t, name in sorted(cases, reverse=True)[:10]]
    doc["failed"] = [f"{c.get('classname')}::{c.get('name')}" for c in root.iter("testcase")
                     if c.find("failure") is not None or c.find("error") is not None]
    return doc


def rig_report(run_dir: str) -> dict:
    """A rig run's summary (``run.zarr`` attrs) with the median wall time of each sub-step over its steps, the
    collision path it took (``detection``, ``wall_contact``, ``particles_per_parcel``) and the
    totals over its steps of the collisions, rounds and in-step wall events (so the figures show that the rounds
    ran on the device, not only that the run ended)."""
    import numpy as np
    import zarr

    group = zarr.open_group(os.path.join(run_dir, "run.zarr"), mode="r")
    attrs = dict(group.attrs)
    summary = dict(attrs.get("summary", {}))
    series = group["series"]
    timings = {}
    for key in sorted(series.keys()):
        if key.startswith("timing_"):
            values = np.asarray(series[key][:], dtype=float)
            if values.size:
                timings[key[len("timing_"):]] = {"median_s": float(np.median(values)), "max_s": float(values.max())}
    case = attrs.get("config", {}).get("case", {})
    totals = {}
    for key in ("collisions_collisions", "collisions_rounds", "collisions_wall_events", "wall_hits"):
        if key in series:
            totals[key] = int(np.asarray(series[key][:], dtype=np.int64).sum())
    path = {key: case.get(key) for key in ("detection", "wall_contact", "particles_per_parcel")}
    return {"run": run_dir, "collisions": summary.get("collisions"), "device": case.get("device"), **path,
            "totals": totals,
            "grid_cells": case.get("grid_cells"), "fluid_cells": case.get("fluid_cells"),
            "particles": case.get("particles"), "steps": summary.get("steps"),
            "median_step_s": timings.get("step", {}).get("median_s"), "sub_steps": timings, "summary": summary}


def summary_report(out: str) -> dict:
    """``steps.tsv`` (written by gpu_check.sh: name, exit code, seconds, command) and every JSON figure beside it."""
    steps = []
    path = os.path.join(out, "steps.tsv")
    if os.path.exists(path):
        with open(path) as fh:
            for line in fh:
                name, rc, seconds, command = line.rstrip("\n").split("\t", 3)
                steps.append({"step": name, "rc": int(rc), "seconds": float(seconds), "command": command})
    figures = {}
    ran = {s["step"] for s in steps} | {s["step"][:-len("_json")] for s in steps if s["step"].endswith("_json")}
    for name in sorted(ran):  # only this run's figures, not a previous run's left in the folder
        path = os.path.join(out, f"{name}.json")
        if not os.path.exists(path):
            continue
        try:
            with open(path) as fh:
                figures[name] = json.load(fh)
        except (OSError, ValueError) as exc:
            figures[name] = {"unreadable": str(exc)}
    failed = [s for s in steps if s["rc"] != 0]
    return {"passed": bool(steps) and not failed, "failed_step": failed[0] if failed else None,
            "wall_s": sum(s["seconds"] for s in steps), "steps": steps, "figures": figures}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    for what in ("device", "kernels"):
        p = sub.add_parser(what)
        p.add_argument("--device", required=True)
        p.add_argument("--out", required=True)
    p = sub.add_parser("models")
    p.add_argument("root")
    p.add_argument("--out", required=True)
    p = sub.add_parser("junit")
    p.add_argument("xml")
    p.add_argument("--out", required=True)
    p = sub.add_parser("rig")
    p.add_argument("run_dir")
    p.add_argument("--out", required=True)
    p = sub.add_parser("summary")
    p.add_argument("out_dir")
    args = parser.parse_args(argv)
    if args.what == "device":
        _write(args.out, device_report(args.device))
    elif args.what == "kernels":
        _write(args.out, kernel_report(args.device))
    elif args.what == "models":
        _write(args.out, models_report(args.root))
    elif args.what == "junit":
        doc = junit_report(args.xml)
        _write(args.out, doc)
        return 0 if doc["tests"] > 0 and not doc["failed"] else 1
    elif args.what == "rig":
        doc = rig_report(args.run_dir)
        _write(args.out, doc)
        return 0 if doc["summary"].get("status") == "complete" and not doc["summary"].get("check_errors") else 1
    else:
        doc = summary_report(args.out_dir)
        with open(os.path.join(args.out_dir, "summary.json"), "w") as fh:
            json.dump(doc, fh, indent=1)
        return 0 if doc["passed"] else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

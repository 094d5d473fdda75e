"""scripts/gpu_check.sh: the prepared GPU run, here as its ``--dry-run`` on the CPU.

The dry run is the same sequence as the GPU run (device report, kernel compilation, the device-agnostic tests on
the device, the DEM / forest / HEL benches, the rig for ktgf, surrogate and dem) at the smallest sizes; this test is
what keeps it runnable between GPU loans. Measured 165–300 s on the 2 shared cores at a load of 7–11 (warm kernel
cache; not measured on idle cores).
"""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from tests.test_collision_models import trained_models  # noqa: F401  (fixture)

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "gpu_check.sh"


def _env(env=None) -> dict:
    """The environment of a check: this interpreter as its PYTHON (the project's, whatever the PATH holds: `make
    test` runs the suite with .venv/bin/python without putting .venv/bin on the PATH), then ``env``."""
    return {**os.environ, "PYTHON": sys.executable, **(env or {})}


def _run(*args, env=None, timeout=900):
    return subprocess.run([str(SCRIPT), *args], capture_output=True, text=True, cwd=ROOT, timeout=timeout,
                          env=_env(env))


def test_dry_run_passes_and_writes_every_figure_as_json(tmp_path, trained_models):
    out = tmp_path / "gpu_out"
    models = str(Path(trained_models["contact"]).parent)  # the test run's tiny models: not trained twice
    done = _run("--dry-run", "--out", str(out), env={"HEL_WARP_TINY_MODELS": models})
    assert done.returncode == 0, done.stderr[-3000:] + done.stdout[-3000:]
    assert "every step passed on cpu" in done.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["passed"] and summary["failed_step"] is None
    names = [s["step"] for s in summary["steps"]]
    assert names == ["device", "kernels", "models", "tests", "tests_json", "bench_dem", "bench_forest", "bench_hel",
                     "rig_ktgf", "rig_ktgf_json", "rig_surrogate", "rig_surrogate_json", "rig_dem", "rig_dem_json",
                     "rig_surrogate_cell", "rig_surrogate_cell_json", "bench_scale"]
    fig = summary["figures"]
    assert [(r["model"], r["tiles"]) for r in fig["bench_scale"]["runs"]] == [("ktgf", 0)]
    assert fig["device"]["device"] == "cpu" and fig["kernels"]["kernel_load_s"] >= 0
    assert fig["tests"]["tests"] >= 10 and fig["tests"]["failures"] == fig["tests"]["errors"] == 0
    assert any("test_device_paths" in s["test"] for s in fig["tests"]["slowest"])
    assert fig["bench_dem"]["sweep"] and fig["bench_dem"]["sweep"][0]["ours"]["rate"] > 0
    forest = fig["bench_forest"]
    assert forest["max_abs_diff_vs_xgboost"] <= 1e-5 and forest["xgboost_device_requested"] == "cpu"
    assert forest["xgboost_device_used"] == "cpu" and forest["warp_kernel_samples_per_s"] > 0
    assert fig["bench_hel"]["gas"] and fig["bench_hel"]["gas"][0]["per_cell_us"] > 0
    for run, model in (("ktgf", "ktgf"), ("surrogate", "surrogate"), ("dem", "dem"), ("surrogate_cell", "surrogate")):
        rig = fig[f"rig_{run}"]
        assert rig["collisions"] == model and rig["device"] == "cpu" and rig["summary"]["status"] == "complete"
        assert rig["steps"] == 2 and rig["median_step_s"] > 0 and not rig["summary"]["check_errors"]
    # the rig's surrogate paths: swept with in-step wall events at weight 1, cell detection at 8 per parcel
    swept, cell = fig["rig_surrogate"], fig["rig_surrogate_cell"]
    assert swept["detection"] == "swept" and swept["particles_per_parcel"] == 1
    assert cell["detection"] == "cell" and cell["particles_per_parcel"] == 8
    assert swept["totals"]["collisions_rounds"] > 0 and cell["totals"]["collisions_rounds"] > 0
    assert swept["totals"]["collisions_wall_events"] > 0  # walls met inside the swept rounds, not at the step end


def test_the_first_failing_step_stops_the_check_and_is_named(tmp_path):
    # a python that fails the kernel step (exit 3) and runs everything else: the check stops there, names the
    # command, writes the summary up to it and exits 1
    fake = tmp_path / "python"
    fake.write_text(f'#!/usr/bin/env bash\nif [ "$2" = kernels ]; then exit 3; fi\nexec {sys.executable} "$@"\n')
    fake.chmod(fake.stat().st_mode | stat.S_IEXEC)
    out = tmp_path / "gpu_out"
    done = _run("--dry-run", "--out", str(out), env={"PYTHON": str(fake)}, timeout=300)
    assert done.returncode == 1
    assert f"FAILED at step 'kernels' (exit 3): {fake} scripts/gpu_check.py kernels --device cpu" in done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert not summary["passed"] and summary["failed_step"]["step"] == "kernels"
    assert [s["step"] for s in summary["steps"]] == ["device", "kernels"] and not (out / "tests.json").exists()


def test_usage_errors_exit_2(tmp_path):
    bad = _run("--out", str(tmp_path / "x"), "--bogus", timeout=60)
    assert bad.returncode == 2 and "usage: scripts/gpu_check.sh [--dry-run] [--out DIR]" in bad.stderr
    missing = _run("--out", timeout=60)
    assert missing.returncode == 2 and "--out needs a directory" in missing.stderr


def test_a_spent_time_budget_stops_the_check_at_the_next_step(tmp_path):
    # TOTAL_TIMEOUT caps the whole check (a lent GPU has ~15 minutes in all): with none left the next step is not
    # started, and the check fails there naming it
    out = tmp_path / "gpu_out"
    done = _run("--dry-run", "--out", str(out), env={"TOTAL_TIMEOUT": "0"}, timeout=120)
    assert done.returncode == 1
    assert "step 'device' ran out of time" in done.stderr and "FAILED at step 'device' (exit 124)" in done.stderr


def test_a_step_past_its_time_cap_is_killed_and_named(tmp_path):
    # STEP_TIMEOUT caps every step (the GPU run's 8 minutes hold by construction): a device step that would sleep
    # 60 s is stopped at 2 s (timeout's exit 124), the check fails there, names it and ends well before the sleep
    import time

    fake = tmp_path / "python"
    fake.write_text(f'#!/usr/bin/env bash\nif [ "$2" = device ]; then sleep 60; fi\nexec {sys.executable} "$@"\n')
    fake.chmod(fake.stat().st_mode | stat.S_IEXEC)
    out = tmp_path / "gpu_out"
    start = time.monotonic()
    done = _run("--dry-run", "--out", str(out), env={"PYTHON": str(fake), "STEP_TIMEOUT": "2"}, timeout=120)
    wall = time.monotonic() - start
    assert done.returncode == 1 and wall < 30, (done.returncode, wall)
    assert "step 'device' ran out of time" in done.stderr and "FAILED at step 'device' (exit 124)" in done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert [s["step"] for s in summary["steps"]] == ["device"] and summary["steps"][0]["seconds"] < 15


def test_the_gpu_run_without_a_gpu_stops_at_its_first_step(tmp_path):
    # The real (non-dry) sequence asks Warp for "cuda" first: where there is none (this machine) the check stops at
    # the device step, names its command and exits 1 without running anything else
    import warp as wp

    if wp.is_cuda_available():
        pytest.skip("a GPU is present: the real run is scripts/gpu_check.sh itself")
    out = tmp_path / "gpu_out"
    done = _run("--out", str(out), timeout=120)
    assert done.returncode == 1
    assert "FAILED at step 'device' (exit" in done.stderr and "gpu_check.py device --device cuda" in done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert [s["step"] for s in summary["steps"]] == ["device"] and not summary["passed"]


# ------------------------------------------------------------------ scripts/gpu_check_cells.sh (cell detection on a GPU)
CELLS = ROOT / "scripts" / "gpu_check_cells.sh"


def _run_cells(*args, env=None, timeout=900):
    return subprocess.run([str(CELLS), *args], capture_output=True, text=True, cwd=ROOT, timeout=timeout,
                          env=_env(env))


def test_cells_check_dry_run_writes_the_physics_and_goes_on_past_a_failed_step(tmp_path, trained_models):
    """The cell-detection GPU check as its ``--dry-run`` on the CPU, with its kernel step made to fail (exit 3):
    one short GPU run must name every failure, so the failure is recorded, every other step still runs and passes,
    the exit is 1; the weight-8 box run twice with one seed is identical (Theta series, counts), every cooling row
    and ratio is there. (One run for both: the dry run is the costliest test of the suite.)"""
    fake = tmp_path / "python"
    fake.write_text(f'#!/usr/bin/env bash\nif [ "$2" = kernels ]; then exit 3; fi\nexec {sys.executable} "$@"\n')
    fake.chmod(fake.stat().st_mode | stat.S_IEXEC)
    out = tmp_path / "cells_out"
    models = str(Path(trained_models["contact"]).parent)
    done = _run_cells("--dry-run", "--out", str(out), env={"PYTHON": str(fake), "HEL_WARP_TINY_MODELS": models})
    assert done.returncode == 1, done.stderr[-3000:] + done.stdout[-3000:]
    assert "step 'kernels' failed (exit 3)" in done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary["steps"]) == ["device", "kernels", "tests", "tests_json", "cool_w1", "cool_w8", "cool_w64",
                                      "cool_w8_again", "box_dem", "box_w1", "box_w8", "box_w64", "rig_bench",
                                      "profile_box", "profile_rig", "profile_rig_loop"]
    assert {name: step["rc"] for name, step in summary["steps"].items() if step["rc"] != 0} == {"kernels": 3}
    assert summary["determinism"]["identical"] is True
    assert summary["tests"]["tests"] >= 1 and summary["tests"]["failures"] == 0
    for w in ("w1", "w8", "w64"):
        row = summary["cooling"][w]
        assert row["device"] == "cpu" and row["collisions"] > 0 and row["collision_frequency_ratio"] > 0
        assert summary["box"][w]["dem_over_helscm"] > 0
    assert set(summary["rig"]["ratios"]) >= {"dem_over_helscm_w1", "dem_over_helscm_w8", "dem_over_helscm_w64"}
    assert [r["weight"] for r in summary["profile"]["box"]] == [1.0, 8.0, 64.0]
    assert all(r["median_step_s"] > 0 for r in summary["profile"]["box"] + summary["profile"]["rig"])
    assert [r["pcg_loop"] for r in summary["profile"]["rig_loop"]] == ["host", "device"]
    assert (tmp_path / "cells_out.tgz").stat().st_size > 0  # everything in one archive


def test_cells_check_usage_errors_exit_2(tmp_path):
    bad = _run_cells("--out", str(tmp_path / "x"), "--bogus", timeout=60)
    assert bad.returncode == 2 and "usage: scripts/gpu_check_cells.sh [--dry-run] [--out DIR]" in bad.stderr


def test_profile_step_runs_both_cases_on_the_cpu_and_reports_every_run(trained_models, capsys):
    """``scripts/profile_step.py`` (the GPU profile of a box and a rig step) on the CPU at smoke sizes: one run per
    weight and per (model, linear solver), each with its step's wall clock; the CPU records no device activity."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    import profile_step

    model = trained_models["contact"]
    assert profile_step.main(["box", "--model", model, "--particles", "1024", "--weights", "1", "8", "--warmup", "1",
                              "--steps", "2", "--json"]) == 0
    box = json.loads(capsys.readouterr().out)
    assert [r["weight"] for r in box["runs"]] == [1.0, 8.0]
    assert all(r["median_step_s"] > 0 and r["activities_per_step"] == 0 for r in box["runs"])
    assert profile_step.main(["rig", "--model", model, "--models", "surrogate_w8", "--linear-solver", "native", "warp",
                              "--cells", "3000", "--max-particles", "96", "--release-steps", "1", "--warmup", "1",
                              "--steps", "1", "--json"]) == 0
    rig = json.loads(capsys.readouterr().out)
    assert [(r["model"], r["linear_solver"]) for r in rig["runs"]] == [("surrogate_w8", "native"),
                                                                        ("surrogate_w8", "warp")]
    assert profile_step.main(["rig", "--model", model, "--models", "ktgf", "--pcg-loop", "host", "device",
                              "--cells", "3000", "--max-particles", "96", "--release-steps", "1", "--warmup", "1",
                              "--steps", "1", "--json"]) == 0
    loops = json.loads(capsys.readouterr().out)
    assert [r["pcg_loop"] for r in loops["runs"]] == ["host", "device"]
    assert all(r["median_step_s"] > 0 for r in loops["runs"])
    assert all(r["median_step_s"] > 0 for r in rig["runs"])


def test_profile_step_bad_input_is_one_line_and_exit_2(tmp_path):
    """``scripts/profile_step.py``: a missing model directory, no steps to time, or a device that is not there: one
    line naming what to change, exit 2."""
    script = str(Path(__file__).resolve().parents[1] / "scripts" / "profile_step.py")
    model = tmp_path / "model"
    model.mkdir()
    for args, says in ((["box", "--model", str(tmp_path / "none")], "no such directory"),
                       (["box", "--model", str(model), "--steps", "0"], "--steps >= 1"),
                       (["box", "--model", str(model), "--device", "nonesuch"], "error")):
        done = subprocess.run([sys.executable, script, *args], capture_output=True, text=True, timeout=300)
        assert done.returncode == 2, (args, done.stderr[-1500:])
        assert says in done.stderr and "Traceback" not in done.stderr



@pytest.mark.parametrize("script", [SCRIPT, ROOT / "scripts" / "gpu_check_cells.sh"], ids=["gpu_check", "cells"])
def test_a_python_without_pytest_is_one_line_saying_what_to_install(tmp_path, script):
    # the check runs the test subset with pytest (a test extra): a python without it is refused before any step runs,
    # in one line that names the install command, exit 2 and nothing written (not a traceback minutes later)
    shadow = tmp_path / "no_pytest" / "pytest"
    shadow.mkdir(parents=True)
    (shadow / "__init__.py").write_text('raise ModuleNotFoundError("No module named \'pytest\'", name="pytest")\n')
    out = tmp_path / "gpu_out"
    done = subprocess.run([str(script), "--dry-run", "--out", str(out)], capture_output=True, text=True, cwd=ROOT,
                          timeout=300, env={**os.environ, "PYTHON": sys.executable,
                                            "PYTHONPATH": str(shadow.parent)})
    assert done.returncode == 2, done.stderr[-2000:]
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "pytest" in lines[0] and "pip install" in lines[0] and ".[test]" in lines[0], lines
    assert "Traceback" not in done.stderr and done.stdout == "" and not out.exists()

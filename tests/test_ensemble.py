"""hel-warp ensemble (hel_warp/studies/ensemble.py) on a local Dask cluster of two workers, with a tiny pure-Python case.

The case (tests/data/ensemble_toy_case.py) is a random walk whose steps are drawn from a generator seeded by
(seed, step), so the test recomputes every member's result on its own (``walk``): the ensemble's means and errors are
checked against that and against the closed-form standard error of the mean, not against numbers of the code.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hel_warp.studies import ensemble as ens
from hel_warp.cli import main
from hel_warp.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
TOY = str(ROOT / "tests" / "data" / "ensemble_toy_case.py")


def walk(seed: int, steps: int = 3, scale: float = 1.0, offset: float = 0.0) -> float:
    """The toy case's final position, computed here independently of the case and the ensemble."""
    return offset + scale * sum(float(np.random.default_rng([seed, k]).normal()) for k in range(steps))


def ensemble(capsys, *argv) -> tuple[int, dict | None, str]:
    """Run ``hel-warp ensemble`` in this process: (exit code, the --json object or None, stderr)."""
    code = main(["ensemble", *argv])
    captured = capsys.readouterr()
    lines = [ln for ln in captured.out.splitlines() if ln.strip()]
    obj = json.loads(lines[-1]) if "--json" in argv and lines else None
    return code, obj, captured.err


def combo(result: dict, name: str) -> dict:
    (c,) = [c for c in result["combinations"] if c["name"] == name]
    return c


# ------------------------------------------------------------------------------------------------ pure functions
def test_seeds_sets_and_folder_names():
    assert ens.parse_seeds("0-3") == [0, 1, 2, 3]
    assert ens.parse_seeds("7") == [7]
    assert ens.parse_seeds("0-2,10,12-13") == [0, 1, 2, 10, 12, 13]
    for bad in ("3-1", "a", "1,1", "0-3,2", "-1", ""):
        with pytest.raises(ConfigError):
            ens.parse_seeds(bad)
    sets = ens.parse_sets(["dt=1e-3,1e-4", "model=/work/models/a b"])
    assert sets == [("dt", ("1e-3", "1e-4")), ("model", ("/work/models/a b",))]
    for bad in (["dt"], ["--dt=1"], ["dt=1,,2"], ["dt=1,1"], ["dt=1", "dt=2"]):
        with pytest.raises(ConfigError):
            ens.parse_sets(bad)
    # the product, the first --set outermost, the seeds innermost; the member's options and folder
    members = ens.plan([0, 5], ens.parse_sets(["dt=1e-3,1e-4", "v=2,3"]))
    assert [m.name for m in members] == [
        "dt=1e-3_v=2_seed0", "dt=1e-3_v=2_seed5", "dt=1e-3_v=3_seed0", "dt=1e-3_v=3_seed5",
        "dt=1e-4_v=2_seed0", "dt=1e-4_v=2_seed5", "dt=1e-4_v=3_seed0", "dt=1e-4_v=3_seed5"]
    assert members[3].case_options() == ["--dt", "1e-3", "--v", "3", "--seed", "5"]
    assert [m.name for m in ens.plan([1], [])] == ["seed1"]
    assert ens.plan([0], sets)[0].name == "dt=1e-3_model=_work_models_a_b_seed0"
    with pytest.raises(ConfigError, match="share the folder name"):
        ens.plan([0], ens.parse_sets(["model=a/b,a_b"]))


def test_jackknife_error_of_a_mean_is_the_standard_error_of_the_mean():
    # for the mean, the jackknife is exactly s / sqrt(n) with s the sample standard deviation (closed form)
    rng = np.random.default_rng(3)
    for n in (2, 3, 9, 50):
        x = rng.normal(1.5, 2.0, size=n)
        mean, se = ens.jackknife_mean(x)
        assert mean == pytest.approx(float(np.mean(x)), rel=1e-12)
        assert se == pytest.approx(float(np.std(x, ddof=1)) / math.sqrt(n), rel=1e-10)
    assert ens.jackknife_mean([4.0]) == (4.0, None)
    assert ens.jackknife_mean([2.0, 2.0, 2.0])[1] == 0.0


def test_scalar_metrics_of_a_summary():
    summary = {"seed": 4, "a": 1, "b": 2.5, "flag": True, "name": "x", "none": None, "nan": float("nan"),
               "nested": {"c": 3, "d": {"e": -1.0}, "seed": 9}, "short": [1.0, 2.0], "long": list(range(100)),
               "rows": [{"v": 1.0}, {"v": 2.0}], "wall_clock_s": 3.0, "kernel_load_s": 9.0,
               "setup_wall_clock_s": 1.0, "parcel_steps_per_second": 5e5, "wall_events": 7}
    assert ens.scalar_metrics(summary) == {
        "a": 1.0, "b": 2.5, "nested.c": 3.0, "nested.d.e": -1.0, "nested.seed": 9.0, "short[0]": 1.0,
        "short[1]": 2.0, "rows[0].v": 1.0, "rows[1].v": 2.0, "wall_events": 7.0}


# ------------------------------------------------------------------------------------------------ the ensemble
def test_product_on_two_workers_with_a_failed_member(tmp_path, capsys):
    out = tmp_path / "ens"
    code, res, err = ensemble(capsys, TOY, "--seeds", "0-3", "--set", "scale=1,2", "--out", str(out), "--workers",
                              "2", "--json", "--no-progress", "--", "--steps", "3", "--fail-seed", "2",
                              "--check-fail-seed", "3")
    assert code == 1  # some members not ok
    names = [f"scale={s}_seed{k}" for s in (1, 2) for k in range(4)]
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == sorted(names + ["logs"])
    status = {e["name"]: (e["status"], e["error"]) for e in res["members"]}
    for s in (1, 2):  # the failed member's one line; the others finished
        assert status[f"scale={s}_seed2"] == ("failed", "toy: error: seed 2 refused on purpose")
        assert status[f"scale={s}_seed3"] == ("check failed", "toy: check failed: x out of range on purpose")
        assert status[f"scale={s}_seed0"] == status[f"scale={s}_seed1"] == ("ok", None)
    assert "failed: scale=1_seed2: toy: error: seed 2 refused on purpose" in err
    assert sorted(res["run"]["ran"]) == sorted(names) and res["run"]["skipped"] == 0
    # each member ran with its own options (the record's command) into its own folder
    record = json.loads((out / "scale=2_seed1" / ens.MEMBER_RECORD).read_text())
    assert record["command"].endswith(f"--steps 3 --fail-seed 2 --check-fail-seed 3 --scale 2 --seed 1 --out "
                                      f"{out / 'scale=2_seed1'} --json --no-progress")
    # the statistics over the ok members (seeds 0, 1) against the walk recomputed here
    for s in (1, 2):
        x = [walk(k, 3, s) for k in (0, 1)]
        m = combo(res, f"scale={s}")["metrics"]
        assert m["x"]["n"] == 2 and m["x"]["mean"] == pytest.approx(np.mean(x), rel=1e-12)
        assert m["x"]["stderr"] == pytest.approx(np.std(x, ddof=1) / math.sqrt(2), rel=1e-10)
        assert m["x2"]["mean"] == pytest.approx(np.mean(np.square(x)), rel=1e-12)
        assert m["nested.half"]["mean"] == pytest.approx(0.5 * np.mean(x), rel=1e-12)
        assert m["short[1]"]["mean"] == pytest.approx(2 * np.mean(x), rel=1e-12)
        assert m["steps"] == {"n": 2, "mean": 3.0, "stderr": 0.0, "varies": False}
        assert not {"seed", "wall_clock_s", "flag", "long[0]"} & set(m)
        assert combo(res, f"scale={s}")["members"] == [f"scale={s}_seed0", f"scale={s}_seed1"]
        # the case's pooled_metrics hook, with the folders of the ok members
        assert combo(res, f"scale={s}")["pooled"]["result"]["metrics"]["sum_x"] == pytest.approx(sum(x), rel=1e-12)
        assert combo(res, f"scale={s}")["pooled"]["result"]["reference_members"] is None
    on_disk = json.loads((out / ens.ENSEMBLE_JSON).read_text())
    assert on_disk == {k: v for k, v in res.items() if k != "run"}
    # the rerun runs the failed members only (a failed check is a finished run); the table names the failures
    code, _, err = ensemble(capsys, TOY, "--seeds", "0-3", "--set", "scale=1,2", "--out", str(out), "--workers",
                            "2", "--no-progress", "--", "--steps", "3", "--fail-seed", "2", "--check-fail-seed", "3")
    assert code == 1
    code, res2, _ = ensemble(capsys, TOY, "--seeds", "0-3", "--set", "scale=1,2", "--out", str(out), "--json",
                             "--no-progress", "--", "--steps", "3", "--fail-seed", "2", "--check-fail-seed", "3")
    assert sorted(res2["run"]["ran"]) == ["scale=1_seed2", "scale=2_seed2"] and res2["run"]["skipped"] == 6
    assert {k: v for k, v in res2.items() if k != "run"} == on_disk


def test_printed_table(tmp_path, capsys):
    assert main(["ensemble", TOY, "--seeds", "0-2", "--out", str(tmp_path / "e"), "--workers", "2",
                 "--no-progress", "--", "--steps", "3"]) == 0
    capsys.readouterr()
    assert main(["ensemble", TOY, "--seeds", "0-2", "--out", str(tmp_path / "e"), "--no-progress", "--",
                 "--steps", "3"]) == 0
    out = capsys.readouterr().out
    x = [walk(k) for k in range(3)]
    row = next(ln.split() for ln in out.splitlines() if ln.strip().startswith("x "))
    assert row[:2] == ["x", "3"] and float(row[2]) == pytest.approx(np.mean(x), rel=1e-5)
    assert float(row[3]) == pytest.approx(np.std(x, ddof=1) / math.sqrt(3), rel=1e-2)
    assert "0 members run, 3 already finished" in out
    assert "pooled: sum_x" in out and "metrics the same in every member not shown" in out


def test_reference_difference_and_its_error(tmp_path, capsys):
    ref, run = str(tmp_path / "ref"), str(tmp_path / "run")
    code, r, _ = ensemble(capsys, TOY, "--seeds", "0-4", "--out", ref, "--workers", "2", "--json", "--no-progress",
                          "--", "--steps", "3", "--offset", "1")
    assert code == 0
    code, a, _ = ensemble(capsys, TOY, "--seeds", "0-4", "--set", "scale=1", "--out", run, "--workers", "2",
                          "--reference", ref, "--json", "--no-progress", "--", "--steps", "3")
    assert code == 0
    c = combo(a, "scale=1")
    d = c["vs_reference"]["x"]
    # the same walks, the reference shifted by +1: the difference is -1; independent ensembles add in quadrature
    se = np.std([walk(k) for k in range(5)], ddof=1) / math.sqrt(5)
    assert d["difference"] == pytest.approx(-1.0, abs=1e-12)
    assert d["stderr"] == pytest.approx(math.sqrt(2.0) * se, rel=1e-10)
    assert c["reference"] == "all" and c["pooled"]["result"]["reference_members"] == 5


def test_interrupted_member_resumes_from_its_checkpoint(tmp_path, capsys, monkeypatch):
    out = tmp_path / "ens"
    # seed 1 stopped after 2 of 4 steps: its folder holds a checkpoint and no finished summary
    member = out / "seed1"
    assert subprocess.run([sys.executable, TOY, "--seed", "1", "--out", str(member), "--steps", "2"]).returncode == 0
    (member / "summary.json").unlink()
    code, res, _ = ensemble(capsys, TOY, "--seeds", "0-1", "--out", str(out), "--workers", "2", "--json",
                            "--no-progress", "--", "--steps", "4")
    assert code == 0
    assert json.loads((member / ens.MEMBER_RECORD).read_text())["mode"] == "resume"
    assert (member / "resumed_from.txt").read_text().split() == ["2"]
    assert json.loads((member / "summary.json").read_text())["x"] == pytest.approx(walk(1, 4), rel=1e-12)
    # a case without --resume starts such a folder afresh (--overwrite)
    monkeypatch.setenv("TOY_NO_RESUME", "1")
    out2 = tmp_path / "ens2"
    member = out2 / "seed1"
    assert subprocess.run([sys.executable, TOY, "--seed", "1", "--out", str(member), "--steps", "2"]).returncode == 0
    (member / "summary.json").unlink()
    code, res, _ = ensemble(capsys, TOY, "--seeds", "1", "--out", str(out2), "--workers", "2", "--json",
                            "--no-progress", "--", "--steps", "4")
    assert code == 0
    assert json.loads((member / ens.MEMBER_RECORD).read_text())["mode"] == "overwrite"
    assert not (member / "resumed_from.txt").exists()
    assert combo(res, "all")["metrics"]["x"]["mean"] == pytest.approx(walk(1, 4), rel=1e-12)


def _member_processes(folder: Path) -> list[int]:
    """Processes whose command line names ``folder`` (members left running)."""
    pids = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                if str(folder).encode() in (proc / "cmdline").read_bytes():
                    pids.append(int(proc.name))
            except OSError:
                pass
    return pids


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the members die with the driver on Linux")
def test_driver_killed_half_way_then_rerun(tmp_path, capsys):
    args = ["--seeds", "0-7", "--workers", "2", "--json", "--no-progress", "--", "--steps", "4", "--sleep", "0.1"]
    code, whole, _ = ensemble(capsys, TOY, "--out", str(tmp_path / "whole"), *args)
    assert code == 0
    out = tmp_path / "killed"
    driver = subprocess.Popen([sys.executable, "-m", "hel_warp.cli", "ensemble", TOY, "--out", str(out), *args],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    finished = []
    while time.monotonic() < deadline and driver.poll() is None:
        finished = [p.parent.name for p in out.glob(f"*/{ens.MEMBER_RECORD}")]
        if len(finished) >= 3:
            break
        time.sleep(0.02)
    driver.send_signal(signal.SIGKILL)
    driver.wait()
    assert 3 <= len(finished) < 8, "the driver was not killed half-way"
    time.sleep(0.3)
    assert _member_processes(out) == []  # no member runs on without its driver
    # finished: a member with its record, or one whose run ended (summary.json complete) while the driver was being
    # killed, before the record was written (on loaded cores a member often ends in that window)
    names = [f"seed{k}" for k in range(8)]
    done = {n: {f: (out / n / f).read_bytes() for f in (ens.MEMBER_RECORD, ens.SUMMARY_JSON) if (out / n / f).exists()}
            for n in names if ens.member_state(out / n)[0] == "finished"}
    assert set(finished) <= set(done) and len(done) < 8
    code, res, _ = ensemble(capsys, TOY, "--out", str(out), *args)
    assert code == 0
    # only the unfinished members ran; the finished ones were left as they were
    assert sorted(res["run"]["ran"]) == sorted(set(names) - set(done))
    assert all((out / n / f).read_bytes() == b for n, files in done.items() for f, b in files.items())
    # the result equals the uninterrupted ensemble's
    assert json.loads((out / ens.ENSEMBLE_JSON).read_text()) == json.loads(
        (tmp_path / "whole" / ens.ENSEMBLE_JSON).read_text())
    x = [walk(k, 4) for k in range(8)]
    assert combo(res, "all")["metrics"]["x"]["mean"] == pytest.approx(np.mean(x), rel=1e-12)


def test_a_running_scheduler(tmp_path, capsys):
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        code, res, _ = ensemble(capsys, TOY, "--seeds", "0-3", "--out", str(tmp_path / "e"), "--scheduler",
                                cluster.scheduler_address, "--json", "--no-progress", "--", "--steps", "3")
    assert code == 0
    assert combo(res, "all")["metrics"]["x"]["mean"] == pytest.approx(np.mean([walk(k) for k in range(4)]), rel=1e-12)


def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, monkeypatch):
    out = tmp_path / "e"
    cases = [
        ([TOY, "--seeds", "0-1", "--set", "nope=1,2", "--out", str(out)], "the case script has no option --nope"),
        ([TOY, "--seeds", "0-1", "--out", str(out), "--", "--seed", "3"], "--seed is set by the ensemble"),
        ([TOY, "--seeds", "0-1", "--set", "scale=1", "--out", str(out), "--", "--scale", "2"], "set by the --set"),
        ([TOY, "--seeds", "1-0", "--out", str(out)], "--seeds"),
        ([TOY, "--out", str(out)], "--seeds required"),
        ([TOY, "--seeds", "0", "--out", str(out), "--workers", "2", "--scheduler", "tcp://127.0.0.1:9"],
         "--workers sizes the local cluster"),
        ([TOY, "--seeds", "0", "--out", str(out), "--reference", str(tmp_path)], "no ensemble.json"),
        ([str(tmp_path / "missing.py"), "--seeds", "0", "--out", str(out)], "not found"),
        ([TOY, "--seeds", "0", "--out", str(out), "--steps", "2"], "the case's own options go after --"),
    ]
    for argv, text in cases:
        assert main(["ensemble", *argv]) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "error:" in err[0] and text in err[0], (argv, err)
        assert not out.exists()
    monkeypatch.setattr(ens, "SCHEDULER_TIMEOUT_S", 1)
    assert main(["ensemble", TOY, "--seeds", "0", "--out", str(out), "--scheduler", "tcp://127.0.0.1:9"]) == 2
    assert "cannot reach the Dask scheduler" in capsys.readouterr().err
    # an existing ensemble with other case arguments is not mixed into
    assert main(["ensemble", TOY, "--seeds", "0", "--out", str(out), "--no-progress", "--", "--steps", "2"]) == 0
    capsys.readouterr()
    assert main(["ensemble", TOY, "--seeds", "0-1", "--out", str(out), "--", "--steps", "3"]) == 2
    assert "holds an ensemble of" in capsys.readouterr().err
    # nor run by two drivers at once (the lock a running driver holds)
    import fcntl

    with open(out / ".ensemble.lock", "a+") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        assert main(["ensemble", TOY, "--seeds", "0-1", "--out", str(out), "--", "--steps", "2"]) == 2
        assert "another hel-warp ensemble runs in" in capsys.readouterr().err
    assert not (out / "seed1").exists()

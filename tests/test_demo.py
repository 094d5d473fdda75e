"""The main job (`hel-warp demo`) end to end at a reduced size: every stage runs and the
physical outcomes it reports are the paper's (Fig. 13: ktgf passes, dem and surrogate rebound)."""

import json
from pathlib import Path

from hel_warp.cli import main


def test_demo_reduced_end_to_end(tmp_path, capsys):
    out = tmp_path / "demo"
    code = main(["demo", "--out", str(out), "--samples", "2000", "--trials", "1", "--cells", "5000",
                 "--max-particles", "60", "--end-time", "0.003"])
    assert code == 0
    summary = json.loads((out / "demo_summary.json").read_text())
    assert summary["three_streams"]["dem"] == "rebound"
    assert summary["three_streams"]["surrogate"] == "rebound"
    assert summary["three_streams"]["ktgf"] == "pass-through"
    report = json.loads((out / "report" / "report.json").read_text())
    models = sorted(run["model"] for run in report["runs"])
    # the surrogate run is labelled with its pair detection (swept, the default)
    assert models in (["dem", "dem-no-contacts", "ktgf", "none", "surrogate/swept"],
                      ["dem", "ktgf", "none", "surrogate/swept"])
    for run in report["runs"]:
        assert run["end_time"] > 0 and run["wall_clock_s"] > 0
    # the table per step: one row per model, printed at the end and kept in the summary
    assert [row["model"] for row in summary["summary_table"]] == [r["model"] for r in report["summary_table"]]
    assert sorted(row["model"] for row in summary["summary_table"]) == models
    captured = capsys.readouterr()
    printed = captured.out
    assert "| model | crossing |" in printed.split("Collision models on the rig against dem")[-1]
    # the demo's own model passes the training's guard check (a guard that moves outcomes away from the DEM)
    assert "WARNING" not in printed and "WARNING" not in captured.err
    # only what the report reads is kept of the rig runs: the particle snapshots and series of run.zarr, no VTK,
    # no gas snapshots, no restart checkpoints (the demo reruns with --overwrite, never --resume)
    for run in report["runs"]:
        run_dir = Path(run["run"])
        assert not (run_dir / "vtk").exists() and not list(run_dir.glob("checkpoint*"))
        gas = run_dir / "run.zarr" / "gas"
        assert (run_dir / "run.zarr" / "snapshots").is_dir()
        assert not gas.exists() or [f.name for f in gas.iterdir()] == ["zarr.json"]  # an empty group at most
    # a rerun reuses the cached data set and model (no retraining) and still succeeds
    assert main(["demo", "--out", str(out), "--samples", "2000", "--trials", "1", "--skip-rig"]) == 0

"""The main job (`hel-warp demo`) end to end at a reduced size: every stage runs and the
physical outcomes it reports are the paper's (Fig. 13: ktgf passes, dem and surrogate rebound)."""

import json

from hel_warp.cli import main


def test_demo_reduced_end_to_end(tmp_path):
    out = tmp_path / "demo"
    code = main(["demo", "--out", str(out), "--samples", "2000", "--trials", "1", "--cells", "5000",
                 "--max-particles", "60", "--end-time", "0.003"])
    assert code == 0
    summary = json.loads((out / "demo_summary.json").read_text())
    assert summary["three_streams"]["dem"] == "rebound"
    assert summary["three_streams"]["surrogate"] == "rebound"
    assert summary["three_streams"]["ktgf"] == "pass-through"
    report = json.loads((out / "report" / "report.json").read_text())
    assert sorted(run["collisions"] for run in report["runs"]) == ["dem", "ktgf", "surrogate"]
    for run in report["runs"]:
        assert run["end_time"] > 0 and run["wall_clock_s"] > 0
    # a rerun reuses the cached data set and model (no retraining) and still succeeds
    assert main(["demo", "--out", str(out), "--samples", "2000", "--trials", "1", "--skip-rig"]) == 0

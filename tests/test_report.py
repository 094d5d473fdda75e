"""hel-warp report on hand-made run directories with known particle velocities.

Independent reference: the profiles and the RMS are written out by hand below from the
positions and velocities the test puts into the snapshots (the weighted mean of eq.
u_b = sum w u / sum w, and sqrt(mean of squared differences) over the sub-boxes both runs fill).
"""

import json
import math

import numpy as np
import pytest

from hel_warp.errors import ConfigError

SECTIONS = [{"name": f"S{k + 1}", "lo": [float(k), 0.0, 0.0], "hi": [float(k + 1), 1.0, 1.0]} for k in range(10)]
BOXES = 4
CENTRES = [(b + 0.5) / BOXES for b in range(BOXES)]


def make_run(path, collisions, snapshots, *, dt=1e-3, collision_series=(0, 0, 0, 0), wall=1.5, diameter=315e-6):
    """A run directory in the layout of cases/colliding_streams.py; snapshots: list of (time, parcels list)."""
    from hel_warp.io import RunWriter

    config = {"case": "synthetic", "collisions": collisions, "dt": dt, "diameter": diameter, "end_time": 0.004,
              "simulated_time": 0.004, "wall_clock_s": wall, "status": "complete", "spacing": 0.1,
              "collision_counts_available": True, "particles_per_parcel": 1.0,
              "rig": {"axial_axis": 0, "transverse_axis": 1, "downstream": [1.0, 0.0, 0.0], "sections": SECTIONS,
                      "domain_lo": [0.0, 0.0, 0.0], "domain_hi": [10.0, 1.0, 1.0], "main_depth": 1.0}}
    writer = RunWriter(path, config=config, vtk=False)
    for step, (time, parcels) in enumerate(snapshots, start=1):
        x = np.array([p[0] for p in parcels], np.float32).reshape(-1, 3)
        v = np.array([p[1] for p in parcels], np.float32).reshape(-1, 3)
        w = np.array([p[2] for p in parcels], np.float32)
        s = np.array([p[3] for p in parcels], np.int32)
        writer.write_snapshot({"x": x, "v": v, "weight": w, "stream": s, "radius": np.full(len(w), 1e-3, np.float32)},
                              time=time, step=step)
    writer.append_series("collisions", np.asarray(collision_series, np.int64))
    return str(path)


def parcel(section, box, u, weight=1.0, stream=0, v_y=0.3):
    return ([section + 0.5, CENTRES[box], 0.5], [u, v_y, 0.0], weight, stream)


@pytest.fixture()
def runs(tmp_path):
    # dem: one parcel per sub-box and snapshot, u = k + b + 0.5 (t1) and k + b + 2.5 (t2)  -> mean k + b + 1.5
    dem = [(t, [parcel(k, b, k + b + offset, stream=b % 2) for k in range(10) for b in range(BOXES)])
           for t, offset in ((0.002, 0.5), (0.004, 2.5))]
    # surrogate: k + b + 2 in both snapshots, except section S1 box 3 empty and S10 box 0 holding weights 1 and 3
    # with u = 1 and 5 (weighted mean (1 + 15) / 4 = 4; an unweighted mean would give 3), plus one parcel moving
    # upstream (u = -6) in S5 box 2 at t2 (mean with it: (8 + 8 - 6) / 3 = 10/3; downstream-only: 8)
    sur = []
    for t in (0.002, 0.004):
        parcels = [parcel(k, b, k + b + 2.0) for k in range(10) for b in range(BOXES)
                   if not (k == 0 and b == 3) and not (k == 9 and b == 0)]
        parcels += [parcel(9, 0, 1.0, weight=1.0) if t == 0.002 else parcel(9, 0, 5.0, weight=3.0)]
        if t == 0.004:
            parcels.append(parcel(4, 2, -6.0))
        # a parcel outside every section (between the rig and nothing) must not count
        parcels.append(([5.5, 1.5, 0.5], [100.0, 0.0, 0.0], 1.0, 0))
        sur.append((t, parcels))
    return (make_run(tmp_path / "dem_run", "dem", dem, collision_series=(3, 0, 5, 2), wall=20.0),
            make_run(tmp_path / "sur_run", "surrogate", sur, collision_series=(1, 1, 0, 2), wall=2.0))


def expected_sur(downstream_only):
    table = {(k, b): k + b + 2.0 for k in range(10) for b in range(BOXES)}
    table[(0, 3)] = None
    table[(9, 0)] = 4.0
    table[(4, 2)] = 8.0 if downstream_only else (8.0 + 8.0 - 6.0) / 3.0
    return table


def test_rms_leaves_out_sparse_sub_boxes():
    from hel_warp.errors import ConfigError
    from hel_warp.report import build_report, profile_rms

    a = [{"mean_axial_velocity": [1.0, 2.0, 3.0], "samples": [50, 12, 2]}]
    b = [{"mean_axial_velocity": [2.0, 4.0, 30.0], "samples": [40, 10, 9]}]
    assert profile_rms(a, b, min_samples=1) == pytest.approx(math.sqrt((1 + 4 + 27**2) / 3))
    assert profile_rms(a, b, min_samples=10) == pytest.approx(math.sqrt((1 + 4) / 2))  # 2 and 9 samples: out
    assert profile_rms(a, b, min_samples=40) == pytest.approx(1.0)
    assert profile_rms(a, b, min_samples=41) is None
    with pytest.raises(ConfigError, match="min-samples"):
        build_report(["unused"], min_samples=0)


@pytest.mark.parametrize("downstream_only", [False, True])
def test_profiles_and_rms_exact(runs, tmp_path, downstream_only):
    from hel_warp.report import write_report

    report = write_report(list(runs), str(tmp_path / "rep"), boxes=[BOXES], downstream_only=downstream_only,
                          figures=False, min_samples=1)
    on_disk = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert on_disk["runs"][1]["profiles"] == report["runs"][1]["profiles"]
    dem, sur = report["runs"]
    assert [dem["collisions"], sur["collisions"]] == ["dem", "surrogate"]
    table = expected_sur(downstream_only)
    for k in range(10):
        pd, ps = dem["profiles"][str(BOXES)][k], sur["profiles"][str(BOXES)][k]
        assert pd["section"] == f"S{k + 1}"
        assert pd["centres"] == pytest.approx(CENTRES)
        assert pd["mean_axial_velocity"] == pytest.approx([k + b + 1.5 for b in range(BOXES)], abs=1e-6)
        for b in range(BOXES):
            if table[(k, b)] is None:
                assert ps["mean_axial_velocity"][b] is None
            else:
                assert ps["mean_axial_velocity"][b] == pytest.approx(table[(k, b)], abs=1e-6)
    # RMS over the 39 sub-boxes both runs fill
    diffs = [table[(k, b)] - (k + b + 1.5) for k in range(10) for b in range(BOXES) if table[(k, b)] is not None]
    assert len(diffs) == 39
    assert sur["profile_rms_vs_dem"][str(BOXES)] == pytest.approx(math.sqrt(np.mean(np.square(diffs))), abs=1e-6)
    assert dem["profile_rms_vs_dem"] is None and sur["dem_reference"] == "dem_run"
    assert sur["paper_experimental_uncertainty"] == 0.63  # the paper's bar for 315 um (section 8)
    # collision rate = detected collisions / simulated time; the rest as stored
    assert dem["collision_rate"] == pytest.approx(10 / 0.004)
    assert sur["collision_rate"] == pytest.approx(4 / 0.004)
    assert (sur["dt"], sur["diameter"], sur["end_time"], sur["wall_clock_s"]) == (1e-3, 315e-6, 0.004, 2.0)


def test_paper_box_counts_and_figures(runs, tmp_path):
    from hel_warp.report import write_report

    report = write_report(list(runs), str(tmp_path / "rep"), boxes=[20, 88, 126])
    for boxes in (20, 88, 126):
        prof = report["runs"][0]["profiles"][str(boxes)]
        assert len(prof) == 10 and len(prof[0]["centres"]) == boxes
        assert prof[0]["centres"][0] == pytest.approx(0.5 / boxes)
        # each dem parcel sits alone in its fine sub-box: the profile holds its time-mean k + b + 1.5
        filled = [u for u in prof[3]["mean_axial_velocity"] if u is not None]
        assert filled == pytest.approx([3 + b + 1.5 for b in range(BOXES)], abs=1e-6)
    names = set(report["figures"])
    assert {"wall_clock.png", "collision_rate.png", "profiles_20.png", "dispersion_sur_run.png",
            "eps_s_dem_run.png"} <= names
    for name in names:
        assert (tmp_path / "rep" / name).stat().st_size > 1000


def test_missing_and_corrupt_run_dirs(tmp_path, capsys):
    from hel_warp.cli import main
    from hel_warp.report import load_run

    with pytest.raises(ConfigError, match="not found"):
        load_run(str(tmp_path / "nowhere"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(ConfigError, match="no run.zarr"):
        load_run(str(tmp_path / "empty"))
    bad = tmp_path / "bad" / "run.zarr"
    bad.mkdir(parents=True)
    (bad / "zarr.json").write_text("{not json")
    with pytest.raises(ConfigError, match="corrupt"):
        load_run(str(tmp_path / "bad"))
    assert main(["report", str(tmp_path / "bad"), "--out", str(tmp_path / "rep")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hel-warp: error:") and "corrupt" in err[0]


def test_dem_reference_must_have_the_same_diameter(runs, tmp_path):
    # a 475 um run is never compared with a 315 um dem run: its RMS is absent, not a cross-size number
    from hel_warp.report import build_report

    dem_dir, _ = runs
    other = make_run(tmp_path / "sur475", "surrogate", [(0.004, [parcel(0, 0, 1.0)])], diameter=475e-6)
    report, _ = build_report([dem_dir, other], boxes=(BOXES,))
    run475 = next(r for r in report["runs"] if r["diameter"] == 475e-6)
    assert run475.get("profile_rms_vs_dem") is None

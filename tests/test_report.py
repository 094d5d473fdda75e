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


def make_run(path, collisions, snapshots, *, dt=1e-3, collision_series=(0, 0, 0, 0), wall=1.5, diameter=315e-6,
             series=None, hel=None, rig_extra=None, particle_contacts=None, end_time=0.004):
    """A run directory in the layout of cases/colliding_streams.py + hel_warp.runs.run (config attrs ``hel``, ``case``;
    attrs ``summary``); snapshots: list of (time, parcels list). ``collision_series``: the real collisions per step
    (``collisions_collisions``; None: no such series); ``series``: more per-step series by name."""
    from hel_warp.runs.io import RunWriter

    rig = {"axial_axis": 0, "transverse_axis": 1, "downstream": [1.0, 0.0, 0.0], "sections": SECTIONS,
           "domain_lo": [0.0, 0.0, 0.0], "domain_hi": [10.0, 1.0, 1.0], "main_depth": 1.0, **(rig_extra or {})}
    case = {"case": "synthetic", "collisions": collisions, "dt": dt, "diameter": diameter, "spacing": 0.1,
            "particles_per_parcel": 1.0, "rig": rig}
    summary = {"collisions": collisions, "dt": dt, "diameter": diameter, "end_time": end_time,
               "simulated_time": end_time, "wall_clock_s": wall, "status": "complete",
               "collision_counts_available": True, "particles_per_parcel": 1.0}
    if particle_contacts is not None:
        case["particle_contacts"] = summary["particle_contacts"] = particle_contacts
    writer = RunWriter(path, config={"hel": hel or {"dt": dt}, "collision": {"name": collisions}, "case": case},
                       vtk=False)
    writer.root.attrs["summary"] = summary
    for step, (time, parcels) in enumerate(snapshots, start=1):
        x = np.array([p[0] for p in parcels], np.float32).reshape(-1, 3)
        v = np.array([p[1] for p in parcels], np.float32).reshape(-1, 3)
        w = np.array([p[2] for p in parcels], np.float32)
        s = np.array([p[3] for p in parcels], np.int32)
        writer.write_snapshot({"x": x, "v": v, "weight": w, "stream": s, "radius": np.full(len(w), 1e-3, np.float32)},
                              time=time, step=step)
    if collision_series is not None:
        writer.append_series("collisions_collisions", np.asarray(collision_series, np.float64))
    for name, values in (series or {}).items():
        writer.append_series(name, np.asarray(values))
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
    from hel_warp.runs.report import build_report, profile_rms

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
    from hel_warp.runs.report import write_report

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
    # collision rate = real collisions (series collisions_collisions) / simulated time; the rest as stored
    assert dem["collision_rate"] == pytest.approx(10 / 0.004)
    assert sur["collision_rate"] == pytest.approx(4 / 0.004)
    assert (sur["dt"], sur["diameter"], sur["end_time"], sur["wall_clock_s"]) == (1e-3, 315e-6, 0.004, 2.0)


def test_paper_box_counts_and_figures(runs, tmp_path):
    from hel_warp.runs.report import write_report

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
    from hel_warp.runs.report import load_run

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
    from hel_warp.runs.report import build_report

    dem_dir, _ = runs
    other = make_run(tmp_path / "sur475", "surrogate", [(0.004, [parcel(0, 0, 1.0)])], diameter=475e-6)
    report, _ = build_report([dem_dir, other], boxes=(BOXES,))
    run475 = next(r for r in report["runs"] if r["diameter"] == 475e-6)
    assert run475.get("profile_rms_vs_dem") is None


# ------------------------------------------------------------------------------------------ stream metrics
# Synthetic snapshots with known answers. The sections span y in [0, 1]; without ``axis_transverse`` the channel axis
# is each section's centre y = 0.5; stream 0 (left) comes from +y, stream 1 (right) from -y (the rig's layout).
TIMES = (0.001, 0.002, 0.003, 0.004)  # end time 0.004: the default window (second half) holds 0.002-0.004


def stream_run(tmp_path, name, placement, *, collisions="surrogate", poison_first=True, **kwargs):
    """Every section holds, at every snapshot, the parcels ``placement`` returns: (y, v_y, weight, stream) tuples.
    ``poison_first``: the snapshot at t = 0.001 (outside the default window) holds the opposite of what the window
    holds, so a metric that ignored the window would read the wrong answer."""
    snaps = []
    for t in TIMES:
        parcels = []
        for k in range(10):
            for y, vy, w, stream in placement(k):
                if poison_first and t == TIMES[0]:
                    y = 1.0 - y
                parcels.append(([k + 0.5, y, 0.5], [5.0, vy, 0.0], w, stream))
        snaps.append((t, parcels))
    return make_run(tmp_path / name, collisions, snaps, **kwargs)


def stay(k):  # each stream on its own side: left at y > 0.5, right at y < 0.5
    return [(0.6, 3.0, 1.0, 0), (0.8, -4.0, 1.0, 0), (0.2, 3.0, 1.0, 1), (0.4, -4.0, 1.0, 1)]


def cross(k):  # each stream entirely on the other side: they passed through each other
    return [(1.0 - y, vy, w, s) for y, vy, w, s in stay(k)]


def mix(k):  # half of each stream's particles on each side, by weight (1 parcel of 3 vs 3 parcels of 1)
    return [(0.7, 2.0, 3.0, 0), (0.3, 2.0, 1.0, 0), (0.35, 2.0, 1.0, 0), (0.45, 2.0, 1.0, 0),
            (0.3, -2.0, 3.0, 1), (0.7, -2.0, 1.0, 1), (0.65, -2.0, 1.0, 1), (0.55, -2.0, 1.0, 1)]


def _metrics(path, **kwargs):
    from hel_warp.runs.report import build_report

    report, _ = build_report([path], boxes=[BOXES], min_samples=1, **kwargs)
    return report["runs"][0]["stream_metrics"]


@pytest.mark.parametrize("placement, crossing", [(stay, 0.0), (cross, 1.0), (mix, 0.5)])
def test_stream_crossing_known_answers(tmp_path, placement, crossing):
    m = _metrics(stream_run(tmp_path, "run", placement))
    assert m["window_s"] == pytest.approx([0.002, 0.004]) and m["snapshots"] == 3
    for section in m["sections"]:
        assert section["crossing"] == {"left": pytest.approx(crossing), "right": pytest.approx(crossing)}
        assert section["stream_crossing"] == pytest.approx(crossing)
        assert section["samples"] == 3 * len(placement(0))
    assert m["stream_crossing"] == pytest.approx(crossing)


def test_stream_window_is_configurable(tmp_path):
    # only the first snapshot (the mirrored one): stay becomes cross
    path = stream_run(tmp_path, "run", stay)
    assert _metrics(path, stream_window=(0.0, 0.25))["stream_crossing"] == pytest.approx(1.0)
    # all four snapshots: 3 staying + 1 crossing snapshot = 1/4 of the samples across
    assert _metrics(path, stream_window=(0.0, 1.0))["stream_crossing"] == pytest.approx(0.25)


def test_axis_and_sides_from_the_rig_layout(tmp_path):
    # axis at y = 0.25, arms swapped (left from -y): stay's left samples (y 0.6, 0.8) both lie across -> 1; its right
    # samples (y 0.2, 0.4) on a +y arm: 0.2 lies across, 0.4 does not -> 1/2
    path = stream_run(tmp_path, "run", stay, rig_extra={"axis_transverse": 0.25,
                                                        "stream_sides": {"0": -1.0, "1": 1.0}})
    section = _metrics(path)["sections"][0]
    assert section["crossing"] == {"left": pytest.approx(1.0), "right": pytest.approx(0.5)}
    assert section["stream_crossing"] == pytest.approx(0.75)


def test_transverse_spread_and_velocity_rms(tmp_path):
    m = _metrics(stream_run(tmp_path, "run", stay))
    for section in m["sections"]:
        # each stream at two positions 0.2 m apart, equal weights: std 0.1 m = 100 mm
        assert section["transverse_spread_mm"] == {"left": pytest.approx(100.0), "right": pytest.approx(100.0)}
        # v_y = +3 and -4 in equal weights: sqrt((9 + 16) / 2)
        assert section["transverse_velocity_rms"] == pytest.approx(math.sqrt(12.5))
    assert m["transverse_velocity_rms"] == pytest.approx(math.sqrt(12.5))
    mixed = _metrics(stream_run(tmp_path, "mixed", mix))["sections"][0]
    # left stream: y = 0.7 (w 3), 0.3, 0.35, 0.45 (w 1 each); weighted mean 0.525, weighted variance by hand
    y, w = np.array([0.7, 0.3, 0.35, 0.45]), np.array([3.0, 1.0, 1.0, 1.0])
    mean = (w * y).sum() / w.sum()
    assert mixed["transverse_spread_mm"]["left"] == pytest.approx(1e3 * math.sqrt((w * (y - mean) ** 2).sum() / w.sum()))
    assert mixed["transverse_velocity_rms"] == pytest.approx(2.0)


def test_stream_composition_per_sub_box(tmp_path):
    # 4 sub-boxes of 0.25: box 0 right only, box 1 empty, box 2 left (w 1) + right (w 3), box 3 left only
    def placement(k):
        return [(0.1, 0.0, 2.0, 1), (0.6, 0.0, 1.0, 0), (0.6, 0.0, 3.0, 1), (0.9, 0.0, 1.0, 0)]

    m = _metrics(stream_run(tmp_path, "run", placement, poison_first=False))
    comp = m["composition"][str(BOXES)][4]
    assert comp["section"] == "S5" and comp["centres"] == pytest.approx(CENTRES)
    assert comp["fractions"]["left"] == [pytest.approx(0.0), None, pytest.approx(0.25), pytest.approx(1.0)]
    assert comp["fractions"]["right"] == [pytest.approx(1.0), None, pytest.approx(0.75), pytest.approx(0.0)]
    assert comp["samples"] == [3, 0, 6, 3]


def test_metrics_against_dem(tmp_path):
    from hel_warp.runs.report import build_report

    dem = stream_run(tmp_path, "dem", mix, collisions="dem")
    sur = stream_run(tmp_path, "sur", cross)
    report, _ = build_report([dem, sur], boxes=[BOXES], min_samples=1)
    entry = report["runs"][1]
    assert entry["dem_reference"] == "dem"
    assert entry["stream_crossing_vs_dem"]["difference"] == pytest.approx(1.0 - 0.5)
    assert entry["stream_crossing_vs_dem"]["sections_compared"] == 10
    # transverse rms: cross has sqrt(12.5), mix 2
    assert entry["transverse_velocity_rms_vs_dem"]["relative_difference"] == pytest.approx((math.sqrt(12.5) - 2) / 2)
    # composition and v_y profiles: an identical run differs by 0; stay vs cross swaps every sub-box's stream
    same, _ = build_report([dem, stream_run(tmp_path, "dem2", mix)], boxes=[BOXES], min_samples=1)
    assert same["runs"][1]["stream_composition_vs_dem"][str(BOXES)] == pytest.approx(0.0)
    assert same["runs"][1]["stream_crossing_vs_dem"]["difference"] == pytest.approx(0.0)
    swapped, _ = build_report([stream_run(tmp_path, "dem3", stay, collisions="dem"), sur], boxes=[BOXES],
                              min_samples=1)
    assert swapped["runs"][1]["stream_composition_vs_dem"][str(BOXES)] == pytest.approx(1.0)
    # v_y profiles: stay has +3 at y 0.6 / 0.2 and -4 at 0.8 / 0.4; cross mirrors y, so every filled box flips sign
    assert swapped["runs"][1]["transverse_velocity_profile_rms_vs_dem"][str(BOXES)] == pytest.approx(7.0)
    assert swapped["runs"][1]["stream_crossing_vs_dem"]["difference"] == pytest.approx(1.0)


# ------------------------------------------------------------------------------------------ collision rates
def test_real_collision_rates_per_stream_pair(tmp_path):
    from hel_warp.runs.report import build_report

    pairs = {f"collisions_collisions_{a}_{b}": np.zeros(4) for a in range(4) for b in range(a, 4)}
    pairs["collisions_collisions_0_0"] = np.array([1.0, 0, 0, 0])
    pairs["collisions_collisions_0_1"] = np.array([0, 2.0, 0, 1.0])
    overlap = {"collisions_detected_pairs": np.array([5, 5, 0, 0], np.int64),
               "collisions_detected_pairs_0_1": np.array([5, 5, 0, 0], np.int64)}
    dem = stream_run(tmp_path, "dem", stay, collisions="dem", collision_series=(1, 2, 0, 1), series={**pairs, **overlap})
    # a surrogate with parcels of weight 8: 0.5 real collisions per step on average (weight-aware, fractional)
    sur = stream_run(tmp_path, "sur", stay, collision_series=(0.5, 0.25, 1.25, 0.0),
                     series={"collisions_detected_pairs": np.array([1, 0, 0, 0], np.int64)})
    old = stream_run(tmp_path, "old", stay, collision_series=None,  # written before the real counts existed
                     series={"collisions_detected_pairs": np.array([2, 0, 0, 0], np.int64)})
    ktgf = stream_run(tmp_path, "ktgf", stay, collisions="ktgf", collision_series=None)
    none = stream_run(tmp_path, "none", stay, collisions="none", collision_series=None)
    report, _ = build_report([dem, sur, old, ktgf, none], boxes=[BOXES], min_samples=1)
    by = {e["label"]: e for e in report["runs"]}
    assert by["dem"]["collision_rate"] == pytest.approx(4 / 0.004)
    assert by["dem"]["collision_rate_per_stream_pair"] == {"left-left": pytest.approx(250.0),
                                                           "left-right": pytest.approx(750.0),
                                                           "right-right": 0.0}
    assert by["dem"]["overlap_pair_rate"] == pytest.approx(10 / 0.004)  # kept under its own key
    assert by["dem"]["overlap_pair_rate_per_stream_pair"]["left-right"] == pytest.approx(10 / 0.004)
    assert by["sur"]["collision_rate"] == pytest.approx(2.0 / 0.004)
    assert by["sur"]["collision_rate_vs_dem"] == pytest.approx((500.0 - 1000.0) / 1000.0)
    assert by["old"]["collision_rate"] is None and "collisions_collisions" in by["old"]["collision_rate_note"]
    assert by["old"]["overlap_pair_rate"] == pytest.approx(500.0)
    assert by["ktgf"]["collision_rate"] is None and "ktgf" in by["ktgf"]["collision_rate_note"]
    assert by["none"]["collision_rate"] == 0.0 and "none" in by["none"]["collision_rate_note"]
    assert by["none"]["collision_rate_vs_dem"] == pytest.approx(-1.0)


# ------------------------------------------------------------------------------------------ like with like
def test_like_with_like_lists_differences_and_measures_the_walls(tmp_path):
    from hel_warp.runs.report import build_report

    dem = stream_run(tmp_path, "dem", mix, collisions="dem", hel={"dt": 1e-3, "wall_friction": 0.3})
    walls = stream_run(tmp_path, "walls", mix, collisions="dem", particle_contacts=False,
                       hel={"dt": 1e-3, "wall_friction": 0.3})
    free = stream_run(tmp_path, "free", stay, collisions="none", collision_series=None,
                      hel={"dt": 1e-3, "wall_friction": 0.0})
    report, _ = build_report([dem, walls, free], boxes=[BOXES], min_samples=1)
    by = {e["label"]: e for e in report["runs"]}
    assert [by[k]["model"] for k in ("dem", "walls", "free")] == ["dem", "dem-no-contacts", "none"]
    # the reference is the dem run with contacts, never the one without
    assert by["walls"]["dem_reference"] == "dem" and by["free"]["dem_reference"] == "dem"
    assert by["free"]["config_differences_vs_dem"] == [{"key": "hel.wall_friction", "dem": 0.3, "run": 0.0}]
    assert by["walls"]["config_differences_vs_dem"] == []  # particle_contacts is the intended difference
    whats = [d["what"] for d in report["like_with_like"]["model_differences"]]
    assert "walls" in whats and "particle-particle collisions" in whats
    (effect,) = report["like_with_like"]["wall_effect"]
    assert (effect["none"], effect["dem_no_contacts"]) == ("free", "walls")
    assert effect["stream_crossing_difference"] == pytest.approx(0.0 - 0.5)  # none stays, walls-only mixes
    assert effect["transverse_velocity_rms_relative_difference"] == pytest.approx((math.sqrt(12.5) - 2.0) / 2.0)
    assert report["like_with_like"]["wall_effect_note"] is None
    alone, _ = build_report([dem, free], boxes=[BOXES], min_samples=1)
    assert alone["like_with_like"]["wall_effect"] == [] and "--no-particle-contacts" in \
        alone["like_with_like"]["wall_effect_note"]


def test_summary_table_figures_and_cli(tmp_path, capsys):
    from hel_warp.cli import main

    dem = stream_run(tmp_path, "dem", mix, collisions="dem")
    sur = stream_run(tmp_path, "sur", cross)
    out = tmp_path / "rep"
    assert main(["report", dem, sur, "--out", str(out), "--boxes", "4", "--min-samples", "1",
                 "--composition-section", "S3"]) == 0
    printed = capsys.readouterr().out
    assert "| surrogate | 1.000 | +0.500 |" in printed  # crossing 1, 0.5 above dem's
    report = json.loads((out / "report.json").read_text())
    rows = {r["model"]: r for r in report["summary_table"]}
    assert rows["surrogate"]["stream_crossing"] == pytest.approx(1.0)
    assert rows["dem"]["stream_crossing_vs_dem"] is None
    assert "| surrogate | 1.000 | +0.500 |" in (out / "summary.md").read_text()
    for name in ("stream_crossing.png", "transverse_velocity_rms.png", "stream_composition_S3.png",
                 "summary_table.png", "collision_rate.png", "overlap_pair_rate.png"):
        assert name in report["figures"] and (out / name).stat().st_size > 1000, name
    for bad, what in ((["--stream-window", "0.8", "0.2"], "stream-window"),
                      (["--composition-section", "S11"], "composition-section")):
        assert main(["report", dem, "--out", str(tmp_path / "bad"), "--no-figures", *bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("hel-warp: error:") and what in err[0]

"""The colliding-streams rig (cases/colliding_streams.py): flows, connectivity, sections, a reduced run.

References: the paper's section 2 (240 and 38.4 l/min, 20 m/s in the supply channels) for the
inlet flows; a flood fill of the fluid mask and the analytic SDF for connectivity; the run
directory contract of hel_warp/runs/report.py for the reduced run.
"""

import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
LITRE_PER_MIN = 1e-3 / 60.0


def load_file(name: str, relative: str, *, register: bool = False):
    """The module in the repository file ``relative`` (cases/ and scripts/ are not packages); ``register`` also
    puts it in ``sys.modules`` (dataclasses of the module need it)."""
    spec = importlib.util.spec_from_file_location(name, ROOT / relative)
    module = importlib.util.module_from_spec(spec)
    if register:
        sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def cs():
    return load_file("colliding_streams", "cases/colliding_streams.py", register=True)


@pytest.fixture(scope="module")
def full_rig(cs):
    dims = cs.RigDimensions()
    grid, geometry, speeds = cs.build_geometry(dims)
    domain = geometry.build(grid, device="cpu")
    return dims, grid, geometry, speeds, domain


def _sdf(geometry, points):
    import warp as wp

    from kernels.sdf import eval_sdf

    pts = wp.array(np.asarray(points, np.float32), dtype=wp.vec3, device="cpu")
    dist = wp.zeros(len(points), dtype=float, device="cpu")
    nrm = wp.zeros(len(points), dtype=wp.vec3, device="cpu")
    eval_sdf(geometry.shapes_struct("cpu"), pts, dist, nrm)
    return dist.numpy()


def test_inlet_flows_match_the_paper(full_rig):
    # Q = (inlet faces x h^2) x normal speed; the paper: 240 l/min main, 38.4 l/min per side arm, 20 m/s
    dims, grid, geometry, speeds, domain = full_rig
    expected = {"main_inlet": 240.0, "left_inlet": 38.4, "right_inlet": 38.4}
    patches = {p.name: p for p in geometry.patches}
    for name, litres in expected.items():
        axis, mask = domain.patch_faces[name]
        area = mask.sum() * grid.spacing**2
        flow = area * patches[name].velocity[axis] / LITRE_PER_MIN
        assert flow == pytest.approx(litres, rel=0.01), name
        assert patches[name].velocity[axis] == pytest.approx(20.0, rel=0.01), name
        assert area == pytest.approx(litres * LITRE_PER_MIN / 20.0, rel=0.01), name
    assert np.prod(grid.shape) == pytest.approx(100_000, rel=0.1)  # "about 100,000 cells" (paper: 107,000)


def test_reduced_grid_keeps_the_flows(cs):
    dims = cs.dimensions_for_cells(5000)
    grid, geometry, speeds = cs.build_geometry(dims)
    domain = geometry.build(grid, device="cpu")
    assert np.prod(grid.shape) == pytest.approx(5000, rel=0.3)
    patches = {p.name: p for p in geometry.patches}
    for name, litres in {"main_inlet": 240.0, "left_inlet": 38.4, "right_inlet": 38.4}.items():
        axis, mask = domain.patch_faces[name]
        assert mask.sum() * grid.spacing**2 * patches[name].velocity[axis] / LITRE_PER_MIN == pytest.approx(litres,
                                                                                                           rel=1e-6)


def test_junction_connected(full_rig, cs):
    from scipy import ndimage

    dims, grid, geometry, speeds, domain = full_rig
    fluid = domain.cell_fluid.numpy().astype(bool)
    labels, count = ndimage.label(fluid)  # face connectivity (6-neighbourhood)
    assert count == 1
    # SDF < 0 along each stream's path: injection box -> supply axis -> inclined arm -> main axis -> outlet
    for side in (0, 1):
        lo, hi = dims.injection_box(side, 0.0)
        start = 0.5 * (np.asarray(lo) + np.asarray(hi))
        arm_start, arm_end = (np.asarray(p) for p in dims.arm_axis(side))
        main_point = np.array([arm_end[0] + abs(arm_end[1]), 0.0, 0.5 * dims.main_depth])
        outlet = np.array([dims.main_length - 1e-3, 0.0, 0.5 * dims.main_depth])
        path = [start, arm_start, arm_end, main_point, outlet]
        points = np.concatenate([np.linspace(a, b, 200) for a, b in zip(path[:-1], path[1:])])
        assert np.all(_sdf(geometry, points) < 0.0), f"arm {side} path leaves the fluid"


def test_ten_sections_downstream_inside_fluid(full_rig):
    dims, grid, geometry, speeds, domain = full_rig
    sections = dims.sections()
    assert len(sections) == 10
    junction_x = max(max(dims.arm_axis(s)[1][0] for s in (0, 1)), 0.0)  # arm axes end inside the main channel
    previous_hi = -math.inf
    for s in sections:
        lo, hi = np.asarray(s["lo"]), np.asarray(s["hi"])
        assert lo[0] > junction_x and lo[0] >= previous_hi
        previous_hi = hi[0]
        # every point of the box (corners pulled in by 1 um) is fluid of the main channel
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        centre = 0.5 * (lo + hi)
        pulled = corners + 1e-6 * np.sign(centre - corners)
        assert np.all(_sdf(geometry, np.vstack([pulled, centre])) < 0.0), s["name"]
    assert previous_hi < dims.main_length


def _args(out, *extra, end_time="0.003"):
    return ["--diameter", "315e-6", "--dt", "1e-3", "--collisions", "none", "--end-time", end_time, "--cells", "5000",
            "--max-particles", "200", "--gas-warmup", "0.001", "--no-vtk", "--no-progress", "--out", str(out), *extra]


def test_reduced_run_writes_what_the_report_needs(cs, tmp_path):
    import zarr

    from hel_warp.runs.report import load_run, profiles

    out = tmp_path / "run"
    assert cs.main(_args(out)) == 0
    run = load_run(str(out))
    c = run.config
    for key in ("collisions", "dt", "diameter", "end_time", "wall_clock_s", "rig"):
        assert key in c
    assert c["collisions"] == "none" and c["dt"] == 1e-3 and c["diameter"] == 315e-6 and c["end_time"] == 0.003
    assert c["check_errors"] == [] and c["status"] == "complete"
    assert c["wall_clock_s"] == pytest.approx(float(np.sum(run.series["timing_step"])))
    assert len(run.rig["sections"]) == 10
    assert run.series["timing_step"].shape == (3,)
    assert len(run.snapshots) == 4  # t = 0 (before the first release) and after each step
    last = run.snapshots[-1]
    # both streams present, parcels alive = injected - removed (the count check of check())
    assert set(np.unique(last["stream"]).tolist()) == {0, 1}
    assert len(last["x"]) == c["injected"] - c["removed"] == 200 - c["removed"]
    assert np.all(np.isfinite(last["v"]))
    assert len(profiles(run, 20)) == 10
    assert zarr.open_group(str(out / "run.zarr"), mode="r").attrs["summary"]["wall_clock_s"] == c["wall_clock_s"]
    # --resume to a later end time continues from the checkpoint: two more steps in the same directory
    assert cs.main(_args(out, "--resume", end_time="0.005")) == 0
    resumed = load_run(str(out))
    assert resumed.config["steps"] == 5 and resumed.config["end_time"] == 0.005
    assert resumed.series["step"].tolist() == [1, 2, 3, 4, 5] and len(resumed.snapshots) == 6


def test_existing_run_dir_refused(cs, tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "run.zarr").mkdir()
    assert cs.main(_args(out)) == 2
    assert "exists" in capsys.readouterr().err
    from hel_warp.cli import main as hel_warp_main  # the same through `hel-warp run CASE_SCRIPT ...`

    assert hel_warp_main(["run", str(ROOT / "cases" / "colliding_streams.py"), *_args(out)]) == 2
    assert "exists" in capsys.readouterr().err
    other = tmp_path / "not_a_run"
    other.mkdir()
    (other / "precious.txt").write_text("keep me")
    assert cs.main(_args(other, "--overwrite")) == 2
    assert (other / "precious.txt").exists()


def test_model_for_another_particle_refused(cs, tmp_path, capsys):
    from hel_warp.case.models import check_model
    from hel_warp.errors import ConfigError

    def species(diameter, density):
        return [cs.hc.Species(name="d1", diameter=diameter, material=cs.hc.Material(density=density))]

    model = tmp_path / "model"
    model.mkdir()
    (model / "metadata.json").write_text(json.dumps({"format": "hel_warp.surrogate",
                                                     "defaults": {"d1": 475e-6, "d2": 475e-6, "rho1": 1000.0,
                                                                  "rho2": 1000.0}}))
    with pytest.raises(ConfigError, match="475 um.*pass --force to"):
        check_model(str(model), species(315e-6, 1000.0), force=False)
    with pytest.raises(ConfigError, match="pass --force-model to"):  # the option of the caller (scripts/bench_rig.py)
        check_model(str(model), species(315e-6, 1000.0), force=False, force_flag="--force-model")
    assert check_model(str(model), species(315e-6, 1000.0), force=True)["defaults"]["d1"] == 475e-6
    check_model(str(model), species(475e-6, 1000.0), force=False)  # the right particle passes
    with pytest.raises(ConfigError, match="density"):
        check_model(str(model), species(475e-6, 950.0), force=False)
    args = _args(tmp_path / "run")
    args[args.index("none")] = "surrogate"
    assert cs.main(args + ["--model", str(model)]) == 2
    assert "--force" in capsys.readouterr().err


def test_paper_particle_sets(cs):
    # paper section 8: 12,000 particles of 315 um = 0.000196 kg; 3,600 of 475 um; one particle per parcel
    import argparse

    parser = argparse.ArgumentParser()
    cs.add_arguments(parser)

    def config(*extra):
        return cs.make_config(parser.parse_args(["--diameter", extra[0], "--dt", "1e-3", "--collisions", "none",
                                                 "--end-time", "0.02", "--out", "x", *extra[1:]]))

    small, large = config("315e-6"), config("475e-6")
    assert (small.particles, small.diameter_std, small.mass_flow) == (12000, 8.2e-6, (0.014, 0.018))
    assert (large.particles, large.diameter_std, large.mass_flow) == (3600, 22e-6, (0.013, 0.019))
    mass = small.particles * 1000.0 * math.pi / 6.0 * 315e-6**3
    assert mass == pytest.approx(0.000196, rel=0.01)
    eight = config("315e-6", "--particles-per-parcel", "8")
    assert eight.particles == 12000 and eight.particles_per_parcel == 8.0  # parcel count kept, mass x 8
    # --real-particles: N real over the paper's window (parcels x the weight the window counts = the paper's 12,000)
    for extra, parcels in ((("--real-particles", "96000"), 96000),
                           (("--real-particles", "96000", "--particles-per-parcel", "8"), 12000),
                           (("--real-particles", "12000", "--particles-per-parcel", "64"), 188)):
        c = config("315e-6", *extra)
        assert c.particles == parcels and c.particles * c.release_weights()[0] == pytest.approx(12000)
    from hel_warp.collisions.cells import CellConfig
    from hel_warp.errors import ConfigError

    with pytest.raises(ConfigError, match="one-size option"):
        config("315e-6", "--real-particles", "96000", "--diameter2", "475e-6", "--mass-fraction2", "0.5")
    with pytest.raises(ConfigError, match="--real-particles must be"):
        config("315e-6", "--real-particles", "10", "--particles-per-parcel", "8")

    # the cell detection's options (the case API's shared ones): refused where the run has no cell detection,
    # validated at the door; the strategy's settings of the run (Case.settings)
    def settings(collisions, *extra):
        args = parser.parse_args(["--diameter", "315e-6", "--dt", "1e-3", "--collisions", collisions, "--end-time",
                                  "0.02", "--out", "x", "--cells", "5000",
                                  *(("--model", "m") if collisions == "surrogate" else ()), *extra])
        return cs.CASE.settings(args, cs.build(args))

    def cell(*extra):
        return settings("surrogate", *extra).strategy.get("cell", {})

    assert cell("--particles-per-parcel", "8", "--cell-coarsen", "3")["coarsen"] == 3
    assert cell("--detection", "cell", "--cell-coarsen", "2")["coarsen"] == 2
    assert cell("--particles-per-parcel", "8") == {}  # not given: CellConfig's defaults
    with pytest.raises(ConfigError, match="--cell-coarsen is an option"):
        settings("none", "--particles-per-parcel", "8", "--cell-coarsen", "3")
    with pytest.raises(ConfigError, match="--cell-coarsen is an option"):
        cell("--cell-coarsen", "3")  # weight 1: swept detection
    with pytest.raises(ConfigError, match="--cell-coarsen must be"):
        cell("--particles-per-parcel", "8", "--cell-coarsen", "0")
    # --no-packing-stress: cell detection only
    assert cell("--particles-per-parcel", "8", "--no-packing-stress")["packing_stress"] is False
    assert CellConfig().packing_stress is True
    with pytest.raises(ConfigError, match="--no-packing-stress is an option"):
        cell("--no-packing-stress")  # weight 1: swept detection
    # --[no-]cell-approaching: cell detection only; not given: CellConfig's default
    assert cell("--particles-per-parcel", "64", "--cell-approaching")["approaching"] is True
    assert cell("--detection", "cell", "--no-cell-approaching")["approaching"] is False
    assert "approaching" not in cell("--particles-per-parcel", "8") and CellConfig().approaching is None
    for flag in ("--cell-approaching", "--no-cell-approaching"):
        with pytest.raises(ConfigError, match=r"--\[no-\]cell-approaching is an option"):
            cell(flag)  # weight 1: swept detection
    # --cell-cfl: cell detection only, validated at the door
    assert cell("--detection", "cell", "--cell-cfl", "0.5")["cfl"] == 0.5
    assert "cfl" not in cell("--detection", "cell") and CellConfig().cfl == 1.0
    with pytest.raises(ConfigError, match="--cell-cfl is an option"):
        cell("--cell-cfl", "0.5")  # weight 1: swept detection
    with pytest.raises(ConfigError, match="--cell-cfl must be"):
        cell("--detection", "cell", "--cell-cfl", "0")


def test_report_on_a_reduced_rig_has_every_new_metric(cs, tmp_path):
    """CI size of the stream metrics: `none` and `ktgf` long enough (0.02 s) for the parcels to reach the sections (from
    t ~ 0.014 s on this grid), a short `dem` (its sub-steps cost ~1 s per step here) for the real collision counts,
    and the report over all of them. Facts checked: what the metrics are by definition (fractions in [0, 1], the
    sample counts of the window, none's rate 0, ktgf's null with its reason), not numbers of this physics."""
    import inspect

    from hel_warp.hel import COLLISION_MODELS
    from hel_warp.runs.report import build_report

    def rig_run(name, model, end_time, *extra):
        args = _args(tmp_path / name, "--no-gas-snapshots", "--output-interval", "0.002", *extra, end_time=end_time)
        args[args.index("none")] = model
        assert cs.main(args) == 0, name
        return str(tmp_path / name)

    runs = [rig_run("none", "none", "0.02"), rig_run("ktgf", "ktgf", "0.02"), rig_run("dem", "dem", "0.002")]
    walls_only = "particle_contacts" in inspect.signature(COLLISION_MODELS["dem"].__init__).parameters
    if walls_only:
        runs.append(rig_run("dem_walls", "dem", "0.002", "--no-particle-contacts"))
    report, loaded = build_report(runs, boxes=(20,), min_samples=1)
    by = {e["label"]: e for e in report["runs"]}
    for label in ("none", "ktgf"):
        sm = by[label]["stream_metrics"]
        assert sm["window_s"] == pytest.approx([0.01, 0.02]) and sm["snapshots"] == 6  # t = 0.010, 0.012, ... 0.020
        filled = [s for s in sm["sections"] if s["samples"]]
        assert filled, f"{label}: no parcel reached a section"
        for s in filled:
            assert 0.0 <= s["stream_crossing"] <= 1.0 and s["transverse_velocity_rms"] > 0.0
            assert sum(s["samples_per_stream"].values()) == s["samples"]
        for comp in sm["composition"]["20"]:
            for b, n in enumerate(comp["samples"]):
                total = sum(f[b] for f in comp["fractions"].values() if f[b] is not None)
                assert (total == pytest.approx(1.0)) if n else total == 0.0
        assert 0.0 <= sm["stream_crossing"] <= 1.0
        assert by[label]["dem_reference"] == "dem" and "stream_crossing_vs_dem" in by[label]
        assert by[label]["kernel_load_s"] >= 0.0 and by[label]["wall_clock_s"] > 0.0
    assert by["none"]["collision_rate"] == 0.0
    assert by["ktgf"]["collision_rate"] is None and "ktgf" in by["ktgf"]["collision_rate_note"]
    dem = by["dem"]
    if dem["collision_rate"] is not None:  # an engine whose DemCollision counts contact onsets
        assert dem["collision_rate"] >= 0.0
        assert set(dem["collision_rate_per_stream_pair"]) >= {"left-left", "left-right", "right-right"}
        assert sum(dem["collision_rate_per_stream_pair"].values()) == pytest.approx(dem["collision_rate"])
    else:
        assert "collisions_collisions" in dem["collision_rate_note"]
    assert dem["overlap_pair_rate"] is not None
    assert [r["model"] for r in report["summary_table"]][:2] == ["none", "ktgf"]
    if walls_only:
        assert by["dem_walls"]["model"] == "dem-no-contacts" and by["dem_walls"]["collision_rate"] == 0.0
        (effect,) = report["like_with_like"]["wall_effect"]
        assert (effect["none"], effect["dem_no_contacts"]) == ("none", "dem_walls")
    # the like-with-like list: the runs share the case settings; the hel config differs only where the models do
    for label in ("none", "ktgf"):
        keys = {d["key"] for d in by[label]["config_differences_vs_dem"]}
        assert not any(k.startswith(("case.", "gas.", "grid.")) for k in keys), keys
    # hel_warp.studies.rig_ensemble: the metrics are ratios over the parcels, so a run pooled with itself (twice the
    # parcels at half the weight) has the metrics of the run; runs of another snapshot schedule are refused
    ens = importlib.import_module("hel_warp.studies.rig_ensemble")
    filled = [k + 1 for k, s in enumerate(by["none"]["stream_metrics"]["sections"]) if s["samples"]]
    one = ens.ensemble_metrics([runs[0]], [runs[1]], min_samples=1, sections=filled[:2])
    two = ens.ensemble_metrics([runs[0], runs[0]], [runs[1], runs[1], runs[1]], min_samples=1, sections=filled[:2],
                               jackknife=True)
    for key in ("stream_crossing", "reference_stream_crossing", "transverse_velocity_rms", "stream_crossing_vs_dem"):
        assert two[key] == pytest.approx(one[key], rel=1e-12), key
    # identical runs leave nothing to the seed-to-seed spread: every jackknife error is 0 (--jackknife)
    for part in ("runs", "reference", "combined"):
        assert all(v == pytest.approx(0.0, abs=1e-12) for v in two["jackknife"][part].values()), part
    # the jackknife of a mean is the standard error of the mean, std(x, ddof=1) / sqrt(n) (closed form)
    x = np.random.default_rng(4).normal(size=9)
    loo = [{"a": float(np.delete(x, k).mean())} for k in range(len(x))]
    assert ens._leave_one_out_error(loo)["a"] == pytest.approx(x.std(ddof=1) / np.sqrt(len(x)), rel=1e-12)
    for key in ("stream_crossing_vs_dem", "transverse_velocity_rms_vs_dem"):  # the fixed sections alike
        assert (two["fixed"][key] is None and one["fixed"][key] is None) or \
            two["fixed"][key] == pytest.approx(one["fixed"][key], rel=1e-12, abs=1e-12)
    assert one["stream_crossing"] == pytest.approx(by["none"]["stream_metrics"]["stream_crossing"], rel=1e-12)
    assert {"fixed_stream_crossing_vs_dem", "fixed_transverse_velocity_rms_vs_dem"} <= set(two["jackknife"]["runs"])
    # the ensemble's hook (hel-warp ensemble): the rig's case file hands it to the ensemble (the loader the ensemble
    # uses), and a run pooled with itself keeps the report's figures, per section too
    from hel_warp.studies.ensemble import load_hook

    rig_hook = load_hook(Path(__file__).resolve().parents[1] / "cases" / "colliding_streams.py")
    assert rig_hook is not None
    assert json.dumps(rig_hook([runs[0]], [runs[1]])["metrics"]) == \
        json.dumps(ens.case_hook([runs[0]], [runs[1]])["metrics"])
    for hook in (ens.case_hook([runs[0], runs[0]], [runs[1]], min_samples=1, sections=filled[:2]),
                 ens.case_hook([runs[0], runs[0]], None, min_samples=1, sections=filled[:2])):
        sections = by["none"]["stream_metrics"]["sections"]
        assert hook["metrics"]["stream_crossing"] == pytest.approx(by["none"]["stream_metrics"]["stream_crossing"])
        assert hook["metrics"]["transverse_velocity_rms_per_section"] == pytest.approx(
            [s["transverse_velocity_rms"] for s in sections], nan_ok=True)
        assert all(v is None or v == pytest.approx(0.0, abs=1e-12) for v in hook["stderr"].values())
    # the ensemble's collision rates are the mean of its runs' (the report's own figure), beside the reference's
    col = ens.ensemble_metrics([runs[2], runs[2]], [runs[2]], min_samples=1)["collisions"]
    if dem["collision_rate"] is not None:
        assert col["collision_rate"] == pytest.approx(dem["collision_rate"], rel=1e-12)
        assert (col["collision_rate_vs_dem"] == pytest.approx(1.0, rel=1e-12) if dem["collision_rate"] > 0.0
                else col["collision_rate_vs_dem"] is None)  # no ratio against a reference that never collided
        assert all(v is None or v == pytest.approx(1.0, rel=1e-12)
                   for v in col["collision_rate_per_stream_pair_vs_dem"].values())
    # with known counts (a run's series replaced): runs of 30 and 50 real collisions against references of 10 and 30,
    # over the dem run's simulated time T: rates 40 / T and 20 / T, ratio 2; per stream pair likewise
    import dataclasses

    from hel_warp.runs.report import load_run

    base = load_run(runs[2])
    t = base.config.get("simulated_time", base.config["end_time"])

    def counted(left_left, left_right):
        series = {"collisions_collisions": np.array([left_left + left_right, 0.0]),
                  "collisions_collisions_0_0": np.array([left_left, 0.0]),
                  "collisions_collisions_0_1": np.array([0.0, left_right])}
        return dataclasses.replace(base, series=series)

    col = ens.ensemble_collisions([counted(20, 10), counted(40, 10)], [counted(10, 0), counted(10, 20)])
    assert col["collision_rate"] == pytest.approx(40.0 / t) and col["reference_collision_rate"] == pytest.approx(20 / t)
    assert col["collision_rate_vs_dem"] == pytest.approx(2.0)
    assert col["collision_rate_per_stream_pair_vs_dem"]["left-left"] == pytest.approx(3.0)
    assert col["collision_rate_per_stream_pair_vs_dem"]["left-right"] == pytest.approx(1.0)
    # none collides at rate 0; ktgf counts no collision, so there is no ratio against it
    col = ens.ensemble_metrics([runs[0]], [runs[1]], min_samples=1)["collisions"]
    assert col["collision_rate"] == 0.0 and col["reference_collision_rate"] is None
    assert col["collision_rate_vs_dem"] is None
    from hel_warp.errors import ConfigError

    with pytest.raises(ConfigError, match="snapshot times differ"):
        ens.ensemble_metrics([runs[0], runs[2]], [runs[1]], min_samples=1)


def test_grouped_jackknife_of_a_mean_is_the_standard_error_of_the_group_means():
    """hel_warp.studies.rig_ensemble --jackknife-groups G: leaving out one of G equal contiguous groups at a time gives,
    for a mean, std(group means, ddof=1) / sqrt(G) (closed form); groups cover every run once; G >= n is the
    leave-one-out jackknife; fewer than 2 groups is refused."""
    ens = importlib.import_module("hel_warp.studies.rig_ensemble")
    from hel_warp.errors import ConfigError

    x = np.random.default_rng(7).normal(size=24)
    parts = ens.leave_out_groups(len(x), 6)
    assert sorted(k for g in parts for k in g) == list(range(24)) and all(len(g) == 4 for g in parts)
    estimates = [{"a": float(np.delete(x, g).mean())} for g in parts]
    means = x.reshape(6, 4).mean(axis=1)
    assert ens._leave_one_out_error(estimates)["a"] == pytest.approx(means.std(ddof=1) / np.sqrt(6), rel=1e-12)
    assert ens.leave_out_groups(5, None) == ens.leave_out_groups(5, 9) == [[k] for k in range(5)]
    uneven = ens.leave_out_groups(10, 3)
    assert sorted(k for g in uneven for k in g) == list(range(10)) and {len(g) for g in uneven} <= {3, 4}
    with pytest.raises(ConfigError, match="at least 2 groups"):
        ens.leave_out_groups(10, 1)
    assert ens.main(["--runs", "a", "--reference", "b", "--jackknife", "--jackknife-groups", "1"]) == 2


def test_collision_events_are_saved_and_match_the_run_s_counts(cs, tmp_path, capsys):
    # the dem's contact onsets of a short reduced run: the file's entries per step equal the run's own counters (an
    # exact bookkeeping check); scripts/collision_events.py reads it; none is refused at the door
    import zarr

    out, path = tmp_path / "dem", tmp_path / "events.npz"
    args = _args(out, "--collision-events", str(path), end_time="0.004")
    args[args.index("none")] = "dem"
    assert cs.main(args) == 0
    ev = np.load(path)
    series = zarr.open_group(str(out / "run.zarr"), mode="r")["series"]
    per_step = np.asarray(series["collisions_collisions"][...], np.int64)  # one entry per step
    assert len(ev["truncated_steps"]) == 0
    assert np.bincount(ev["step"], minlength=len(per_step)).tolist() == per_step.tolist()
    assert per_step.sum() > 0 and np.all(ev["particle_a"] < ev["particle_b"])
    assert np.all(np.isfinite(ev["radius_a"])) and np.all(ev["speed"] > 0)
    mod = load_file("collision_events", "scripts/collision_events.py")
    assert mod.summary(mod.load(str(path)))["all"]["count"] == per_step.sum()
    assert cs.main(_args(tmp_path / "none", "--collision-events", str(path))) == 2
    assert "--collision-events records the dem and surrogate collisions" in capsys.readouterr().err


def test_collision_events_script_counts_repeats_and_size_classes():
    # synthetic list: pair (1, 2) meets at 0, 0.5 ms and 5 ms -> two repeats, one within 1 ms; two size classes
    mod = load_file("collision_events", "scripts/collision_events.py")
    a, b = np.array([1, 1, 3, 1]), np.array([2, 2, 4, 2])
    t = np.array([0.0, 5e-4, 1e-3, 5e-3])
    rep, soon = mod.repeats(a, b, t)
    assert rep.tolist() == [False, True, False, True] and soon.tolist() == [False, True, False, False]
    d = {"particle_a": a, "particle_b": b, "time": t, "speed": np.array([1.0, 0.1, 2.0, 0.01]),
         "stream_a": np.array([0, 0, 0, 0]), "stream_b": np.array([1, 1, 0, 1]),
         "radius_a": np.array([1.0, 1.0, 2.0, 1.0]), "radius_b": np.array([2.0, 2.0, 2.0, 2.0])}
    res = mod.summary(d)
    assert res["streams 0-1"]["count"] == 3 and res["streams 0-1"]["repeat_share"] == pytest.approx(2 / 3)
    assert res["cross small-large"]["count"] == 3 and res["cross large-large"]["count"] == 0
    assert res["all"]["share_below_0.05"] == pytest.approx(0.25)


def test_bench_rig_refuses_a_missing_model_and_a_model_of_another_size_in_one_line(tmp_path, capsys):
    """scripts/bench_rig.py: a --model that is no trained directory is refused at the door, and a model the rig's
    own check refuses (another mean diameter, without --force-model) ends with one line and exit 2, no traceback."""
    bench = load_file("bench_rig_errors", "scripts/bench_rig.py")
    with pytest.raises(SystemExit) as exit_info:
        bench.main(["--models", "surrogate", "--model", str(tmp_path / "none")])
    assert exit_info.value.code == 2 and "metadata.json" in capsys.readouterr().err
    model = tmp_path / "model"
    model.mkdir()
    (model / "metadata.json").write_text(json.dumps({"form": "contact"}))
    code = bench.main(["--models", "surrogate", "--model", str(model), "--cells", "5000", "--max-particles", "10",
                       "--end-time", "0.002"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("bench_rig: error:") and "Traceback" not in err

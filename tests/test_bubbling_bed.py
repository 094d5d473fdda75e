"""The bubbling bed (cases/bubbling_bed.py) against the fixed- and fluidized-bed laws: below minimum fluidization a
settled bed stays settled and its pressure drop is Ergun's; above it the bed expands and its pressure drop is its
weight per area. A bed of 1,500 particles in a 9.6 mm square column (4 x 4 x 30 cells of 2.4 mm) keeps CI short;
the full bed is the case's default."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "cases"))

import bubbling_bed as bb  # noqa: E402

SMALL = ["--particles", "1500", "--width", "9.6e-3", "--depth", "9.6e-3", "--cells", "4,4,30", "--no-vtk",
         "--no-progress", "--json"]


def run_case(tmp_path, *args):
    out = tmp_path / "run"
    done = subprocess.run([sys.executable, str(ROOT / "cases" / "bubbling_bed.py"), *args, "--out", str(out)],
                          capture_output=True, text=True, cwd=ROOT, timeout=900)
    return done, out


@pytest.mark.parametrize("bad, message", [
    (["--velocity", "-0.1"], ">= 0 m/s"),
    (["--cells", "20,4,30"], "smaller than a particle"),
    (["--particles", "900000"], "fill more than 0.6"),
    (["--velocity", "0.1,0.2", "--hold", "0.1", "--end-time", "0.1"], "shorter than the levels need"),
    (["--distributor-noise", "1.5"], "must be in [0, 1)"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, bad, message):
    done, out = run_case(tmp_path, *SMALL, "--collisions", "none", "--end-time", "0.01", *bad)
    assert done.returncode == 2, done.stderr
    lines = [l for l in done.stderr.splitlines() if l.strip()]
    assert len(lines) == 1 and lines[0].startswith("hel-warp: error:") and message in lines[0], done.stderr
    assert not out.exists()


@pytest.mark.parametrize("collisions", ["none", "surrogate"])
def test_settled_below_and_fluidized_above_minimum_fluidization(collisions, tmp_path, monkeypatch):
    """Two levels, 0.3 and 2 U_mf (Wen-Yu, 0.342 m/s), each held 0.2 s. ``none``: the MP-PIC bed (no binary
    collisions: the packing stress and drag alone decide whether it holds or lifts). ``surrogate``: HELSCM with the
    cell detection the bed chooses, its model built on first use for these 1.2 mm spheres (an empty cache: the data
    set of DEM impacts and the training run inside the test, as for a new user); its binary collisions must neither
    collapse the settled bed nor keep it boiling below U_mf, nor hold it down above."""
    umf = bb.wen_yu_umf(1.2e-3, 1000.0)
    low, high = 0.3 * umf, 2.0 * umf
    if collisions == "surrogate":
        monkeypatch.setenv("HEL_WARP_CACHE", str(tmp_path / "cache"))
    done, out = run_case(tmp_path, *SMALL, "--collisions", collisions, "--velocity", f"{low},{high}", "--hold", "0.2")
    assert done.returncode == 0, done.stderr[-2000:]
    s = json.loads(done.stdout)  # one object: the automatic model's build reports on stderr
    if collisions == "surrogate":  # the automatic model, for these particles, and used by the collisions
        assert s["model"].startswith(str(tmp_path / "cache"))
        meta = json.loads((Path(s["model"]) / "metadata.json").read_text())
        assert meta["defaults"]["d1"] == pytest.approx(1.2e-3) and meta["defaults"]["rho1"] == pytest.approx(1000.0)
        assert s["collision_totals"]["cell_accepted"] > 0
    for key in ("levels", "bed_weight_per_area", "ergun_pressure_drop", "minimum_fluidization_velocity_wen_yu",
                "wall_clock_s", "particles", "parcels"):
        assert key in s
    weight = s["bed_weight_per_area"]
    # the weight per area from the inputs alone: N rho_p pi d^3 / 6 g / (W D)
    assert weight == pytest.approx(1500 * 1000 * math.pi / 6 * 1.2e-3**3 * 9.80665 / 9.6e-3**2, rel=1e-9)
    below, above = s["levels"]
    # below U_mf: the bed stays where it settled, give or take the compaction until the packing stress carries its
    # weight (twice the mean particle height; this 9.6 mm square column's poured cells beside the walls are looser
    # than the stress's onset)...
    assert 0.88 * s["settled_height"] < below["mean_height_x2"] < 1.02 * s["settled_height"]
    # ...and the gas pays Ergun's pressure drop at the bed's voidage, not its weight. Ergun is convex in eps_s and
    # the packing stress compacts the bottom more than the mean (the stress there carries the whole bed), so the
    # drop of the real bed lies above Ergun's at its mean voidage: between 0.8 and 1.5 of it.
    eps_s = s["settled_solids_fraction"] * s["settled_height"] / below["mean_height_x2"]
    ergun = bb.ergun(low, below["mean_height_x2"], 1 - eps_s, 1.2e-3)
    assert 0.8 * ergun < below["pressure_drop"] < 1.5 * ergun
    # Ergun's law integrated through the bed the level holds (each cell layer's time-averaged voidage): the drag and
    # the gas solver pay it within 10 %, the unevenness of the layers included
    layered = below["ergun_pressure_drop_layers"]
    assert below["pressure_drop"] == pytest.approx(layered, rel=0.10), (below["pressure_drop"], layered)
    assert below["pressure_drop"] < 0.7 * weight
    # above U_mf: the bed is lifted and expands; the gas carries its weight (a fluidized bed's drop is W / A,
    # within 15 %: the plug oscillations of a narrow column, averaged over the level's second half)
    assert above["pressure_drop"] == pytest.approx(weight, rel=0.15)
    assert above["mean_height_x2"] > 1.05 * s["settled_height"]
    assert s["parcels"] == 1500
    for name in ("bed_snapshots.png", "bed_solids_fraction.png", "bed_history.png", "bed_fluidization.png"):
        assert (out / name).stat().st_size > 10_000


def test_the_measured_minimum_fluidization_is_where_ergun_meets_the_weight():
    """A curve made of Ergun's law below and the bed weight above: the branches meet where Ergun's drop equals the
    weight, the root of a quadratic solved here independently; with one fixed level, where that level's line
    through the origin meets the weight."""
    height, voidage, d = 0.035, 0.42, 1.2e-3
    weight = 197.7
    a = height * 150.0 * bb.GAS_VISCOSITY * (1 - voidage) ** 2 / (voidage**3 * d**2)
    b = height * 1.75 * bb.GAS_DENSITY * (1 - voidage) / (voidage**3 * d)
    exact = (-a + math.sqrt(a * a + 4 * b * weight)) / (2 * b)
    levels = [0.1, 0.2, 0.3, 0.45, 0.6, 0.8, 1.0]
    drops = [bb.ergun(u, height, voidage, d) if bb.ergun(u, height, voidage, d) < weight else weight for u in levels]
    assert bb.measured_umf(levels, drops, weight) == pytest.approx(exact, rel=1e-9)
    assert bb.measured_umf(levels[:1] + levels[3:], drops[:1] + drops[3:], weight) == pytest.approx(
        weight * levels[0] / drops[0], rel=1e-12)
    # a slug that hits the top of the box (one level's mean at 2.8 times the weight) leaves the meeting point
    assert bb.measured_umf(levels, drops[:-1] + [2.8 * weight], weight) == pytest.approx(exact, rel=1e-9)
    assert bb.measured_umf(levels[:3], drops[:3], weight) is None  # no level on the plateau
    assert bb.measured_umf(levels[3:], drops[3:], weight) is None  # no level on the fixed branch


def test_the_error_of_a_level_mean_follows_the_correlation_of_its_fluctuations():
    """The standard error of the mean of a correlated series against its analytic value: white noise sigma / sqrt(n);
    an AR(1) series x_k = phi x_(k-1) + noise has the integrated autocorrelation time (1 + phi) / (2 (1 - phi))
    samples, so its mean's error is sigma sqrt((1 + phi) / ((1 - phi) n)) (Sokal 1997). A pure sine over whole
    periods has no error at all; the estimate stays below its standard deviation."""
    rng = np.random.default_rng(7)
    n, sigma = 40_000, 3.0
    white = rng.normal(0.0, sigma, n)
    assert bb.mean_error(white) == pytest.approx(sigma / math.sqrt(n), rel=0.1)
    phi = 0.8
    x = np.empty(n)
    x[0] = 0.0
    kicks = rng.normal(0.0, 1.0, n)
    for k in range(1, n):
        x[k] = phi * x[k - 1] + kicks[k]
    exact = x.std() * math.sqrt((1 + phi) / ((1 - phi) * n))
    assert bb.mean_error(x) == pytest.approx(exact, rel=0.2)
    sine = np.sin(2 * np.pi * np.arange(100) / 100)  # one period in the window, as a 5 Hz bed in 0.2 s
    assert 0.1 * sine.std() < bb.mean_error(sine) <= sine.std()
    assert bb.mean_error([5.0]) is None and bb.mean_error([2.0, 2.0, 2.0]) == 0.0


def test_the_comparison_measures_profile_distances_and_costs_against_the_reference():
    """``scripts/bed_report.py``'s comparison on made-up runs: a profile is at distance 0 from itself and at |c|
    from itself shifted by c (the RMS of a constant), one sampled on other x is interpolated onto the reference's;
    a run is matched at the reference's last velocity; the cost ratio is the reference's wall clock per simulated
    second over the run's."""
    sys.path.insert(0, str(ROOT / "scripts"))
    import bed_report

    x = [0.0012 * (2 * k + 1) for k in range(6)]
    base = [0.5 - 0.05 * k for k in range(6)]

    def run(name, shift, wall, velocity=0.66, points=x):
        values = [0.5 - 0.05 * (p / 0.0024 - 0.5) + shift for p in points]
        level = {"velocity": velocity, "bed_height": 0.05, "mean_height_x2": 0.045, "pressure_drop": 190.0,
                 "pressure_drop_std": 10.0, "pressure_frequency": 3.0,
                 "solids_fraction_profiles": {"0.01": list(map(list, zip(points, values)))}}
        return None, {"collision_model": name, "levels": [{**level, "velocity": 0.3}, level], "wall_clock_s": wall,
                      "simulated_time": 2.0, "bed_weight_per_area": 197.7}

    assert bed_report.profile_distance(list(zip(x, base)), list(zip(x, base))) == 0.0
    fine = [0.0006 * k for k in range(25)]  # the same straight line on other points, across the whole width
    result = bed_report.compare([run("dem", 0.0, 2000.0), run("surrogate", 0.03, 100.0),
                                 run("ktgf", 0.0, 50.0, points=fine), run("none", 0.0, 40.0, velocity=0.9)], 0)
    rows = {r["run"]: r for r in result["runs"]}
    assert set(rows) == {"dem", "surrogate", "ktgf"}  # none ran no level at 0.66 m/s
    assert rows["dem"]["profile_rms"]["0.01"] == 0.0 and rows["dem"]["reference"]
    assert rows["surrogate"]["profile_rms"]["0.01"] == pytest.approx(0.03, rel=1e-12)
    assert rows["ktgf"]["profile_rms"]["0.01"] == pytest.approx(0.0, abs=1e-9)
    assert rows["surrogate"]["reference_cost_ratio"] == pytest.approx(20.0)
    assert rows["surrogate"]["wall_clock_per_simulated_s"] == pytest.approx(50.0)
    assert "eps_s RMS at 10 mm" in bed_report.comparison_table(result)


def test_the_distributor_noise_keeps_the_superficial_velocity():
    """``--distributor-noise A``: per face 1 + A (u - mean u), u uniform in [-1, 1]: the factors average exactly 1
    (the superficial velocity is the schedule's), lie within 1 +- 2A, vary across the faces, and repeat for a
    seed."""
    faces = np.random.default_rng(3).uniform(0.0, 0.04, (72, 3))
    f = bb.distributor_noise(0.2, 5)(faces)
    assert f.mean() == pytest.approx(1.0, abs=1e-14) and np.all(np.abs(f - 1.0) <= 0.4) and f.std() > 0.05
    assert np.array_equal(f, bb.distributor_noise(0.2, 5)(faces))
    assert not np.array_equal(f, bb.distributor_noise(0.2, 6)(faces))


def test_the_noise_floor_of_a_profile_distance_is_the_error_of_its_average():
    """``scripts/bed_report.py``'s ``profile_noise`` on a made-up probe series: a fixed profile plus white noise of
    sigma per point and sample, n samples in the window, has its average uncertain by sigma / sqrt(n) at each point
    (the analytic error of a mean); the estimate from the window's two halves finds it within 10 %, and a series
    without noise has none. The floor of two such runs is their errors in quadrature."""
    sys.path.insert(0, str(ROOT / "scripts"))
    import bed_report

    rng = np.random.default_rng(11)
    n, cells, sigma = 4000, 400, 0.05
    t = np.linspace(1.0, 2.0, n)
    shape = 0.5 + 0.1 * np.sin(np.linspace(0.0, np.pi, cells))

    def root(noise):
        return {"probes": {"profile_10mm": {"time": t, "solids_fraction": shape + noise * rng.normal(size=(n, cells))}}}

    level = {"window": [1.0, 2.0], "velocity": 0.66}
    assert bed_report.profile_noise(root(sigma), level, "0.01") == pytest.approx(sigma / math.sqrt(n), rel=0.1)
    assert bed_report.profile_noise(root(0.0), level, "0.01") == pytest.approx(0.0, abs=1e-12)
    assert bed_report.profile_noise(None, level, "0.01") is None
    assert bed_report.profile_noise(root(sigma), level, "0.02") is None  # no probe at 20 mm
    x = [[0.001 * k, float(v)] for k, v in enumerate(shape)]
    summary = {"collision_model": "dem", "wall_clock_s": 10.0, "simulated_time": 2.0, "bed_weight_per_area": 197.7,
               "levels": [{**level, "bed_height": 0.05, "mean_height_x2": 0.045, "pressure_drop": 190.0,
                           "pressure_drop_std": 10.0, "pressure_frequency": 3.0,
                           "solids_fraction_profiles": {"0.01": x}}]}
    result = bed_report.compare([(root(sigma), summary), (root(sigma), {**summary, "collision_model": "ktgf"})], 0)
    floors = {r["run"]: r["profile_noise_floor"] for r in result["runs"]}
    assert floors["dem"] == {}
    assert floors["ktgf"]["0.01"] == pytest.approx(math.sqrt(2.0) * sigma / math.sqrt(n), rel=0.1)

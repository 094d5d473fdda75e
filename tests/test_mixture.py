"""Binary size mixtures: the data set's pair types, the mixture CLI, the kinetic theory of a mixture,
a two-size binary collision against the closed form, and the per-species outputs of the cooling case.

References used below:
- pair types of a mixture: number fractions x_i = (w_i / E[d_i^3]) / sum, rows of type (i, j) in proportion
  x_i x_j E[(d_i + d_j)^2] (the collision rate n_i n_j pi sigma_ij^2 <|g|> with one velocity distribution for
  every size; surrogate/configurations.py);
- frictionless central impact of unequal masses (docs/physics/references.md "Binary collision outcome"):
  v1' = v1 - (1 + e) m2/(m1 + m2) (g.n) n, v2' = v2 + (1 + e) m1/(m1 + m2) (g.n) n, with e the DEM's own
  restitution measured on an equal pair (its damping depends on the damping constant alone, not on sizes or masses);
- one species of the mixture kinetic theory is Haff's law, dTheta/dt = -8 (1 - e^2) g0 eps Theta^(3/2) / (sqrt(pi) d),
  and the Enskog frequency 24 eps g0 sqrt(Theta) / (sqrt(pi) d); elastic collisions exchange energy, lose none.
"""

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
D1, D2 = 315e-6, 475e-6
S1, S2 = 8.2e-6, 22e-6


# ------------------------------------------------------------------------------------------ data set
def test_pair_types_follow_the_collision_proportion():
    from surrogate.configurations import generate
    from surrogate.dataset import make_spec

    spec = make_spec(samples=10, seed=0, diameter=3.6e-4, diameter_std=0.0, mixture_diameters=(D1, D2),
                     mixture_mass_fractions=(0.5, 0.5)).configurations
    # the closed form, from the mass fractions (not from the spec's own functions)
    cube = np.array([D1**3 + 3 * D1 * S1**2, D2**3 + 3 * D2 * S2**2])
    x = (np.array([0.5, 0.5]) / cube) / (np.array([0.5, 0.5]) / cube).sum()
    cross = lambda i, j: ((D1, D2)[i] + (D1, D2)[j]) ** 2 + ((S1, S2)[i] ** 2 + (S1, S2)[j] ** 2)  # noqa: E731
    weights = {"ss": x[0] ** 2 * cross(0, 0), "sl": 2 * x[0] * x[1] * cross(0, 1), "ll": x[1] ** 2 * cross(1, 1)}
    total = sum(weights.values())
    expected = {k: v / total for k, v in weights.items()}
    assert expected["ss"] == pytest.approx(0.475, abs=0.002) and expected["ll"] == pytest.approx(0.091, abs=0.002)
    n = 16384
    c = generate(spec, 7, 0, n)
    big1, big2 = c.d1 > 395e-6, c.d2 > 395e-6
    measured = {"ss": np.mean(~big1 & ~big2), "sl": np.mean(big1 != big2), "ll": np.mean(big1 & big2)}
    for k in expected:  # binomial standard error, 4 sigma
        assert abs(measured[k] - expected[k]) < 4 * math.sqrt(expected[k] * (1 - expected[k]) / n), (k, measured)
    # cross pairs carry either label order with equal chance (the set stays symmetric in the labels)
    sl = big1 != big2
    assert abs(np.mean(big2[sl]) - 0.5) < 4 * math.sqrt(0.25 / sl.sum())
    # each species keeps its size distribution
    assert abs(c.d1[~big1].mean() - D1) < 0.5e-6 and abs(c.d1[~big1].std() - S1) < 0.5e-6
    assert abs(c.d1[big1].mean() - D2) < 2e-6 and abs(c.d1[big1].std() - S2) < 2e-6


def _dataset_cli(capsys, *args):
    """``hel-warp dataset ARGS`` in this process: (exit code, stderr)."""
    from hel_warp.cli import main

    try:
        code = main(["dataset", *args])
    except SystemExit as exc:  # argparse
        code = exc.code
    return code, capsys.readouterr().err


@pytest.mark.parametrize("extra,needle", [
    (["--diameters", "315e-6,475e-6", "--mass-fractions", "0.5,0.6"], "sum to 1"),
    (["--diameters", "315e-6,475e-6", "--mass-fractions", "0.5,0.25,0.25"], "3 values for 2"),
    (["--diameters", "315e-6,475e-6", "--diameter-stds", "8.2e-6"], "1 values for 2"),
    (["--diameters", "315e-6,-475e-6"], "> 0"),
    (["--diameters", "315e-6,475e-6", "--diameter-stds", "8.2e-6,-1e-6"], ">= 0"),
    (["--diameters", "315e-6,475e-6", "--mass-fractions", "1.5,-0.5"], "> 0"),
    (["--diameters", "315e-6"], "at least two"),
    (["--diameters", "315e-6,475e-6", "--mixture", "315e-6,475e-6"], "not both"),
    (["--diameters", "315e-6,475e-6", "--diameter", "315e-6"], "replaces --diameter"),
    (["--mass-fractions", "0.5,0.5"], "go with --diameters"),
])
def test_dataset_mixture_bad_input_is_one_line_exit_2(tmp_path, capsys, extra, needle):
    code, err = _dataset_cli(capsys, "--out", str(tmp_path / "set"), "--samples", "10", *extra)
    lines = [line for line in err.strip().splitlines() if line and "CUDA" not in line]
    assert code == 2, err
    assert len(lines) == 1 and "error" in lines[0] and needle in lines[0], err
    assert not (tmp_path / "set").exists()


def test_mixture_option_is_deprecated_but_keeps_its_rows(tmp_path, capsys):
    """--mixture still writes its earlier set (equal chance per particle), with a warning naming --diameters."""
    from surrogate.dataset import load_dataset, make_spec
    from surrogate.configurations import generate

    code, err = _dataset_cli(capsys, "--out", str(tmp_path / "old"), "--samples", "64", "--chunk-size", "64",
                             "--mixture", "315e-6,475e-6", "--no-progress", "--friction", "0")
    assert code == 0, err
    assert "deprecated" in err and "--diameters" in err
    ds = load_dataset(tmp_path / "old")
    spec = make_spec(samples=64, seed=0, diameter=315e-6, mixture_diameters=(D1, D2)).configurations
    c = generate(spec, 0, 0, 64)
    np.testing.assert_array_equal(ds.inputs[:, 6], c.d1)
    assert "mixture_mass_fractions" not in ds.attrs["configuration"]


# ------------------------------------------------------------------------------------------ metrics per pair type
@pytest.fixture(scope="module")
def mixture_model(tmp_path_factory):
    """(model dir, spec): a tiny frictionless contact-form model of the 315/475 um mixture (2,000 DEM rows, 1 trial,
    30-40 trees, no sweep: CI time)."""
    from hel_warp.material import Material
    from surrogate import train as T
    from surrogate.dataset import build_dataset, make_spec
    from surrogate.features import load_collision_data

    root = tmp_path_factory.mktemp("tiny_mixture_model")
    spec = make_spec(samples=2000, seed=1, diameter=3.6e-4, diameter_std=0.0, material=Material(friction=0.0),
                     chunk_size=2000, mixture_diameters=(D1, D2), mixture_mass_fractions=(0.5, 0.5))
    build_dataset(root / "data", spec, progress=False, overwrite=True)
    data = load_collision_data(str(root / "data"))
    saved = T.SEARCH_SPACE["n_estimators"]
    T.SEARCH_SPACE["n_estimators"] = (30, 40)
    try:
        T.train(data, str(root / "model"), T.TrainConfig(form="contact", trials=1, jobs=1, progress=False,
                                                          report=False, sweep=False))
    finally:
        T.SEARCH_SPACE["n_estimators"] = saved
    return root / "model", spec


def test_metrics_per_pair_type(mixture_model):
    """A tiny mixture model's metrics.json reports small-small / small-large / large-large with their shares."""
    model, spec = mixture_model
    metrics = json.loads((model / "metrics.json").read_text())
    types = metrics["pair_types"]
    assert list(types) == ["small-small", "small-large", "large-large"]
    assert sum(t["rows"] for t in types.values()) == metrics["n_test_rows"]
    p = spec.configurations.mixture_pair_probabilities()
    expected = {"small-small": p[0, 0], "small-large": p[0, 1] + p[1, 0], "large-large": p[1, 1]}
    n = metrics["n_test_rows"]
    for name, row in types.items():
        assert abs(row["share"] - expected[name]) < 4 * math.sqrt(expected[name] * (1 - expected[name]) / n)
        assert 0 <= row["g_error_pct_median"] <= row["g_error_pct_p99"] <= row["g_error_pct_max"]
    assert types["small-large"]["diameters_um"] == [315.0, 475.0]


# ------------------------------------------------------------------------------------------ two-size collision
def _central_pair(d1, d2, speed, restitution=0.9):
    """A frictionless central impact in the DEM of ``hel-warp impact`` (simulate_pairs), COM frame plus a drift."""
    from hel_warp.collisions.impact import place_just_apart, simulate_pairs, stable_time_step
    from hel_warp.material import Material

    mat = Material(friction=0.0)
    r1, r2 = np.array([d1 / 2]), np.array([d2 / 2])
    m1, m2 = d1**3, d2**3
    g = np.array([[0.0, 0.0, -speed]])
    drift = np.array([[0.3, -0.2, 0.1]])
    v1, v2 = m2 / (m1 + m2) * g + drift, -m1 / (m1 + m2) * g + drift
    dt = min(stable_time_step(r, 1000.0, mat.youngs_modulus, mat.poisson_ratio, 20.0) for r in (r1, r2))
    x1, x2 = place_just_apart(normal=np.array([[0.0, 0.0, -1.0]]), velocity1=v1, velocity2=v2, radius1=r1,
                              radius2=r2, dt=dt)
    res = simulate_pairs(x1=x1, x2=x2, v1=v1, v2=v2, radius1=r1, radius2=r2, density1=1000.0, density2=1000.0,
                         youngs1=mat.youngs_modulus, poisson1=mat.poisson_ratio, restitution=restitution,
                         friction=0.0)
    return v1[0], v2[0], res.velocity1[0], res.velocity2[0]


@pytest.mark.parametrize("speed", [0.1, 2.0, 20.0])
def test_two_size_central_impact_matches_the_closed_form(speed):
    from hel_warp._warp import init_warp

    init_warp()
    # the DEM's own restitution, from an equal 315 um pair at this speed
    v1, v2, u1, u2 = _central_pair(D1, D1, speed)
    e = (u1[2] - u2[2]) / (v2[2] - v1[2])
    assert e == pytest.approx(0.9, rel=2e-3)  # the damping calibration (dt_factor 0.5: <= 0.3 %)
    v1, v2, u1, u2 = _central_pair(D1, D2, speed)
    m1, m2 = D1**3, D2**3
    n = np.array([0.0, 0.0, -1.0])
    gn = float(np.dot(v1 - v2, n))
    expect1 = v1 - (1 + e) * m2 / (m1 + m2) * gn * n
    expect2 = v2 + (1 + e) * m1 / (m1 + m2) * gn * n
    # float32 state: round-off ~1e-7 of the speeds; the restitution of the unequal pair equals the equal pair's
    tol = 2e-5 * speed + 1e-6
    np.testing.assert_allclose(u1, expect1, atol=tol)
    np.testing.assert_allclose(u2, expect2, atol=tol)
    # momentum m1 v1 + m2 v2 conserved
    np.testing.assert_allclose(m1 * u1 + m2 * u2, m1 * v1 + m2 * v2, atol=1e-6 * (m1 + m2) * speed)


# ------------------------------------------------------------------------------------------ kinetic theory
def test_mixture_kinetic_theory_reduces_to_haff_and_enskog():
    from hel_warp.collisions import mixture as mx

    d, eps, e, theta = 315e-6, 0.01, 0.9, 1.3
    m = 1000.0 * math.pi * d**3 / 6
    n = 6 * eps / (math.pi * d**3)
    g0_cs = (1 - eps / 2) / (1 - eps) ** 3
    # one size split into two equal "species": the mixture formulas must give one species' results
    dens, diam, mass, th = [n / 2, n / 2], [d, d], [m, m], [theta, theta]
    assert mx.contact_g0(dens, diam) == pytest.approx(np.full((2, 2), g0_cs), rel=1e-12)
    rate = mx.temperature_rates(dens, diam, mass, th, e)
    haff = -8 * (1 - e**2) * g0_cs * eps * theta**1.5 / (math.sqrt(math.pi) * d)
    assert rate == pytest.approx([haff, haff], rel=1e-12)
    per_particle = 2 * mx.collision_rates(dens, diam, mass, th).sum() / n
    assert per_particle == pytest.approx(24 * eps * g0_cs * math.sqrt(theta) / (math.sqrt(math.pi) * d), rel=1e-12)


def test_mixture_kinetic_theory_conserves_energy_when_elastic_and_equilibrates():
    from hel_warp.collisions import mixture as mx

    dens, diam = [2e6, 5e5], [D1, D2]
    mass = [1000.0 * math.pi * d**3 / 6 for d in diam]
    theta = [1.0, 0.1]  # T_1 = m_1 Theta_1 < T_2? no: m_2 / m_1 = 3.4, so T_2 = 0.34 T_1: out of equipartition
    rate = mx.temperature_rates(dens, diam, mass, theta, 1.0)
    energy_rate = sum(r * n_ * m_ for r, n_, m_ in zip(rate, dens, mass))
    assert abs(energy_rate) < 1e-12 * sum(abs(r) * n_ * m_ for r, n_, m_ in zip(rate, dens, mass))
    assert rate[0] < 0 < rate[1]  # energy flows from the hotter species (T = m Theta) to the colder
    # at equipartition and e = 1 nothing changes
    eq = [1.0, mass[0] / mass[1]]
    assert mx.temperature_rates(dens, diam, mass, eq, 1.0) == pytest.approx([0.0, 0.0], abs=1e-9)
    # the Sauter mean of the two sizes
    assert mx.sauter_mean([0.7, 0.3], diam, [0, 0]) == pytest.approx((0.7 * D1**3 + 0.3 * D2**3)
                                                                      / (0.7 * D1**2 + 0.3 * D2**2))
    x = mx.number_fractions([0.5, 0.5], diam, [0, 0])
    assert x[1] / x[0] == pytest.approx((D1 / D2) ** 3)
    assert mx.mass_fractions(x, diam, [0, 0]) == pytest.approx([0.5, 0.5])


# ------------------------------------------------------------------------------------------ the report per size class
SECTIONS = [{"name": f"S{k + 1}", "lo": [float(k), 0.0, 0.0], "hi": [float(k + 1), 1.0, 1.0]} for k in range(10)]


def _mixture_run(path, collisions, parcels, *, mixture=True, times=(0.002, 0.003, 0.004)):
    """A run directory in the layout of cases/colliding_streams.py: ``parcels`` (x, v, radius, stream) in every
    snapshot; the rig names its size classes (315 / 475 um) when ``mixture``."""
    from hel_warp.runs.io import RunWriter

    rig = {"axial_axis": 0, "transverse_axis": 1, "downstream": [1.0, 0.0, 0.0], "sections": SECTIONS,
           "domain_lo": [0.0, 0.0, 0.0], "domain_hi": [10.0, 1.0, 1.0], "main_depth": 1.0,
           "size_classes": ([{"diameter": D1, "diameter_std": S1, "parcels": 1},
                             {"diameter": D2, "diameter_std": S2, "parcels": 1}] if mixture else None)}
    sizes = {"diameter2": D2, "mass_fraction2": 0.5} if mixture else {}
    case = {"case": "synthetic", "collisions": collisions, "dt": 1e-3, "diameter": D1, "rig": rig, **sizes}
    summary = {"collisions": collisions, "dt": 1e-3, "diameter": D1, "end_time": 0.004, "simulated_time": 0.004,
               "wall_clock_s": 1.0, "status": "complete", **sizes}
    writer = RunWriter(path, config={"hel": {"dt": 1e-3}, "collision": {"name": collisions}, "case": case}, vtk=False)
    writer.root.attrs["summary"] = summary
    for step, t in enumerate(times, start=1):
        writer.write_snapshot({"x": np.array([p[0] for p in parcels], np.float32),
                               "v": np.array([p[1] for p in parcels], np.float32),
                               "radius": np.array([p[2] for p in parcels], np.float32),
                               "weight": np.ones(len(parcels), np.float32),
                               "stream": np.array([p[3] for p in parcels], np.int32)}, time=t, step=step)
    return str(path)


def _placement(small_cross: float, large_cross: bool, u_small: float, u_large: float):
    """In every section: the small parcels of each stream on their own side (left y > 0.5) or a share crossed, the
    large ones all on their own side or all across, with axial velocities u_small / u_large."""
    out = []
    for k in range(10):
        for stream, own in ((0, 0.75), (1, 0.25)):
            far = 1.0 - own
            out.append(([k + 0.5, own, 0.5], [u_small, 1.0, 0.0], 0.5 * (D1 + 3e-6), stream))
            out.append(([k + 0.5, far if small_cross else own, 0.5], [u_small, -1.0, 0.0], 0.5 * (D1 - 5e-6), stream))
            out.append(([k + 0.5, far if large_cross else own, 0.5], [u_large, 2.0, 0.0], 0.5 * (D2 + 10e-6), stream))
    return out


def test_report_splits_a_mixture_by_size_class(tmp_path):
    """Small parcels: half of each stream across (crossing 0.5), axial 3 m/s; large: all across (1.0), 6 m/s,
    v_y 2 m/s. The dem reference of the same mixture: nobody crosses, axial 3 and 5 m/s. Per class the report must
    give these answers, the whole run their parcel-weighted mix; a one-size dem run is not the reference."""
    from hel_warp.runs.report import build_report

    sur = _mixture_run(tmp_path / "sur", "surrogate", _placement(True, True, 3.0, 6.0))
    dem = _mixture_run(tmp_path / "dem", "dem", _placement(False, False, 3.0, 5.0))
    single = _mixture_run(tmp_path / "dem315", "dem", _placement(False, False, 0.0, 0.0), mixture=False)
    report, _ = build_report([sur, dem, single], boxes=[2], min_samples=1)
    entry = next(e for e in report["runs"] if e["label"] == "sur")
    assert entry["dem_reference"] == "dem" and entry["sizes"].startswith("315/475 um")
    small, large = entry["size_classes"]
    assert (small["label"], large["label"]) == ("315 um", "475 um")
    assert small["stream_metrics"]["stream_crossing"] == pytest.approx(0.5)
    assert large["stream_metrics"]["stream_crossing"] == pytest.approx(1.0)
    assert entry["stream_metrics"]["stream_crossing"] == pytest.approx(2.0 / 3.0)  # 2 of the 3 parcels of a stream
    assert small["stream_crossing_vs_dem"]["difference"] == pytest.approx(0.5)
    assert large["stream_crossing_vs_dem"]["difference"] == pytest.approx(1.0)
    # v_y rms: small sqrt((1 + 1)/2) = 1, large 2 (the same in both runs)
    assert small["stream_metrics"]["transverse_velocity_rms"] == pytest.approx(1.0)
    assert large["stream_metrics"]["transverse_velocity_rms"] == pytest.approx(2.0)
    assert large["transverse_velocity_rms_vs_dem"]["relative_difference"] == pytest.approx(0.0, abs=1e-6)
    # axial profiles: small 3 vs 3 -> RMS 0 where both fill a box; large 6 vs 5 -> 1 m/s
    assert small["profile_rms_vs_dem"]["2"] == pytest.approx(0.0, abs=1e-6)
    assert large["profile_rms_vs_dem"]["2"] == pytest.approx(1.0)
    assert small["paper_experimental_uncertainty"] == 0.63 and large["paper_experimental_uncertainty"] == 0.71
    rows = [r for r in report["summary_table"] if r["label"].startswith("sur")]
    assert [r["model"] for r in rows] == ["surrogate", "surrogate [315 um]", "surrogate [475 um]"]


# ------------------------------------------------------------------------------------------ the cooling box
@pytest.fixture(scope="module")
def hc():
    from hel_warp.cli.commands._common import load_case_module

    return load_case_module(str(ROOT / "cases" / "homogeneous_cooling.py"))


def _cooling(hc, capsys, tmp_path, *extra, particles=400, eps="0.01", dt="1e-4", end="1e-3"):
    argv = ["--dt", dt, "--solids-fraction", eps, "--particles", str(particles), "--diameter", str(D1),
            "--diameter2", str(D2), "--number-fraction2", "0.3", "--granular-temperature", "1", "--end-time", end,
            "--out", str(tmp_path / "run"), "--json", "--no-progress", *extra]
    try:
        code = hc.main([str(a) for a in argv])
    except SystemExit as exc:
        code = exc.code
    out = capsys.readouterr()
    return code, (json.loads(out.out) if code == 0 else None), out.err


def test_cooling_mixture_start_and_species_outputs(hc, capsys, tmp_path):
    """``none``: the start is at equipartition (m_1 Theta_1 = m_2 Theta_2) with the mixture's mass-weighted Theta
    exactly Theta0, the species counts are round(F N), the box holds their volume at eps_s, no two spheres overlap
    (brute force over all pairs, sum of the radii), and ballistic flight keeps every temperature."""
    code, s, err = _cooling(hc, capsys, tmp_path, "--collisions", "none")
    assert code == 0, err
    m1, m2 = D1**3, D2**3
    n2 = round(0.3 * 400)
    assert s["species"]["particles"] == [400 - n2, n2]
    assert s["box_length"] == pytest.approx((math.pi * ((400 - n2) * D1**3 + n2 * D2**3) / (6 * 0.01)) ** (1 / 3))
    t1, t2 = s["granular_temperature_1_initial"], s["granular_temperature_2_initial"]
    assert m1 * t1 == pytest.approx(m2 * t2, rel=1e-6) and s["temperature_ratio_final"] == pytest.approx(1.0, rel=1e-6)
    mix = ((400 - n2) * m1 * t1 + n2 * m2 * t2) / ((400 - n2) * m1 + n2 * m2)
    assert mix == pytest.approx(1.0, rel=1e-6) and s["granular_temperature_initial"] == pytest.approx(1.0, rel=1e-6)
    assert len(s["granular_temperature_1"]) == len(s["time"]) == len(s["granular_temperature_2"])
    assert s["granular_temperature_2_final"] == pytest.approx(t2, rel=1e-6) and s["collisions"] == 0
    # no overlap at the start (the case's own start, rebuilt from its config)
    args = argparse_args(hc, tmp_path)
    config = hc.make_config(args)
    x, _ = hc.initial_state(config)
    radius = 0.5 * np.asarray(config.species.diameters)[hc.mixture_labels(config)]
    sep = x[:, None, :] - x[None, :, :]
    sep -= config.box_length * np.round(sep / config.box_length)
    gap = np.sqrt((sep**2).sum(axis=2)) - (radius[:, None] + radius[None, :])
    gap[np.diag_indices(len(x))] = np.inf
    assert gap.min() > 0


def argparse_args(hc, tmp_path):
    import argparse

    parser = argparse.ArgumentParser()
    hc.add_arguments(parser)
    return parser.parse_args(["--collisions", "none", "--dt", "1e-4", "--solids-fraction", "0.01", "--particles",
                              "400", "--diameter", str(D1), "--diameter2", str(D2), "--number-fraction2", "0.3",
                              "--granular-temperature", "1", "--end-time", "1e-3", "--out", str(tmp_path / "x")])


@pytest.mark.parametrize("extra,needle", [
    (["--collisions", "none", "--number-fraction2", "1.2"], "must lie in (0, 1)"),
    (["--collisions", "none", "--diameter2=-1e-6"], "must be > 0"),
])
def test_cooling_mixture_bad_input_is_one_line_exit_2(hc, capsys, tmp_path, extra, needle):
    code, _, err = _cooling(hc, capsys, tmp_path, *extra)
    lines = [line for line in err.strip().splitlines() if line and "CUDA" not in line]
    assert code == 2 and len(lines) == 1 and needle in lines[0], err


def test_cooling_mixture_needs_both_options(hc, capsys, tmp_path):
    argv = ["--collisions", "none", "--dt", "1e-4", "--solids-fraction", "0.01", "--particles", "400", "--diameter",
            str(D1), "--diameter2", str(D2), "--granular-temperature", "1", "--end-time", "1e-3", "--out",
            str(tmp_path / "run")]
    assert hc.main(argv) == 2
    assert "needs both --diameter2 and --number-fraction2" in capsys.readouterr().err


def test_cooling_mixture_refuses_a_one_size_model(hc, capsys, tmp_path, mixture_model):
    """A model whose training domain lacks the second size is refused (here: the mixture model asked for 600 um)."""
    model, _ = mixture_model
    argv = ["--collisions", "surrogate", "--model", str(model), "--dt", "1e-4", "--solids-fraction", "0.01",
            "--particles", "400", "--diameter", str(D1), "--diameter2", "600e-6", "--number-fraction2", "0.3",
            "--granular-temperature", "1", "--end-time", "1e-3", "--out", str(tmp_path / "run")]
    assert hc.main(argv) == 2
    assert "600 um" in capsys.readouterr().err


def test_swept_surrogate_meets_each_pair_type_at_the_kinetic_theory_rate(hc, capsys, tmp_path, mixture_model):
    """HELSCM (swept) on a 315/475 um mixture: the collisions of each pair type against the Enskog rate of a binary
    mixture, n_i n_j g0_ij pi sigma_ij^2 sqrt(8/pi) sqrt(Theta_i + Theta_j) over the measured Theta_i(t) (BMCSL g0),
    within 4 standard errors (1/sqrt(C)); momentum conserved; T_2/T_1 leaves 1 (the start is at equipartition)."""
    model, _ = mixture_model
    code, s, err = _cooling(hc, capsys, tmp_path, "--collisions", "surrogate", "--model", str(model),
                            particles=1000, eps="0.05", dt="1e-4", end="2e-3")
    assert code == 0, err
    assert s["check_errors"] == [] and s["momentum_drift"] < 1e-5
    for name, row in s["collision_pair_types"].items():
        assert row["collisions"] > 50, (name, row)
        assert abs(row["ratio"] - 1.0) < 4 * row["ratio_stderr"], (name, row)
    total = sum(row["collisions"] for row in s["collision_pair_types"].values())
    assert total == s["collisions"]
    assert abs(s["collision_frequency_ratio"] - 1.0) < 4 * s["collision_frequency_ratio_stderr"]
    assert s["granular_temperature_final"] < s["granular_temperature_initial"]


# ------------------------------------------------------------------------------------------ the rig
@pytest.fixture(scope="module")
def cs():
    import importlib.util

    spec = importlib.util.spec_from_file_location("colliding_streams_mixture", ROOT / "cases" / "colliding_streams.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["colliding_streams_mixture"] = module
    spec.loader.exec_module(module)
    return module


def _rig_args(cs, *extra):
    import argparse

    parser = argparse.ArgumentParser()
    cs.add_arguments(parser)
    return parser.parse_args(["--diameter", str(D1), "--dt", "1e-3", "--collisions", "none", "--end-time", "0.003",
                              "--out", "unused", *extra])


def test_rig_mixture_release_splits_the_mass(cs):
    """50/50 by mass of the paper's one-size mass (12,000 x E[d^3] at 315 um): parcels per species = mass / mean
    particle mass; the Sauter mean that KTGF gets; the holders' flows the mass-fraction mix of the paper's."""
    config = cs.make_config(_rig_args(cs, "--diameter2", str(D2), "--mass-fraction2", "0.5"))
    cube1, cube2 = D1**3 + 3 * D1 * S1**2, D2**3 + 3 * D2 * S2**2
    assert config.particles == round(0.5 * 12000)
    assert config.particles2 == round(0.5 * 12000 * cube1 / cube2)
    mass1, mass2 = config.particles * cube1, config.particles2 * cube2
    assert mass2 / (mass1 + mass2) == pytest.approx(0.5, abs=2e-4)
    assert config.mass_flow == pytest.approx((0.0135, 0.0185))
    sauter = (config.particles * cube1 + config.particles2 * cube2) / (config.particles * (D1**2 + S1**2)
                                                                       + config.particles2 * (D2**2 + S2**2))
    assert cs.sauter_mean_of(config) == pytest.approx(sauter)
    with pytest.raises(Exception, match="needs both --diameter2 and --mass-fraction2"):
        cs.make_config(_rig_args(cs, "--diameter2", str(D2)))
    with pytest.raises(Exception, match="must lie in"):
        cs.make_config(_rig_args(cs, "--diameter2", str(D2), "--mass-fraction2", "1"))


def live_parcels(rig) -> dict:
    """Host arrays of the rig's live parcels (x, v, radius, weight, stream)."""
    p = rig.pool.particles
    alive = p.alive.numpy().astype(bool)
    return {name: getattr(p, name).numpy()[alive] for name in ("x", "v", "radius", "weight", "stream")}


def test_rig_mixture_both_holders_release_both_sizes(cs):
    """A reduced rig: after the release window every holder has put out its half of each species (sizes told apart
    by the nearest mean in stds), and the rig layout names the size classes for the report."""
    from hel_warp.collisions.mixture import species_of

    config = cs.make_config(_rig_args(cs, "--diameter2", str(D2), "--mass-fraction2", "0.5", "--cells", "5000",
                                      "--max-particles", "120"))
    rig = cs.CollidingStreams(config)
    while rig.solver.time < max(rig.release_window) + 1e-9:
        rig.step()
    snap = live_parcels(rig)
    kind = species_of(2.0 * snap["radius"], [D1, D2], [S1, S2])
    for k, n in enumerate((config.particles, config.particles2)):
        for side in (0, 1):
            assert int(np.sum((kind == k) & (snap["stream"] == side))) == (n // 2 if side == 0 else n - n // 2)
    assert [c["diameter"] for c in rig.rig_layout()["size_classes"]] == [D1, D2]
    assert cs.check(rig) == []

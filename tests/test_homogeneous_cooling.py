"""cases/homogeneous_cooling.py: the start, the CLI contract, and the HELSCM surrogate against kinetic theory.

References (docs/physics/references.md, "Collisions in a granular gas"): the Enskog collision frequency
omega = 24 eps g0 sqrt(Theta) / (sqrt(pi) d) with the Carnahan-Starling g0, and Haff's law, Theta^-1/2 growing
linearly at 4 (1 - e^2) g0 eps / (d sqrt(pi)).
"""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
CASE = ROOT / "cases" / "homogeneous_cooling.py"
D = 315e-6


@pytest.fixture(scope="module")
def hc():
    from hel_warp.cli.commands._common import load_case_module

    return load_case_module(str(CASE))


def _args(hc, **over):
    import argparse

    parser = argparse.ArgumentParser()
    hc.add_arguments(parser)
    opts = {"collisions": "none", "dt": "1e-4", "solids-fraction": "0.01", "particles": "343", "diameter": str(D),
            "granular-temperature": "1", "end-time": "1e-3", "out": "unused"}
    opts.update({k.replace("_", "-"): v for k, v in over.items()})
    argv = []
    for k, v in opts.items():
        if v is True:
            argv.append(f"--{k}")
        elif v is not None:
            argv += [f"--{k}", str(v)]
    return parser.parse_args(argv)


def _brute_force_min_gap(x, box):
    """Smallest minimum-image centre distance over all pairs, O(N^2) (independent of the cKDTree check)."""
    s = x[:, None, :] - x[None, :, :]
    s -= box * np.round(s / box)
    dist = np.sqrt((s**2).sum(axis=2))
    dist[np.diag_indices(len(x))] = np.inf
    return dist.min()


@pytest.mark.parametrize("particles,eps,weight", [(343, 0.01, 1), (500, 0.05, 1), (400, 0.3, 1), (600, 0.02, 3)])
def test_start_zero_momentum_exact_theta_no_overlap(hc, tmp_path, particles, eps, weight):
    """Zero total momentum, Theta exactly Theta0, no overlap (periodic images included), the asked eps_s."""
    cfg = hc.make_config(_args(hc, particles=particles, solids_fraction=eps, particles_per_parcel=weight,
                               granular_temperature=2.5, out=tmp_path / "o"))
    x, v = hc.initial_state(cfg)
    w = np.full(len(x), float(weight))
    assert len(x) == particles // weight == cfg.parcels
    scale = math.sqrt(2.5)
    assert np.abs((w[:, None] * v).sum(axis=0)).max() < 1e-12 * particles * scale
    assert hc.granular_temperature(v, w) == pytest.approx(2.5, rel=1e-12)
    L = cfg.box_length
    assert np.all((x >= 0.0) & (x < L))
    assert _brute_force_min_gap(x, L) >= D
    assert hc.first_periodic_overlap(x, D, L) is None
    # eps_s of the real particles: N pi d^3 / 6 / L^3
    assert particles * math.pi * D**3 / 6.0 / L**3 == pytest.approx(eps, rel=1e-12)


def test_start_fills_the_box_uniformly(hc, tmp_path):
    """The occupied lattice sites are a random subset: every octant holds about 1/8 of the parcels."""
    cfg = hc.make_config(_args(hc, particles=4000, out=tmp_path / "o"))
    x, _ = hc.initial_state(cfg)
    octant = (x // (0.5 * cfg.box_length)).astype(int) @ np.array([1, 2, 4])
    counts = np.bincount(octant, minlength=8)
    assert np.all(np.abs(counts - 500) < 5 * math.sqrt(500))


def _run_case(hc, capsys, argv):
    code = hc.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


BASE = ["--dt", "1e-4", "--solids-fraction", "0.02", "--particles", "300", "--diameter", D,
        "--granular-temperature", "1", "--end-time", "2e-3"]


def test_none_keeps_theta_and_counts_nothing(hc, capsys, tmp_path):
    """Ballistic flight: Theta stays Theta0 (float32 velocities, untouched), 0 collisions; the --json contract."""
    out = tmp_path / "none"
    code, stdout, _ = _run_case(hc, capsys, ["--collisions", "none", *BASE, "--out", out, "--json"])
    assert code == 0
    result = json.loads(stdout)
    for key in ("time", "granular_temperature", "collisions", "collision_frequency", "solids_fraction", "particles",
                "parcels", "enskog_collision_frequency", "haff_slope", "fitted_slope", "cooling_rate_ratio",
                "collision_frequency_ratio", "wall_clock_s", "strategy_counts", "strategy_flags"):
        assert key in result, key
    assert len(result["time"]) == len(result["granular_temperature"]) == 21
    assert result["time"][-1] == pytest.approx(2e-3)
    theta = np.asarray(result["granular_temperature"])
    assert np.abs(theta - 1.0).max() < 1e-6
    assert result["collisions"] == 0 and result["collision_frequency"] == 0.0
    assert result["solids_fraction"] == 0.02 and result["particles"] == 300 and result["parcels"] == 300
    assert result["cooling_rate_ratio"] == pytest.approx(0.0, abs=1e-3)
    # the references: Carnahan-Starling g0 and Haff's slope in closed form
    g0 = (1 - 0.01) / 0.98**3
    assert result["g0_carnahan_starling"] == pytest.approx(g0, rel=1e-12)
    assert result["haff_slope"] == pytest.approx(4 * 0.19 * g0 * 0.02 / (D * math.sqrt(math.pi)), rel=1e-12)
    # Theta(t) is read from float32 velocities: equal to Theta0 to ~1e-8
    assert result["enskog_collision_frequency"] == pytest.approx(24 * 0.02 * g0 / (math.sqrt(math.pi) * D), rel=1e-6)
    assert json.loads((out / "summary.json").read_text())["collisions"] == 0
    assert (out / "cooling.png").stat().st_size > 1000
    # an existing output directory needs --overwrite
    code, _, err = _run_case(hc, capsys, ["--collisions", "none", *BASE, "--out", out, "--json"])
    assert code == 2 and "--overwrite" in err


def test_ktgf_runs_with_the_engine_term(hc, capsys, tmp_path):
    """ktgf: the engine's KTGF acceleration on a periodic grid; no binary collisions, finite, in the box."""
    code, stdout, _ = _run_case(hc, capsys, ["--collisions", "ktgf", *BASE, "--out", tmp_path / "k", "--json"])
    assert code == 0
    result = json.loads(stdout)
    assert result["collisions"] == 0
    assert result["diagnostics"]["ktgf_cells_with_solids"] > 0
    assert np.all(np.isfinite(result["granular_temperature"]))
    assert any("ktgf" in note for note in result["notes"])


BAD = [
    (["--dt", "0"], "--dt"),
    (["--dt", "nan"], "finite"),
    (["--solids-fraction", "-0.1"], "--solids-fraction"),
    (["--solids-fraction", "1.2"], "--solids-fraction"),
    (["--solids-fraction", "0.6"], "lattice"),
    (["--particles", "1"], "--particles"),
    (["--diameter", "-1e-4"], "--diameter"),
    (["--granular-temperature", "0"], "--granular-temperature"),
    (["--end-time", "5e-5"], "shorter than one step"),
    (["--particles-per-parcel", "7"], "does not divide"),
    (["--particles-per-parcel", "0"], "--particles-per-parcel"),
    (["--collisions", "surrogate-paper"], "--model"),
    (["--collisions", "surrogate", "--model", "/no/such/model"], "no such directory"),
    (["--collisions", "none", "--detection", "swept"], "--detection"),
    (["--collisions", "bogus"], "invalid choice"),
]


def _options(**over) -> list[str]:
    """BASE options (a dict) with ``over`` replacing or adding entries (``None`` drops one)."""
    opts = {"--collisions": "none", **{BASE[i]: str(BASE[i + 1]) for i in range(0, len(BASE), 2)}}
    for k, v in over.items():
        key = "--" + k.replace("_", "-")
        if v is None:
            opts.pop(key, None)
        else:
            opts[key] = str(v)
    return [a for kv in opts.items() for a in kv]


@pytest.mark.parametrize("extra,needle", BAD)
def test_bad_input_is_one_line_exit_2(hc, capsys, tmp_path, extra, needle):
    """Every bad value: one line naming what to change on stderr, exit code 2, nothing written."""
    over = {extra[i].lstrip("-").replace("-", "_"): extra[i + 1] for i in range(0, len(extra), 2)}
    argv = _options(**over) + ["--out", str(tmp_path / "bad")]
    try:
        code = hc.main(argv)
    except SystemExit as exc:  # argparse: a choice or type error
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2
    lines = [line for line in err.strip().splitlines() if line and "CUDA" not in line]
    assert len(lines) == 1 and "error" in lines[0] and needle in lines[0], err
    assert not (tmp_path / "bad").exists()


def test_a_box_narrower_than_the_swept_search_sub_steps_it_and_keeps_kinetic_theory(hc, capsys, tmp_path,
                                                                                   trained_models):
    """1,000 particles at eps_s 0.05 and dt = 1e-3 s: the box (3.8 mm) is narrower than twice the step's swept search
    (2 (r + v_max dt) ~ 9 mm at Theta0 = 1), so the step runs in sub-steps that fit; the collisions still follow
    Enskog and Haff within the run's statistics (about 11,000 collisions)."""
    argv = ["--collisions", "surrogate", "--model", trained_models["contact"], "--dt", "1e-3", "--solids-fraction",
            "0.05", "--particles", "1000", "--diameter", D, "--granular-temperature", "1", "--end-time", "1e-2",
            "--out", tmp_path / "narrow", "--json", "--no-vtk"]
    code, out, err = _run_case(hc, capsys, argv)
    assert code == 0, err
    result = json.loads(out.strip().splitlines()[-1])
    assert result["swept_substeps"] > 1
    _check_kinetic_theory(result)


def test_reachable_through_hel_warp_run(tmp_path):
    """``hel-warp run cases/homogeneous_cooling.py ...`` runs the case (and passes its exit code 2 on through)."""
    out = tmp_path / "via_run"
    base = [sys.executable, "-m", "hel_warp.cli", "run", str(CASE), "--collisions", "none", *map(str, BASE)]
    done = subprocess.run([*base, "--out", str(out), "--json"], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["parcels"] == 300
    bad = subprocess.run([*base, "--out", str(out), "--particles-per-parcel", "7"], capture_output=True, text=True,
                         cwd=ROOT)
    assert bad.returncode == 2 and "does not divide" in bad.stderr


# ------------------------------------------------------------------------------------- physics against kinetic theory
@pytest.fixture(scope="session")
def trained_models(tmp_path_factory):
    """Tiny frictionless contact- and paper-form models (shared with test_collision_models.py's cache)."""
    from test_collision_models import train_tiny_models

    root = tmp_path_factory.getbasetemp() / "tiny_collision_models"
    root.mkdir(exist_ok=True)
    return train_tiny_models(root)


def _check_kinetic_theory(result):
    """Tolerances from the statistics of the run (the case's ``*_stderr``, see its module docstring):
    the collision count of a run with C expected collisions has a relative standard error 1/sqrt(C) (Poisson), the
    energy lost (and so the fitted slope of Theta^-1/2) sqrt(2/C) (E[g_n^4] / E[g_n^2]^2 = 2 for collisions of a
    Maxwellian gas). Allowed: 4 standard errors (a false alarm once in ~16,000 runs), plus 0.03 on the cooling
    rate for the soft-sphere DEM the surrogate was trained on (its energy loss per impact is 0.2-2 % below the
    hard-sphere (1 - e^2) m g_n^2 / 4 up to 60 deg incidence, 5 % at 75 deg: ``hel-warp impact``)."""
    f_tol = 4.0 * result["collision_frequency_ratio_stderr"]
    c_tol = 4.0 * result["cooling_rate_ratio_stderr"] + 0.03
    assert abs(result["collision_frequency_ratio"] - 1.0) < f_tol, (result["collision_frequency_ratio"], f_tol)
    assert abs(result["cooling_rate_ratio"] - 1.0) < c_tol, (result["cooling_rate_ratio"], c_tol)
    assert result["check_errors"] == []


def test_surrogate_swept_follows_enskog_and_haff(hc, capsys, tmp_path, trained_models, full_size):
    """HELSCM pairwise with swept detection at dt = 1e-4 s, eps_s = 0.05 (a particle meets a partner every ~4
    steps, several collisions per step in the box): the collision frequency within 4 sigma of Enskog's and
    Theta^-1/2 growing at Haff's slope within 4 sigma + 3 %. CI: 500 particles, 8 ms (~3,800 collisions, sigma
    1.6 % / 2.3 %); HEL_WARP_FULL=1: 4,000 particles (sigma 0.6 % / 0.8 %)."""
    particles = 4000 if full_size else 500
    argv = ["--collisions", "surrogate", "--model", trained_models["contact"], "--detection", "swept", "--dt", "1e-4",
            "--solids-fraction", "0.05", "--particles", particles, "--diameter", D, "--granular-temperature", "1",
            "--end-time", "8e-3", "--out", tmp_path / "swept", "--json"]
    code, stdout, err = _run_case(hc, capsys, argv)
    assert code == 0, err
    result = json.loads(stdout)
    assert result["collisions_per_particle"] > 10
    _check_kinetic_theory(result)


@pytest.mark.slow
def test_surrogate_swept_at_the_paper_step(hc, capsys, tmp_path, trained_models, full_size):
    """The same at the paper's dt = 1e-3 s, where a particle flies ~5 diameters per step; the box must hold the
    step's search (L > 2 x 2 (r + v_max dt) ~ 19 mm): 4,000 particles at eps_s = 0.005 in CI size (~16,000
    collisions), HEL_WARP_FULL=1: 8,000 at eps_s = 0.01, the reference case (~60,000)."""
    particles, eps = (8000, 0.01) if full_size else (4000, 0.005)
    argv = ["--collisions", "surrogate", "--model", trained_models["contact"], "--detection", "swept", "--dt", "1e-3",
            "--solids-fraction", eps, "--particles", particles, "--diameter", D, "--granular-temperature", "1",
            "--end-time", "0.04", "--out", tmp_path / "swept3", "--json"]
    code, stdout, err = _run_case(hc, capsys, argv)
    assert code == 0, err
    _check_kinetic_theory(json.loads(stdout))

"""cases/three_streams.py (paper sec. 7, Fig. 13) at CI size: 9 steps of 1e-4 s, every pair met.

Physical facts: with no interaction the lateral velocities keep their sign (drag alone slows them);
the CFD-DEM rebound reverses them with |v_y'| = e |v_y| (head-on in the relative frame, frictionless
geometry: the relative velocity lies along the centre line) less the drag of 0.9 ms; the surrogate
rebounds like the DEM within the model's accuracy, with one surrogate call per pair (the pair still
overlapping at a later step end is never collided again); KTGF at eps_s < 0.06 sees no collision
(paper sec. 7): the lateral velocities keep their sign.
"""

from __future__ import annotations

import json
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from tests.test_collision_models import E_REST, impulse_n_mae, train_tiny_models  # noqa: E402

STEPS = 9


@pytest.fixture(scope="session")
def tiny_models(tmp_path_factory):
    root = tmp_path_factory.getbasetemp() / "tiny_collision_models"
    root.mkdir(exist_ok=True)
    return train_tiny_models(root)


def run_case(collisions, out, model=None, render=False) -> dict:
    from cases.three_streams import main

    argv = ["--collisions", collisions, "--out", str(out), "--steps", str(STEPS), "--no-progress", "--overwrite"]
    if model is not None:
        # the tiny model is frictionless, the case's material has mu = 0.3: --force, since the pairs meet head-on in
        # their relative frame (no tangential velocity), where friction plays no part
        argv += ["--model", model, "--force"]
    if not render:
        argv.append("--no-render")
    assert main(argv) == 0
    with open(os.path.join(out, "summary.json")) as fh:
        return json.load(fh)


@pytest.fixture(scope="module")
def dem_result(tmp_path_factory):
    return run_case("dem", tmp_path_factory.mktemp("streams_dem"))


def lateral(result, stream):
    return np.asarray(result["streams"][str(stream)]["vy_final"])


def test_no_interaction_streams_pass_through(tmp_path):
    from cases.three_streams import stream_velocity

    result = run_case("none", tmp_path)
    assert result["outcome"] == "pass-through"
    for s in (0, 1):
        vy0 = stream_velocity(s)[1]
        # drag only: same sign, slower (F_D ~ 13 1/s over <= 0.9 ms: < 2 %)
        assert np.all(lateral(result, s) / vy0 > 0.97) and np.all(lateral(result, s) / vy0 < 1.0)
    assert result["max_cell_eps_s"] < 0.06  # the paper's dilute regime


def test_dem_streams_rebound_with_the_restitution(dem_result):
    from cases.three_streams import stream_velocity

    assert dem_result["outcome"] == "rebound"
    for s in (0, 1):
        vy0 = stream_velocity(s)[1]
        ratio = -lateral(dem_result, s) / vy0
        # e = 0.9 reversal, less up to 2 % of drag over the run
        assert np.all(ratio <= E_REST * 1.003) and np.all(ratio > E_REST * 0.97)


def test_surrogate_streams_rebound_like_dem_once_per_pair(tiny_models, dem_result, tmp_path):
    from cases.three_streams import stream_velocity

    result = run_case("surrogate", tmp_path, model=tiny_models["contact"], render=True)
    assert result["outcome"] == "rebound"
    assert result["collision_counts_total"]["surrogate_calls"] == 3  # three pairs, each collided once
    g = 2.0 * abs(stream_velocity(0)[1])  # lateral approach speed of a pair
    tol = g * (0.5 * 5.0 * impulse_n_mae(tiny_models["contact"]) + 0.003)
    for s in (0, 1):
        assert np.abs(lateral(result, s) - lateral(dem_result, s)).max() <= tol
    for path in result["pictures"]:
        assert os.path.getsize(path) > 1000


def test_ktgf_streams_pass_through(tmp_path):
    # Paper sec. 7: at eps_s < 0.06 the granular pressure does not make the streams collide. With the solids
    # strain taken only between cells holding solids and the gas exchange 3 K_sg Theta of eq. (8)
    # (kernels/ktgf.py), Theta stays <= ~10 m^2/s^2 (it was 1e3-1e4 from the false strain next to empty
    # cells) and every lateral velocity keeps its sign. KTGF still slows the lateral approach (to ~30-55 %
    # after 9 steps): the two crossing streams are one mass-averaged solids velocity field with a real
    # grid-scale shear between them, which the algebraic Theta turns into a granular pressure.
    from cases.three_streams import stream_velocity

    result = run_case("ktgf", tmp_path)
    assert result["max_cell_eps_s"] < 0.06
    assert result["outcome"] == "pass-through"
    for s in (0, 1):
        assert np.all(lateral(result, s) / stream_velocity(s)[1] > 0.0)


def test_case_writes_summary_and_refuses_too_few_steps(tmp_path, capsys):
    from cases.three_streams import main

    out = tmp_path / "run"
    assert main(["--collisions", "none", "--steps", "5", "--out", str(out), "--no-render"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hel-warp: error: --steps must be >= 9")
    assert not out.exists()  # refused before anything is written
    assert main(["--collisions", "none", "--steps", str(STEPS), "--out", str(out), "--no-render",
                 "--no-progress"]) == 0
    with open(out / "summary.json") as fh:
        assert json.load(fh)["outcome"] == "pass-through"
    assert (out / "run.zarr").is_dir()

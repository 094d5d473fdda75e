"""``hel-warp impact``: JSON keys, physics of a single impact against closed forms, one-line errors."""

import json
import math
import subprocess
import sys

import pytest

from hel_warp import Material

KEYS = {"contact_duration", "max_overlap", "max_normal_force", "velocity_after", "velocity2_after",
        "omega_after", "omega2_after", "dt", "steps", "restitution_measured"}


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "hel_warp.cli", "impact", *args], capture_output=True, text=True)


def _json(*args):
    out = _cli(*args, "--json")
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)  # stdout is exactly one JSON object


def test_json_keys_and_elastic_sphere_sphere_matches_johnson():
    d, v, rho, e_mod, nu = 315e-6, 1.5, 1000.0, 5e8, 0.4
    data = _json("--diameter", str(d), "--velocity", f"0,0,-{v}", "--restitution", "1", "--friction", "0")
    assert set(data) >= KEYS
    r = d / 2
    m = rho * 4 / 3 * math.pi * r**3
    m_eff, r_eff, e_eff = m / 2, r / 2, 1 / (2 * (1 - nu**2) / e_mod)
    # Johnson (1985) §11.4 closed forms; tolerance 1 % (runner: >= 40 steps per contact, error ~(dt/tc)^2)
    delta = (15 * m_eff * v**2 / (16 * e_eff * math.sqrt(r_eff))) ** 0.4
    assert data["max_overlap"] == pytest.approx(delta, rel=0.01)
    assert data["max_normal_force"] == pytest.approx(4 / 3 * e_eff * math.sqrt(r_eff) * delta**1.5, rel=0.01)
    assert data["contact_duration"] == pytest.approx(2.868 * (m_eff**2 / (r_eff * e_eff**2 * v)) ** 0.2, rel=0.01)
    # equal masses, e = 1: the velocities are exchanged (momentum and energy conservation)
    assert data["velocity_after"] == pytest.approx([0, 0, 0], abs=0.01 * v)
    assert data["velocity2_after"] == pytest.approx([0, 0, -v], rel=0.01)
    # never above the eq. (12) stable step
    assert data["dt"] <= Material().time_step(r, max_speed=20.0).chosen * (1 + 1e-9)
    assert data["steps"] > 0


def test_wall_restitution_and_sliding_spin():
    mu, e, v, theta = 0.2, 0.8, 2.0, math.radians(75)
    data = _json("--target", "wall", "--restitution", str(e), "--friction", str(mu),
                 "--velocity", f"{v * math.sin(theta)},0,{-v * math.cos(theta)}")
    assert data["restitution_measured"] == pytest.approx(e, rel=0.01)
    assert data["velocity2_after"] == [0.0, 0.0, 0.0] and data["omega2_after"] == [0.0, 0.0, 0.0]
    # gross sliding (tan 75 deg = 3.7 >= 3.5 mu (1+e) = 1.26): |omega'| = 2.5 mu (1+e) v cos(theta) / R
    spin = 2.5 * mu * (1 + e) * v * math.cos(theta) / (315e-6 / 2)
    assert abs(data["omega_after"][1]) == pytest.approx(spin, rel=0.01)


def test_compliant_wall_lengthens_the_contact():
    rigid = _json("--target", "wall", "--restitution", "1")
    soft = _json("--target", "wall", "--restitution", "1", "--youngs2", "5e8", "--poisson2", "0.4")
    # t_c ~ E*^(-2/5): a wall of the sphere's material halves E*, so t_c grows by 2^(2/5)
    assert soft["contact_duration"] / rigid["contact_duration"] == pytest.approx(2**0.4, rel=0.01)


def test_explicit_dt_is_used_and_text_output_works():
    out = _cli("--dt", "1e-8", "--velocity", "0,0,-0.5")
    assert out.returncode == 0, out.stderr
    assert "contact duration" in out.stdout and "1.0000e-08" in out.stdout


@pytest.mark.parametrize("args", [
    ["--diameter", "-1e-4"],
    ["--diameter2", "0"],
    ["--poisson", "0.6"],
    ["--poisson2", "-1"],
    ["--restitution", "0"],
    ["--restitution", "1.2"],
    ["--velocity", "nan,0,-1"],
    ["--velocity", "0,0"],
    ["--velocity", "0,0,1"],                    # receding: would have to start overlapped
    ["--dt", "1e-5"],                           # above the eq. (12) stable step
    ["--density", "-5"],
    ["--target", "wall", "--velocity2", "0,0,1"],
    ["--model", "spring"],
])
def test_bad_input_is_one_line_exit_2(args):
    out = _cli(*args)
    assert out.returncode == 2
    assert "Traceback" not in out.stderr
    lines = [ln for ln in out.stderr.strip().splitlines() if "CUDA" not in ln]  # Warp's driver notice
    assert len(lines) == 1 and "error" in lines[0]

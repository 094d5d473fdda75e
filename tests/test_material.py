"""Material validation and the DEM time step of eqs. (12)-(15), checked against hand-worked values."""

import math
import subprocess
import sys
import json

import pytest

from hel_warp import ConfigError, Material


def test_timestep_matches_hand_computation():
    # Worked by hand from eqs. (13)-(15): r = 157.5 um, rho = 1000, E = 5e8, nu = 0.4.
    m = Material(density=1000.0, youngs_modulus=5e8, poisson_ratio=0.4)
    r = 157.5e-6
    G = 5e8 / 2.8
    rayleigh = math.pi * r / (0.1631 * 0.4 + 0.8766) * math.sqrt(1000.0 / G)
    step = m.time_step(r)
    assert step.rayleigh == pytest.approx(rayleigh, rel=1e-12)
    assert step.chosen == pytest.approx(0.2 * min(step.rayleigh, step.hertz, step.cundall))
    # The paper reports 2.46e-7 s for its polyethylene; our default modulus lands within 2 %.
    assert step.chosen == pytest.approx(2.46e-7, rel=0.02)


def test_hertz_step_scales_with_speed():
    # eq. (14): t_H ~ V_max^(-1/5)
    m = Material()
    a, b = m.time_step(1e-3, max_speed=1.0).hertz, m.time_step(1e-3, max_speed=32.0).hertz
    assert a / b == pytest.approx(32.0**0.2, rel=1e-12)


@pytest.mark.parametrize("field,value", [
    ("poisson_ratio", 0.5), ("poisson_ratio", -1.0), ("restitution", 0.0), ("restitution", 1.01),
    ("density", -1.0), ("youngs_modulus", 0.0), ("density", float("nan")), ("friction", -0.1),
])
def test_bad_material_is_refused(field, value):
    with pytest.raises(ConfigError, match=field):
        Material(**{field: value})


def test_time_step_above_stable_is_refused():
    m = Material()
    stable = m.time_step(1e-4).chosen
    m.check_time_step(stable, 1e-4)
    with pytest.raises(ConfigError, match="above the stable"):
        m.check_time_step(stable * 1.5, 1e-4)


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "hel_warp.cli", *args], capture_output=True, text=True)


def test_cli_timestep_json():
    out = _cli("timestep", "--diameter", "315e-6", "--json")
    assert out.returncode == 0, out.stderr
    data = json.loads(out.stdout)
    assert set(data) >= {"rayleigh", "hertz", "cundall", "chosen"}
    assert data["chosen"] == pytest.approx(Material().time_step(157.5e-6).chosen)


@pytest.mark.parametrize("args", [["--diameter", "-1"], ["--diameter", "nan"], ["--poisson", "0.7"]])
def test_cli_bad_input_is_one_line_exit_2(args):
    out = _cli("timestep", *args)
    assert out.returncode == 2
    assert "Traceback" not in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1

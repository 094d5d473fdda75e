"""Drag laws and the semi-implicit push of eq. (4), checked against force balances solved here
independently (scipy root finding), the closed-form formulas of the drag correlations, the discrete
linear-drag solution, and the momentum bookkeeping of the recorded drag impulse."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest
import warp as wp
from scipy.optimize import brentq

from hel_warp.parcels.coupling import CouplingFields, GridSpec, PushConfig, push_parcels, single_particle_response
from hel_warp.parcels.particles import Particles
from kernels.push import DRAG_LAWS, eval_drag_rate

AIR = dict(fluid_density=1.205, fluid_viscosity=1.81e-5)


def cd_sn(re):
    """Schiller-Naumann drag coefficient (written here again, not imported)."""
    return 24.0 / re * (1.0 + 0.15 * re**0.687) if re <= 1000.0 else 0.44


def terminal_sn(d, rho_p, rho_f, mu, g):
    """Root of (rho_p - rho_f) g pi d^3/6 = 1/2 rho_f Cd(Re) v^2 pi d^2/4, Re = rho_f v d / mu."""
    def balance(v):
        return (rho_p - rho_f) * g * math.pi * d**3 / 6.0 - 0.5 * rho_f * cd_sn(rho_f * v * d / mu) * v * v * math.pi * d**2 / 4.0
    return brentq(balance, 1e-9, 100.0, xtol=1e-14, rtol=1e-13)


@pytest.mark.parametrize("dt", [1e-4, 1e-3])
@pytest.mark.parametrize("d", [315e-6, 475e-6])
def test_terminal_velocity_polyethylene_in_air(d, dt):
    g = 9.80665
    expect = terminal_sn(d, 1000.0, AIR["fluid_density"], AIR["fluid_viscosity"], g)
    r = single_particle_response(diameter=d, density=1000.0, dt=dt,
                                 config=PushConfig(drag="schiller-naumann", gravity=(0, 0, -g), **AIR))
    assert r["converged"]
    # steady state of the semi-implicit update is F_D v = g' exactly, for any dt: float32 + stopping tolerance
    assert r["terminal_velocity"] == pytest.approx(expect, rel=0.01)
    assert r["terminal_velocity"] == pytest.approx(expect, rel=1e-4)


@pytest.mark.parametrize("dt", [1e-4, 1e-3])
def test_mfix_dem06_terminal_velocity(dt):
    # MFIX DEM06: 100 um, rho_p 2000, rho_f 1.2, mu 1.8e-5, g 9.80665 -> 0.45740 m/s (published value)
    cfg = PushConfig(drag="schiller-naumann", fluid_density=1.2, fluid_viscosity=1.8e-5, gravity=(0, 0, -9.80665))
    r = single_particle_response(diameter=100e-6, density=2000.0, config=cfg, dt=dt)
    assert r["terminal_velocity"] == pytest.approx(0.45740, rel=0.01)
    assert r["terminal_velocity"] == pytest.approx(terminal_sn(100e-6, 2000.0, 1.2, 1.8e-5, 9.80665), rel=1e-4)


def test_response_time_matches_discrete_linear_drag():
    # d = 10 um: Re ~ 2e-3, the Schiller-Naumann correction 0.15 Re^0.687 ~ 2e-3, drag ~ linear (Stokes).
    # Semi-implicit Euler on dv/dt = (v_t - v)/tau: v_n = v_t (1 - (1 + dt/tau)^-n), so 63.2 % is reached at
    # t = dt / ln(1 + dt/tau).
    d, rho = 10e-6, 1000.0
    tau = rho * d * d / (18.0 * AIR["fluid_viscosity"])
    dt = tau / 50.0
    r = single_particle_response(diameter=d, density=rho, dt=dt, config=PushConfig(drag="schiller-naumann", **AIR))
    assert r["response_time"] == pytest.approx(dt / math.log1p(dt / tau), rel=5e-3)


def test_semi_implicit_push_is_stable_and_monotone_at_large_dt():
    # 20 um: tau ~ 1.2 ms, so dt = 1e-3 s is ~ tau; an explicit scheme at dt = 3 tau would diverge.
    d = 20e-6
    cfg = PushConfig(drag="schiller-naumann", **AIR)
    parts = Particles.from_numpy(np.zeros((1, 3)), d / 2, density=1000.0, check_overlap=False)
    fields = CouplingFields.allocate(GridSpec(origin=(0, 0, 0), spacing=1.0, shape=(1, 1, 1)), 1)
    params = cfg.params(3.6e-3)
    speeds = []
    for _ in range(60):
        push_parcels(parts, fields, params)
        speeds.append(-float(parts.v.numpy()[0, 2]))
    speeds = np.array(speeds)
    assert np.all(np.diff(speeds) >= -1e-9)
    assert speeds[-1] == pytest.approx(terminal_sn(d, 1000.0, 1.205, 1.81e-5, 9.80665), rel=1e-3)


def _rates(law, eps_s, slip, d, rho_p, rho_f=1.205, mu=1.81e-5):
    n = len(slip)

    def a(v):
        return wp.array(np.broadcast_to(np.asarray(v, np.float32), (n,)).copy(), dtype=float)

    out = wp.zeros(n, dtype=float)
    eval_drag_rate(DRAG_LAWS[law], a(eps_s), a(slip), a(d), a(rho_p), rho_f, mu, out)
    return out.numpy().astype(np.float64)


def test_drag_laws_match_published_formulas():
    rho_f, mu, d, rho_p = 1.205, 1.81e-5, 315e-6, 1000.0
    cases = [(0.0, 0.5), (0.05, 1.0), (0.15, 2.0), (0.19, 0.3), (0.21, 0.3), (0.4, 0.1), (0.55, 3.0), (0.3, 0.0)]
    eps = np.array([c[0] for c in cases])
    slip = np.array([c[1] for c in cases])
    ef = 1.0 - eps

    def cd_re(re):  # Cd * Re of Schiller-Naumann
        return np.where(re > 1000.0, 0.44 * re, 24.0 * (1.0 + 0.15 * re**0.687))

    re = rho_f * slip * d / mu
    f_sn = 18.0 * mu * cd_re(re) / (24.0 * rho_p * d * d)
    # Wen-Yu: beta = 3/4 Cd eps_s eps_f rho_f |du| eps_f^-2.65 / d with Cd at eps_f Re; F = beta/(eps_s rho_p)
    with np.errstate(divide="ignore", invalid="ignore"):
        cd_wy = np.where(slip > 0, cd_re(ef * re) / np.maximum(ef * re, 1e-300), 0.0)
    f_wy = np.where(slip > 0, 0.75 * cd_wy * ef * rho_f * slip * ef**-2.65 / (d * rho_p),
                    0.75 * 24.0 * mu * ef**-2.65 / (rho_p * d * d))
    # Ergun: beta = 150 eps_s^2 mu/(eps_f d^2) + 1.75 rho_f eps_s |du| / d
    f_er = (150.0 * eps * mu / (ef * d * d) + 1.75 * rho_f * slip / d) / rho_p
    f_gi = np.where(ef <= 0.8, f_er, f_wy)
    assert np.allclose(_rates("schiller-naumann", eps, slip, d, rho_p), f_sn, rtol=1e-5)
    assert np.allclose(_rates("wen-yu", eps, slip, d, rho_p), f_wy, rtol=1e-5)
    assert np.allclose(_rates("ergun", eps, slip, d, rho_p), f_er, rtol=1e-5)
    assert np.allclose(_rates("gidaspow", eps, slip, d, rho_p), f_gi, rtol=1e-5)
    # a lone particle (eps_s = 0): Wen-Yu and Gidaspow reduce to Schiller-Naumann
    single = _rates("gidaspow", [0.0] * 3, [0.1, 1.0, 5.0], d, rho_p)
    assert np.allclose(single, _rates("schiller-naumann", [0.0] * 3, [0.1, 1.0, 5.0], d, rho_p), rtol=1e-6)


def test_drag_impulse_balances_particle_momentum():
    # v_new - v = dt F_D (u_f - v_new) + dt a_body exactly; recorded impulse = weight m F_D dt (u_f - v_new)
    rng = np.random.default_rng(3)
    n = 64
    d = rng.uniform(200e-6, 500e-6, n)
    rho = rng.uniform(900.0, 2500.0, n)
    w = rng.integers(1, 9, n).astype(float)
    v0 = rng.normal(0, 2, (n, 3))
    parts = Particles.from_numpy(rng.uniform(0, 1, (n, 3)), d / 2, v=v0, density=rho, weight=w, check_overlap=False)
    fields = CouplingFields.allocate(GridSpec(origin=(0, 0, 0), spacing=1.0, shape=(1, 1, 1)), n)
    u_f = rng.normal(0, 3, (n, 3)).astype(np.float32)
    grad_p = rng.normal(0, 50, (n, 3)).astype(np.float32)
    fields.parcel_u_f.assign(u_f)
    fields.parcel_grad_p.assign(grad_p)
    fields.parcel_eps_s.assign(rng.uniform(0, 0.4, n).astype(np.float32))
    dt = 1e-3
    cfg = PushConfig(drag="gidaspow", **AIR)
    v_before = parts.v.numpy().astype(np.float64)
    push_parcels(parts, fields, cfg.params(dt))
    v_after = parts.v.numpy().astype(np.float64)
    m = w * parts.density.numpy() * math.pi / 6.0 * (2 * parts.radius.numpy().astype(np.float64)) ** 3
    g = np.array(cfg.gravity)
    a_body = g[None, :] * ((rho - 1.205) / rho)[:, None] - grad_p / rho[:, None]
    impulse = fields.parcel_drag_impulse.numpy()
    momentum_change = m[:, None] * (v_after - v_before)
    residual = momentum_change - m[:, None] * dt * a_body - impulse
    scale = np.abs(m[:, None] * v_after).max()
    assert np.abs(residual).max() <= 1e-6 * scale  # float32 velocities
    assert np.all(fields.parcel_drag_coeff.numpy() > 0)


def test_particle_cli_json_and_stokes_number():
    out = subprocess.run([sys.executable, "-m", "hel_warp.cli", "particle", "--diameter", "100e-6", "--density",
                          "2000", "--gas-density", "1.2", "--gas-viscosity", "1.8e-5", "--dt", "1e-4",
                          "--flow-time", "0.01", "--json"], capture_output=True, text=True, check=True)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["terminal_velocity"] == pytest.approx(0.45740, rel=0.01)
    assert result["stokes_number"] == pytest.approx(result["response_time"] / 0.01, rel=1e-12)


@pytest.mark.parametrize("argv", [["--diameter", "0", "--density", "1000"],
                                  ["--diameter", "1e-4", "--density", "1.0"],
                                  ["--diameter", "1e-4", "--density", "1000", "--dt", "-1"],
                                  ["--diameter", "1e-4", "--density", "1000", "--flow-time", "0"],
                                  ["--diameter", "nan", "--density", "1000"],
                                  ["--diameter", "1e-4", "--density", "1000", "--drag", "stokes"]])
def test_particle_cli_refuses_bad_input_in_one_line(argv):
    out = subprocess.run([sys.executable, "-m", "hel_warp.cli", "particle", *argv], capture_output=True, text=True)
    assert out.returncode == 2
    lines = [ln for ln in out.stderr.strip().splitlines() if "error" in ln]
    assert len(lines) == 1 and "Traceback" not in out.stderr

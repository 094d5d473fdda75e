"""cases/periodic_riser.py at one tile (224 spheres, 800 cells) and hel_warp.runs.counters.

References: the benchmark's numbers (224 spheres of 100 um in 0.8 x 10 x 0.8 mm: eps_s, the buoyant weight);
conservation of the particles in a periodic box; Newton's second law for the whole mixture in a periodic box
(the only external forces are the imposed mean pressure gradient and the particles' buoyant weight, so the total
axial momentum changes at V (-dp'/dy - (rho_p - rho_f) eps_s g)); ``wp.launch`` itself for the counters; the
uncounted run, bit for bit.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from dataclasses import replace

import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from tests.test_collision_models import trained_models  # noqa: E402,F401  (fixture)

KEYS = ("particles", "parcels", "fluid_cells", "steps", "wall_clock_s", "parcel_steps_per_second", "slip_velocity",
        "solids_flux", "solids_fraction_variance", "launches_per_step", "device_reads_per_step")


def _flow(tiles=0, gradient=None, weight="1"):
    import cases.periodic_riser as R

    args = argparse.Namespace(tiles=tiles, samples=10, particles_per_parcel=weight, end_time=0.01, dt=1e-4)
    flow = R.build(args)
    if gradient is not None:
        flow.gas = replace(flow.gas, mean_pressure_gradient=(0.0, gradient, 0.0))
    return flow


def _sim(flow, collisions="none", device="cpu"):
    from hel_warp.case.build import Settings, build

    return build(flow, Settings(collisions=collisions, dt=1e-4, device=device))


def test_the_driving_gradient_is_the_buoyant_weight_of_the_benchmark_suspension():
    """224 spheres of 100 um in 0.8 x 10 x 0.8 mm: eps_s = 0.018326; (rho_p - rho_f) eps_s g = 359.25 Pa/m
    (3.59 Pa over 10 mm); every tiling keeps eps_s and has 224 4^K particles on (4 2^K, 50, 4 2^K) cells."""
    import cases.periodic_riser as R

    eps = 224 * math.pi / 6 * (100e-6) ** 3 / (0.8e-3 * 10e-3 * 0.8e-3)
    assert R.solids_fraction() == pytest.approx(eps, rel=1e-12)
    assert R.pressure_gradient() == pytest.approx(-(2000.0 - 1.0) * eps * 9.80665, rel=1e-12)
    assert R.pressure_gradient() * 10e-3 == pytest.approx(-3.5925, abs=1e-3)
    for k in (0, 2):
        flow = _flow(tiles=k)
        assert flow.cells == (4 * 2**k, 50, 4 * 2**k) and flow.real_particles == 224 * 4**k
        assert flow.spacing == pytest.approx(0.2e-3)
    # the reference's linear contact: pi sqrt(m*/k_n); the Hertz modulus gives the same duration at 1 m/s
    from hel_warp.collisions.contact_law import hertz_contact_duration

    m = 2000.0 * math.pi / 6 * (100e-6) ** 3
    assert R.contact_duration() == pytest.approx(math.pi * math.sqrt(0.5 * m / 10.0), rel=1e-12)
    e_eff = R.equivalent_youngs_modulus() / (2 * (1 - R.POISSON**2))
    assert hertz_contact_duration(e_eff, 25e-6, 0.5 * m, 1.0) == pytest.approx(R.contact_duration(), rel=1e-9)


def _momentum_rate(sim, steps, skip):
    import cases.periodic_riser as R

    totals = []
    for k in range(steps):
        sim.solver.step()
        if k >= skip:
            p = R.momentum(sim.solver)
            totals.append(p["gas"] + p["solids"])
    return np.polyfit(np.arange(len(totals)) * 1e-4, totals, 1)[0]


def test_particles_stay_in_the_periodic_box_and_their_volume_is_the_cells_solids(device):
    """30 steps: every parcel alive and inside [0, L), the particle mass unchanged, and the cells' eps_s summing
    to the particles' volume (the deposit conserves it)."""
    import cases.periodic_riser as R

    flow = _flow()
    sim = _sim(flow, device=device)
    p = sim.solver.pool.particles
    mass0 = float(np.sum(p.density.numpy() * p.radius.numpy().astype(np.float64) ** 3 * p.alive.numpy()))
    for _ in range(30):
        sim.solver.step()
    alive = p.alive.numpy().astype(bool)
    assert alive.sum() == 224
    x = p.x.numpy()[alive]
    assert np.all(x >= 0.0) and np.all(x < np.asarray(flow.hi))
    assert float(np.sum(p.density.numpy() * p.radius.numpy().astype(np.float64) ** 3 * p.alive.numpy())) == \
        pytest.approx(mass0, rel=1e-12)
    eps = sim.solver.fields.cell_eps_s.numpy().astype(np.float64)
    assert eps.mean() == pytest.approx(R.solids_fraction(), rel=1e-4)
    assert np.all(np.abs(p.v.numpy()[alive]) < 1.0)  # nothing thrown out: slip of order the terminal velocity


def test_the_mean_pressure_gradient_balances_the_suspension_weight(device):
    """Newton's second law for the mixture in the periodic box: without the gradient the total axial momentum falls
    at the buoyant weight (rate -1 in units of (rho_p - rho_f) eps_s g V, within 1 %); with it, the rate is
    zero within 2 % of the weight over steps 50-120, while the gas alone gains momentum at ~0.3 of the weight
    (the residue is the scheme's: parcels feel the interpolated pressure gradient, not the transpose of the
    deposit)."""
    import cases.periodic_riser as R

    volume = 0.8e-3 * 10e-3 * 0.8e-3
    weight = volume * (2000.0 - 1.0) * R.solids_fraction() * 9.80665
    free = _momentum_rate(_sim(_flow(gradient=0.0), device=device), 12, 2)
    assert free / weight == pytest.approx(-1.0, abs=0.01)
    balanced_sim = _sim(_flow(), device=device)
    balanced = _momentum_rate(balanced_sim, 120, 50)
    assert abs(balanced / weight) < 0.02
    gas = R.momentum(balanced_sim.solver)["gas"]
    assert gas > 0.1 * weight * 120e-4  # the gas is driven up: the balance is not trivial


@pytest.mark.parametrize("collisions", ["none", "ktgf", "dem", "surrogate"])
def test_one_tile_runs_with_every_model_and_reports_the_keys(collisions, tmp_path, capsys,
                                                            trained_models):  # noqa: F811
    """Each model: 6 steps of one tile from the command line, exit 0, the summary's keys, the check passed, the
    counts per step positive; the slip positive (the gas rises through the falling solids)."""
    from cases.periodic_riser import main

    argv = ["--collisions", collisions, "--tiles", "0", "--dt", "1e-4", "--end-time", "6e-4", "--out",
            str(tmp_path / collisions), "--no-vtk", "--no-progress", "--json", "--samples", "3"]
    if collisions == "surrogate":
        # the tiny model is for 315 um spheres of another material: --force (the test is that the step runs)
        argv += ["--model", trained_models["contact"], "--force"]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in KEYS:
        assert summary[key] is not None, key
    assert summary["particles"] == 224 and summary["parcels"] == 224 and summary["fluid_cells"] == 800
    assert summary["steps"] == 6 and summary["check_errors"] == []
    assert summary["launches_per_step"] > 0 and summary["device_reads_per_step"] >= 0
    assert summary["slip_velocity"] > 0
    if collisions == "dem":
        import cases.periodic_riser as R

        assert summary["dem_step"] <= R.contact_duration() / R.DEM_STEPS_PER_CONTACT * (1 + 1e-9)


@pytest.mark.parametrize("bad, words", [(["--tiles", "-1"], "--tiles"), (["--tiles", "9"], "--tiles"),
                                         (["--particles-per-parcel", "0"], "weight"),
                                         (["--collisions", "surrogate-paper"], "invalid choice"),
                                         (["--samples", "0"], "--samples")])
def test_bad_input_is_one_line_and_exit_2(bad, words, tmp_path, capsys):
    from cases.periodic_riser import main

    out = tmp_path / "run"
    argv = ["--collisions", "none", "--end-time", "2e-4", "--out", str(out), "--no-progress"]
    argv = [a for a in argv if not (bad[0] == "--collisions" and a in ("--collisions", "none"))] + bad
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and err.startswith("hel-warp: error:")
    assert words.lower() in err.lower()
    assert not out.exists()


def test_counters_count_what_warp_does_and_change_no_result(device):
    """Three wp.launch calls, one recorded launch replayed twice, one numpy(): 5 launches, 1 read; a recorded
    launch is not a launch until replayed; a loop's or branch's condition tested on the host is a read, one tested
    in a captured graph is not. Five riser steps counted and uncounted: positions and velocities equal
    bit for bit; outside the block Warp's functions are its own again."""
    import warp as wp

    from hel_warp.runs import counters

    @wp.kernel
    def bump(a: wp.array(dtype=float)):
        a[wp.tid()] = a[wp.tid()] + 1.0

    a = wp.zeros(4, dtype=float, device=device)
    launch, numpy = wp.launch, wp.array.numpy
    with counters.counting():
        before = counters.snapshot()
        for _ in range(3):
            wp.launch(bump, dim=4, inputs=[a], device=device)
        recorded = wp.launch(bump, dim=4, inputs=[a], device=device, record_cmd=True)
        recorded.launch()
        recorded.launch()
        values = a.numpy()
        d = counters.snapshot() - before
    assert (d.launches, d.graph_launches, d.reads) == (5, 0, 1)
    assert np.all(values == 5.0)

    # a loop condition tested on the host is a read per test (on CUDA a pinned copy and a sync): three passes, four
    # tests; one capture_if, one test; the same loop captured and replayed: one graph launch, no read
    @wp.kernel
    def count_down(n: wp.array(dtype=wp.int32)):
        n[wp.tid()] = n[wp.tid()] - 1

    n = wp.array([3], dtype=wp.int32, device=device)
    capture_if, capture_while = wp.capture_if, wp.capture_while
    with counters.counting():
        before = counters.snapshot()
        wp.capture_while(n, lambda: wp.launch(count_down, dim=1, inputs=[n], device=device))
        wp.capture_if(n, on_false=lambda: None)
        d = counters.snapshot() - before
        n.fill_(3)
        with wp.ScopedCapture(device=device, force_module_load=False) as capture:
            wp.capture_while(n, lambda: wp.launch(count_down, dim=1, inputs=[n], device=device))
        before = counters.snapshot()
        wp.capture_launch(capture.graph)
        replayed = counters.snapshot() - before
    assert (d.launches, d.reads) == (3, 4 + 1)
    assert (replayed.launches, replayed.graph_launches, replayed.reads) == (0, 1, 0)
    assert int(n.numpy()[0]) == 0
    assert wp.launch is launch and wp.array.numpy is numpy
    assert wp.capture_if is capture_if and wp.capture_while is capture_while

    results = []
    for counted in (False, True):
        sim = _sim(_flow(), device=device)
        if counted:
            with counters.counting():
                for _ in range(5):
                    sim.solver.step()
        else:
            for _ in range(5):
                sim.solver.step()
        p = sim.solver.pool.particles
        results.append((p.x.numpy().copy(), p.v.numpy().copy(), sim.solver.gas.cell_velocity.numpy().copy()))
    for off, on in zip(*results):
        assert np.array_equal(off, on)


def test_bench_scale_dry_run_writes_its_json_and_plot(tmp_path):
    """scripts/bench_scale.py --dry-run (K = 0, 3 steps, ``none``): one row with the cost and memory figures, the
    plot; the seconds per parcel-step are the median step over the parcels."""
    import subprocess

    repo = os.path.join(os.path.dirname(__file__), "..")
    proc = subprocess.run([sys.executable, os.path.join(repo, "scripts", "bench_scale.py"), "--dry-run", "--models",
                           "none", "--out", str(tmp_path)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-500:]
    rows = json.loads((tmp_path / "bench_scale.json").read_text())["runs"]
    assert len(rows) == 1 and rows[0]["parcels"] == 224 and rows[0]["tiles"] == 0
    assert rows[0]["seconds_per_parcel_step"] == pytest.approx(rows[0]["step_s"] / 224, rel=1e-12)
    assert rows[0]["bytes_per_particle"] > 0 and rows[0]["launches_per_step"] > 0
    assert (tmp_path / "bench_scale.png").stat().st_size > 0


def _head_on(speed, steps_per_contact, sample):
    """Two riser spheres meeting head-on at relative ``speed`` under the riser's dem contact: (restitution,
    time in contact sampled every ``sample`` s)."""
    import cases.periodic_riser as R
    from hel_warp.collisions.cfd_dem import DemCollision
    from hel_warp.parcels.particles import Particles

    r = 0.5 * R.DIAMETER
    gap = 0.2 * speed * R.contact_duration()
    x = np.array([[0.5e-3 - r - gap, 0.5e-3, 0.5e-3], [0.5e-3 + r + gap, 0.5e-3, 0.5e-3]])
    v = np.array([[0.5 * speed, 0.0, 0.0], [-0.5 * speed, 0.0, 0.0]])
    p = Particles.from_numpy(x, np.full(2, r), v=v, density=R.PARTICLE_DENSITY, device="cpu")
    dem = DemCollision(material=R.material(), periodic_box=(1e-3,) * 3,
                       dt_dem=R.contact_duration() / steps_per_contact)
    R.use_linear_contact(dem)
    touching = 0
    for _ in range(int(round(2.0 * R.contact_duration() / sample))):
        dem.advance_free(p, sample)
        xs = p.x.numpy().astype(np.float64)
        touching += np.linalg.norm(xs[1] - xs[0]) < 2.0 * r
    vs = p.v.numpy().astype(np.float64)
    return (vs[1, 0] - vs[0, 0]) / speed, touching * sample


def test_the_reference_contact_is_the_benchmarks_linear_spring_dashpot():
    """Head-on pairs under the dem strategy the riser runs: the restitution is e = 0.8 (within 1.5 % at the riser's
    DEM step of t_c / 20, first-order convergence to within 0.3 % at t_c / 100), and the contact lasts
    pi sqrt(m*/k_n) = 22.7 us at 1 m/s and at 0.1 m/s alike (a linear spring; a Hertz contact of that duration at
    1 m/s would last 10^(1/5) = 1.58 times longer at 0.1 m/s)."""
    import cases.periodic_riser as R

    e, _ = _head_on(1.0, R.DEM_STEPS_PER_CONTACT, R.contact_duration() / 10)
    assert e == pytest.approx(0.8, abs=0.015)
    tc = R.contact_duration()
    for speed in (1.0, 0.1):
        e, duration = _head_on(speed, 100, tc / 50)
        assert e == pytest.approx(0.8, abs=0.003)
        assert duration == pytest.approx(tc, rel=0.05)


@pytest.mark.parametrize("collisions", ["none", "ktgf", "surrogate"])
def test_read_back_at_outputs_reads_nothing_in_a_steady_step_and_changes_no_result(collisions, tmp_path, capsys,
                                                                                 trained_models):  # noqa: F811
    """``--read-back output`` (the CUDA default) on the CPU, through the code the GPU runs: a steady HEL step has no
    device-to-host read and at most 5 captured graphs (the four CG solves, each one graph looping on the device;
    HELSCM's cell detection at parcels of 4: its sub-step loop the fifth, planned on the device), and the run's
    summary is the per-step reading run's (slip, flux, variance, momentum: the same bits)."""
    from cases.periodic_riser import main

    summaries = {}
    for mode in ("step", "output"):
        argv = ["--collisions", collisions, "--tiles", "0", "--dt", "1e-4", "--end-time", "1.2e-3", "--out",
                str(tmp_path / mode), "--no-vtk", "--no-progress", "--json", "--samples", "4", "--read-back", mode,
                "--output-interval", "1.2e-3"]  # one output, at the end: the steps between are steady
        if collisions == "surrogate":  # the cell detection (weights > 1); the tiny model's domain: --force
            argv += ["--particles-per-parcel", "4", "--model", trained_models["contact"], "--force"]
        assert main(argv) == 0
        summaries[mode] = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    step, output = summaries["step"], summaries["output"]
    assert output["device_reads_per_step"] == 0 and step["device_reads_per_step"] > 0
    assert output["graph_launches_per_step"] <= 5
    assert output["launches_per_step"] < step["launches_per_step"]
    for key in ("slip_velocity", "solids_flux", "solids_fraction_variance", "momentum", "series"):
        assert output[key] == step[key], key

"""The run loop (``hel_warp.runs.run``): run.zarr contents, VTK, bitwise restart, failures keep the last checkpoint."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hel_warp.errors import ConfigError, HelWarpError

DT = 1e-3


def build(collision="ktgf"):
    """Closed 8 x 6 x 8 mm box of air, a windowed injector (parcels fall, bounce), an outlet plane at x = 7 mm."""
    from hel_warp.parcels.coupling import PushConfig
    from hel_warp.gas.solver import GasConfig, GasField, GasSolver
    from hel_warp.gas.grid import Box, Geometry, Grid
    from hel_warp.hel import HelConfig, HelSolver, Outlet, ScheduledInjection, collision_model
    from hel_warp.parcels.pool import ParcelPool, VolumeInjection

    grid = Grid(spacing=1e-3, shape=(8, 6, 8))
    domain = Geometry(shapes=(Box(lo=(0, 0, 0), hi=(0.008, 0.006, 0.008)),)).build(grid)
    push = PushConfig(drag="gidaspow")
    gas_solver = GasSolver(domain, GasConfig(density=push.fluid_density, viscosity=push.fluid_viscosity))
    injection = VolumeInjection(box_lo=(0.001, 0.001, 0.0005), box_hi=(0.005, 0.005, 0.003), diameter_mean=3e-4,
                                diameter_std=3e-5, count=300, speed=1.0, direction=(1.0, 0.2, -1.0), seed=11)
    config = HelConfig(dt=DT, push=push, injectors=(ScheduledInjection(injection=injection, t_end=0.004),),
                       outlets=(Outlet(point=(0.007, 0, 0), normal=(1, 0, 0)),))
    strategy = (collision_model("ktgf", particle_diameter=3e-4, particle_density=1000.0) if collision == "ktgf"
                else collision_model(collision))
    return HelSolver(pool=ParcelPool.empty(400), gas_solver=gas_solver, gas=GasField(domain), config=config,
                     collision=strategy)


def run_config(out, steps, *, output_every=3, checkpoint_every=None, vtk=False):
    from hel_warp.runs.run import RunConfig

    # checkpoint_wall_s=0: a checkpoint at every output (these tests are about what a checkpoint holds)
    return RunConfig(out_dir=str(out), end_time=steps * DT, output_interval=output_every * DT,
                     checkpoint_interval=None if checkpoint_every is None else checkpoint_every * DT, vtk=vtk,
                     checkpoint_wall_s=0.0)



class Interrupt(Exception):
    """Raised by :func:`stop_at`: a run killed mid-way (the restart tests)."""


def stop_at(step):
    """A ``Run.run(progress=...)`` callback that interrupts the run when the solver reaches ``step``."""
    def progress(solver):
        if solver.step_count == step:
            raise Interrupt

    return progress

def test_run_zarr_holds_snapshots_gas_fields_timings_and_config(tmp_path):
    import zarr

    from hel_warp.runs.io import read_snapshot
    from hel_warp.runs.run import Run

    solver = build()
    Run(solver, run_config(tmp_path, 6, vtk=True), case_config={"name": "test-case"}).run()
    root = zarr.open_group(str(tmp_path / "run.zarr"), mode="r")
    config = root.attrs["config"]
    assert config["hel"]["dt"] == DT and config["collision"]["name"] == "ktgf"
    assert config["hel"]["material"]["wall_restitution_normal"] == 0.8
    assert config["case"] == {"name": "test-case"} and config["run"]["end_time"] == pytest.approx(6 * DT)
    np.testing.assert_array_equal(root["step"][...], [0, 3, 6])
    assert root.attrs["snapshot_count"] == 3 and root.attrs["gas_snapshot_count"] == 3
    series = root["series"]
    np.testing.assert_array_equal(series["step"][...], np.arange(1, 7))
    for sub in ("deposit", "gas_step", "interpolate", "collide", "push", "remove_at_outlets", "reflect_at_walls",
                "inject", "step"):
        timing = series[f"timing_{sub}"][...]
        assert timing.shape == (6,) and np.all(timing > 0)
    assert np.all(series["timing_step"][...] >= series["timing_gas_step"][...])
    arrays, attrs = read_snapshot(tmp_path, -1)
    assert attrs["step"] == 6 and attrs["count"] == arrays["x"].shape[0] == solver.pool.alive_count()
    assert arrays["x"].shape[0] > 0  # injected parcels are in the last snapshot
    assert root["gas"]["000002"]["cell_velocity"].shape == (8, 6, 8, 3)
    vtk = sorted(p.name for p in (tmp_path / "vtk").iterdir())
    assert {"particles.pvd", "gas.pvd", "particles_0002.vtp", "gas_0002.vti"} <= set(vtk)
    assert (tmp_path / "checkpoint.npz").exists()


def test_collision_counts_hook_is_written_per_step(tmp_path):
    import zarr

    from hel_warp.hel import NoCollision
    from hel_warp.runs.run import Run

    class Counting(NoCollision):
        name = "counting"
        calls = 0

        def accelerate(self, solver):
            super().accelerate(solver)
            self.calls += 1

        def counts(self):
            return {"pairs": 2 * self.calls, "clusters": 1} if self.calls != 2 else {"late": 7}

    solver = build("none")
    solver.collision = Counting()
    Run(solver, run_config(tmp_path, 4, output_every=2)).run()
    series = zarr.open_group(str(tmp_path / "run.zarr"), mode="r")["series"]
    # a count missing on a step reads 0 there; every series is one entry per step
    np.testing.assert_array_equal(series["collisions_pairs"][...], [2, 0, 6, 8])
    np.testing.assert_array_equal(series["collisions_clusters"][...], [1, 0, 1, 1])
    np.testing.assert_array_equal(series["collisions_late"][...], [0, 7, 0, 0])


def test_restart_continues_bitwise_identically(tmp_path):
    """2N steps in one go == N steps, interruption a few steps later, restart from the checkpoint at N, N more."""
    import zarr

    from hel_warp.runs.run import Run

    n = 6
    straight = build()
    Run(straight, run_config(tmp_path / "a", 2 * n)).run()

    first = build()
    with pytest.raises(Interrupt):  # checkpoints at 0 and 6 (every 6 steps), a snapshot at 9 that must be dropped
        Run(first, run_config(tmp_path / "b", 2 * n, checkpoint_every=n)).run(progress=stop_at(n + 4))
    resumed = build()
    Run(resumed, run_config(tmp_path / "b", 2 * n, checkpoint_every=n), restart=True).run()
    assert resumed.step_count == straight.step_count == 2 * n
    a, b = straight.state(), resumed.state()
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)  # bitwise (NaN-free, so equality is exact)
    za = zarr.open_group(str(tmp_path / "a" / "run.zarr"), mode="r")
    zb = zarr.open_group(str(tmp_path / "b" / "run.zarr"), mode="r")
    np.testing.assert_array_equal(za["step"][...], zb["step"][...])
    np.testing.assert_array_equal(za["series"]["step"][...], zb["series"]["step"][...])
    np.testing.assert_array_equal(za["series"]["wall_hits"][...], zb["series"]["wall_hits"][...])
    for k in range(za.attrs["snapshot_count"]):
        np.testing.assert_array_equal(za["snapshots"][f"{k:06d}"]["x"][...], zb["snapshots"][f"{k:06d}"]["x"][...])
    # the run exercised injection, walls and the outlet
    assert straight.pool.used == 300 and straight.wall_hit_count() > 0 and straight.pool.removed_count() > 0


def test_restart_with_another_configuration_is_refused(tmp_path):
    from hel_warp.runs.run import Run

    Run(build(), run_config(tmp_path, 3)).run()
    with pytest.raises(ConfigError, match="another configuration"):
        Run(build("none"), run_config(tmp_path, 6), restart=True)


def test_nan_in_a_field_stops_the_run_and_keeps_the_last_checkpoint(tmp_path):
    from hel_warp.runs.run import Run, read_checkpoint

    def poison(solver):
        if solver.step_count == 6:  # after the step, before the output check of step 6
            p = solver.gas.cell_pressure.numpy()
            p[2, 2, 2] = np.nan
            solver.gas.cell_pressure.assign(p)

    solver = build()
    with pytest.raises(HelWarpError, match=r"NaN/inf found at step 6.*gas cell_pressure.*last good checkpoint "
                                           r"\(step 3\).*--restart"):
        Run(solver, run_config(tmp_path, 9)).run(progress=poison)
    state, _, path = read_checkpoint(tmp_path)
    assert path.name == "checkpoint.npz" and int(state["step"]) == 3
    assert np.all(np.isfinite(state["gas/cell_pressure"]))
    import zarr

    np.testing.assert_array_equal(zarr.open_group(str(tmp_path / "run.zarr"), mode="r")["step"][...], [0, 3])


def test_default_checkpoints_are_a_wall_clock_apart_and_a_restart_from_one_is_exact(tmp_path):
    """No --checkpoint-interval: a checkpoint at the first step, then none sooner than ``checkpoint_wall_s`` of wall
    clock (here never within the run), the last step always; the series are complete at the end, and a run killed
    after several snapshots restarts from the step-0 checkpoint and ends bit for bit as the straight run."""
    import dataclasses

    import zarr

    from hel_warp.runs.run import CHECKPOINT_WALL_S, Run, RunConfig, read_checkpoint

    assert RunConfig(out_dir=str(tmp_path), end_time=DT, output_interval=DT).checkpoint_wall_s == CHECKPOINT_WALL_S
    gated = lambda out: dataclasses.replace(run_config(out, 9), checkpoint_wall_s=3600.0)  # noqa: E731
    straight = build()
    Run(straight, gated(tmp_path / "a")).run()
    state, _, path = read_checkpoint(tmp_path / "a")
    assert int(state["step"]) == 9
    assert int(np.load(tmp_path / "a" / "checkpoint.prev.npz")["step"]) == 0  # none at the outputs 3 and 6
    za = zarr.open_group(str(tmp_path / "a" / "run.zarr"), mode="r")
    np.testing.assert_array_equal(za["step"][...], [0, 3, 6, 9])
    np.testing.assert_array_equal(za["series"]["step"][...], np.arange(1, 10))
    np.testing.assert_array_equal(za["series"]["output_step"][...], [0, 3, 6, 9])

    first = build()
    with pytest.raises(Interrupt):  # killed at step 8: snapshots at 3 and 6 written, the checkpoint is step 0's
        Run(first, gated(tmp_path / "b")).run(progress=stop_at(8))
    assert int(read_checkpoint(tmp_path / "b")[0]["step"]) == 0
    resumed = build()
    Run(resumed, gated(tmp_path / "b"), restart=True).run()
    a, b = straight.state(), resumed.state()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    zb = zarr.open_group(str(tmp_path / "b" / "run.zarr"), mode="r")
    for name in ("step", "series/step", "series/output_step", "series/wall_hits", "series/timing_step"):
        assert zb[name].shape == za[name].shape, name
    np.testing.assert_array_equal(za["series"]["wall_hits"][...], zb["series"]["wall_hits"][...])
    np.testing.assert_array_equal(za["snapshots"]["000002"]["x"][...], zb["snapshots"]["000002"]["x"][...])


def test_pressure_solve_failure_keeps_the_checkpoint_and_gives_the_advice(tmp_path):
    from hel_warp.runs.run import Run, read_checkpoint

    def starve(solver):
        if solver.step_count == 4:
            solver.gas_solver.config = dataclasses.replace(solver.gas_solver.config, pressure_max_iterations=1,
                                                           pressure_tolerance=1e-12)

    with pytest.raises(HelWarpError, match=r"step failed at step 4.*pressure solve did not converge.*raise "
                                           r"pressure_max_iterations.*last good checkpoint \(step 3\)"):
        Run(build(), run_config(tmp_path, 9)).run(progress=starve)
    assert int(read_checkpoint(tmp_path)[0]["step"]) == 3


def test_a_torn_checkpoint_falls_back_to_the_previous_one(tmp_path):
    from hel_warp.runs.run import Run, read_checkpoint

    Run(build(), run_config(tmp_path, 6)).run()  # checkpoints at 0, 3, 6: prev holds step 3
    (tmp_path / "checkpoint.npz").write_bytes(b"torn")
    state, _, path = read_checkpoint(tmp_path)
    assert path.name == "checkpoint.prev.npz" and int(state["step"]) == 3


def test_hel_warp_run_passes_the_options_to_the_case_script(tmp_path, capsys):
    from hel_warp.cli import main

    script = tmp_path / "my_case.py"
    script.write_text("import json\n\ndef main(argv):\n    print(json.dumps(argv))\n    return 4\n")
    assert main(["run", str(script), "--diameter", "3e-4", "--out", "x"]) == 4
    assert capsys.readouterr().out.strip() == '["--diameter", "3e-4", "--out", "x"]'
    plain = tmp_path / "plain.py"
    plain.write_text("import sys\nprint('argv', sys.argv[1:])\n")  # no main(): run once as __main__
    assert main(["run", str(plain), "--a", "1"]) == 0
    assert capsys.readouterr().out.strip() == "argv ['--a', '1']"
    assert main(["run", "no_such_case"]) == 2
    assert "case script 'no_such_case' not found" in capsys.readouterr().err


def test_the_example_of_hel_warp_run_help_runs_as_printed(tmp_path, capsys, monkeypatch):
    """The command ``hel-warp run --help`` prints as its example, taken from the help text and run in an empty
    folder: it exits 0 and leaves a complete run of the case it names where it says."""
    import json
    import shlex

    from hel_warp.cli import main

    with pytest.raises(SystemExit):
        main(["run", "--help"])
    text = capsys.readouterr().out.replace("\\\n", " ")
    (line,) = [ln for ln in text.splitlines() if ln.strip().startswith("hel-warp run ")]
    argv = shlex.split(line)
    assert argv[:2] == ["hel-warp", "run"]
    monkeypatch.chdir(tmp_path)
    assert main(argv[1:]) == 0, capsys.readouterr().err[-2000:]
    out = tmp_path / argv[argv.index("--out") + 1]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "complete" and summary["check_errors"] == []
    assert summary["case"] == argv[2] and summary["collision_model"] == argv[argv.index("--collisions") + 1]


def test_an_end_time_shorter_than_one_step_is_refused(tmp_path, capsys):
    # round(end / dt) = 0 steps would write a run of no step and exit 0; the run refuses it instead
    from hel_warp.runs.run import Run, RunConfig

    with pytest.raises(ConfigError, match="shorter than one step"):
        Run(build(), RunConfig(out_dir=str(tmp_path / "a"), end_time=0.4 * DT, output_interval=DT))
    Run(build(), RunConfig(out_dir=str(tmp_path / "b"), end_time=DT, output_interval=DT)).run()  # one step: fine
    from hel_warp.cli import main  # through the case script: one line, exit 2, before any rig is built

    args = ["run", "colliding_streams", "--diameter", "315e-6", "--dt", "1e-3", "--collisions", "none",
            "--end-time", "5e-4", "--out", str(tmp_path / "c"), "--no-progress"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "shorter than one step" in err[0]
    assert not (tmp_path / "c").exists()


def test_cuda_without_a_gpu_is_a_one_line_error(tmp_path, capsys):
    import warp as wp

    from hel_warp.cli import main
    from hel_warp.runs.run import check_device

    wp.init()
    if wp.is_cuda_available():
        pytest.skip("this machine has a CUDA device")
    with pytest.raises(ConfigError, match="--device cpu"):
        check_device("cuda")
    with pytest.raises(ConfigError, match="cpu, cuda or cuda:N"):
        check_device("gpu")
    assert check_device("cpu") == "cpu"
    for argv in (["run", "colliding_streams", "--diameter", "315e-6", "--dt", "1e-3", "--collisions", "none",
                  "--end-time", "0.003", "--out", str(tmp_path / "c"), "--no-progress", "--device", "cuda"],
                 ["demo", "--out", str(tmp_path / "demo"), "--device", "cuda"],
                 # a case script that builds on the device itself: Warp's RuntimeError becomes the one line
                 ["run", "three_streams", "--collisions", "none", "--out", str(tmp_path / "t"), "--device", "cuda"],
                 ["predict", "--model", str(tmp_path / "no_model"), "--device", "cuda"]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and ": error: " in err[0] and "Traceback" not in err[0], (argv, err)
        assert "cuda" in err[0].lower() and "--device cpu" in err[0], err
    assert not (tmp_path / "demo" / "dataset").exists()  # refused before the first stage


def test_weight_aware_counts_stay_fractional(tmp_path):
    # a surrogate collision between parcels of weights 0.5 and 2 is min(w_i, w_j) = 0.5 real collisions: the
    # series must keep the fraction (an int64 series would store 0)
    import zarr

    from hel_warp.hel import NoCollision
    from hel_warp.runs.run import Run

    class Weighted(NoCollision):
        name = "weighted"

        def counts(self):
            return {"collisions": 0.5, "detected_pairs": 1}

    solver = build("none")
    solver.collision = Weighted()
    Run(solver, run_config(tmp_path, 3)).run()
    series = zarr.open_group(str(tmp_path / "run.zarr"), mode="r")["series"]
    np.testing.assert_array_equal(series["collisions_collisions"][...], [0.5, 0.5, 0.5])
    assert series["collisions_detected_pairs"].dtype == np.int64


KERNEL_SOURCE = '''
import warp as wp

@wp.kernel
def fresh_kernel(values: wp.array(dtype=float)):
    i = wp.tid()
    values[i] = values[i] * {factor!r} + wp.sin(values[i])
'''


def test_kernel_compilation_is_timed_apart_from_the_steps(tmp_path):
    """A strategy whose kernel no cache holds (a module made fresh for this test): compiling it takes seconds on
    the CPU, the step itself microseconds. The run compiles every imported Warp module before the first timed
    step, so the step timings exclude it and ``kernel_load_s`` holds it."""
    import importlib.util
    import uuid

    import warp as wp
    import zarr

    from hel_warp.hel import NoCollision
    from hel_warp.runs.run import Run

    source = tmp_path / f"fresh_{uuid.uuid4().hex}.py"
    source.write_text(KERNEL_SOURCE.format(factor=1.0 + uuid.uuid4().int % 1000 / 1e6))
    spec = importlib.util.spec_from_file_location(source.stem, source)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)

    class Fresh(NoCollision):
        name = "fresh"

        def accelerate(self, solver):
            super().accelerate(solver)
            values = wp.ones(8, dtype=float, device=solver.pool.particles.device)
            wp.launch(module.fresh_kernel, dim=8, inputs=[values], device=values.device)

    solver = build("none")
    solver.collision = Fresh()
    runner = Run(solver, run_config(tmp_path / "run", 2))
    runner.run()
    root = zarr.open_group(str(tmp_path / "run" / "run.zarr"), mode="r")
    collide = root["series"]["timing_collide"][...]
    assert root.attrs["kernel_load_s"] == pytest.approx(runner.kernel_load_s)
    # the compilation landed in kernel_load_s, not in the first step's collide timing
    assert collide[0] < 0.2 * runner.kernel_load_s, (collide, runner.kernel_load_s)


def test_load_kernels_keeps_cpu_only_modules_off_cuda():
    """``load_kernels`` builds every kernels/ module for the CPU, the serial queue included, but hands a CUDA device
    every module except ``CPU_ONLY_MODULES`` (NVRTC took over ten minutes on the queue; CUDA resolves in rounds)."""
    import types

    import warp as wp

    from hel_warp.runs.run import CPU_ONLY_MODULES, kernel_modules, load_kernels

    load_kernels("cpu")
    cpu_names = {m.name for m in kernel_modules(wp.get_device("cpu"))}
    assert set(CPU_ONLY_MODULES) <= cpu_names and "kernels.collide" in cpu_names
    cuda_names = {m.name for m in kernel_modules(types.SimpleNamespace(is_cuda=True))}
    assert cuda_names == cpu_names - set(CPU_ONLY_MODULES)


def test_counts_staged_on_the_device_come_back_row_by_row_in_step_order():
    """``HelConfig.read_back`` 'output': the run loop copies each step's collision-count arrays into a device
    buffer per dtype and reads it once per output. Staged rows come back with each step's values (int32 and
    float32 arrays, a 2-D one flattened and reshaped) and its host extras, in order; a full buffer or arrays of
    another layout are refused (the caller drains first), and after a drain the log takes a new layout."""
    import warp as wp

    from hel_warp.runs.run import _DeviceCountsLog

    log = _DeviceCountsLog(rows=3)
    counts = wp.zeros(4, dtype=wp.int32, device="cpu")
    pairs = wp.zeros((2, 2), dtype=wp.int32, device="cpu")
    speed = wp.zeros(1, dtype=wp.float32, device="cpu")
    expected = []
    for step in range(3):
        counts.assign(np.arange(4, dtype=np.int32) + 10 * step)
        pairs.assign(np.array([[step, 1], [2, 3 * step]], np.int32))
        speed.assign(np.array([0.5 * step], np.float32))
        assert log.stage({"step": step}, {"counts": counts, "pairs": pairs, "speed": speed}, {"windows": step + 1})
        expected.append((counts.numpy().copy(), pairs.numpy().copy(), speed.numpy().copy()))
    assert not log.stage({"step": 3}, {"counts": counts, "pairs": pairs, "speed": speed}, {})  # full
    drained = log.drain()
    assert [row["step"] for row, _, _ in drained] == [0, 1, 2]
    for (row, host, extras), (c, p, s) in zip(drained, expected):
        assert extras == {"windows": row["step"] + 1}
        assert np.array_equal(host["counts"], c) and np.array_equal(host["pairs"], p) and host["pairs"].shape == (2, 2)
        assert np.array_equal(host["speed"], s)
    assert log.drain() == []
    other = wp.full(3, 7, dtype=wp.int32, device="cpu")
    assert log.stage({"step": 4}, {"cell_counts": other}, {})  # a new layout once nothing waits
    assert not log.stage({"step": 5}, {"counts": counts}, {})  # another layout while a row waits
    (row, host, _), = log.drain()
    assert row["step"] == 4 and host["cell_counts"].tolist() == [7, 7, 7]

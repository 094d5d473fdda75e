"""Every CUDA-only branch of the engine, run on the test device through the same functions.

No GPU has run this code yet, so each branch that the engine takes only on CUDA is exercised here on whatever
device ``HEL_WARP_DEVICE`` names (the ``device`` fixture, default ``cpu``) and compared with the branch the CPU
takes today. Warp >= 1.19 records and replays graphs on the CPU too (``wp.ScopedCapture`` / ``capture_launch``,
``capture_if`` and ``capture_while`` as conditional nodes), so even the captured paths run here, captured; what
still differs on a GPU is the graph backend (CUDA graphs vs Warp's CPU replay) and the CUDA compiler.

References (docs/developer/conventions.md rule 9): the eager steps for the captured ones (bit for bit: the same kernels in the
same order on the same data), the CPU's native CG for warp.optim.linear.cg (both stop at ||r|| <= tol ||b||),
the CPU's rows-per-thread default and XGBoost's own ``inplace_predict`` for the forest (bit for bit).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from tests.test_collision_models import D, RHO, trained_models  # noqa: F401  (fixture)


def require_graph_conditionals(device):
    """CUDA graphs with conditional nodes (capture_if / capture_while) need CUDA >= 12.4 and its driver; Warp's CPU
    graphs always have them."""
    if wp.get_device(device).is_cuda and not wp.is_conditional_graph_supported():
        pytest.skip("this CUDA driver/toolkit has no conditional graph nodes (CUDA >= 12.4); the DEM launches eagerly")


# ------------------------------------------------------------------------------ Warp's conditional nodes
@wp.kernel
def count_down(counter: wp.array(dtype=wp.int32), total: wp.array(dtype=wp.float32)):
    total[0] = total[0] + 1.0
    counter[0] = counter[0] - 1


@wp.kernel
def add_value(total: wp.array(dtype=wp.float32), value: wp.float32):
    total[0] = total[0] + value


def test_capture_while_and_if_are_a_host_loop_and_branch_outside_a_capture_and_nodes_inside(device):
    """What the engine relies on: outside a capture, ``wp.capture_while`` is a host loop that calls its body while
    the device flag is non-zero and ``wp.capture_if`` a host branch (DEMSolver._advance, DemCollision.simulate,
    kernels/collide.py resolve_swept run so on every device today); under a capture each body is called once to
    record it, and the replayed graph takes the loop and the branch from the flag's value at replay time."""
    require_graph_conditionals(device)
    counter = wp.array([4], dtype=wp.int32, device=device)
    flag = wp.zeros(1, dtype=wp.int32, device=device)
    total = wp.zeros(1, dtype=wp.float32, device=device)
    calls = {"while": 0, "if": 0}

    def body():
        calls["while"] += 1
        wp.launch(count_down, dim=1, inputs=[counter, total], device=device)

    def branch():
        calls["if"] += 1
        wp.launch(add_value, dim=1, inputs=[total, 100.0], device=device)

    wp.capture_while(counter, body)
    wp.capture_if(flag, on_true=branch)  # flag 0: not taken
    assert calls == {"while": 4, "if": 0} and total.numpy()[0] == 4.0 and counter.numpy()[0] == 0

    with wp.ScopedCapture(device=device) as capture:
        counter.fill_(3)
        wp.capture_while(counter, body)
        wp.capture_if(flag, on_true=branch)
    assert calls == {"while": 5, "if": 1}  # recorded once each, nothing run yet
    assert total.numpy()[0] == 4.0
    wp.capture_launch(capture.graph)
    assert total.numpy()[0] == 7.0  # three rounds, branch not taken (flag 0 at replay)
    flag.fill_(1)
    wp.capture_launch(capture.graph)
    assert total.numpy()[0] == 110.0 and calls == {"while": 5, "if": 1}  # taken from the replay-time flag


# ------------------------------------------------------------------------------ DEM: graph-captured sub-steps
def _dem_column(device, **config):
    from hel_warp.collisions.dem import DEMConfig, DEMSolver
    from hel_warp.material import Material
    from hel_warp.parcels.particles import Particles, lattice_positions

    n = 800
    material = Material(density=2500.0, youngs_modulus=1e8, poisson_ratio=0.3, restitution=0.5, friction=0.3)
    lo, hi = (0.0, 0.0, 0.0), (0.02, 0.02, 0.06)
    x = lattice_positions(n, 2.3e-3, lo, hi, jitter=0.2e-3, seed=5)
    radius = np.random.default_rng(5).uniform(0.9e-3, 1.0e-3, n)
    v = np.random.default_rng(6).normal(0.0, 0.5, (n, 3))  # a stirred column: lists rebuilt every ~100 steps
    p = Particles.from_numpy(x, radius, v=v, density=material.density, box_lo=lo, box_hi=hi, device=device)
    return DEMSolver(DEMConfig(material=material, box_lo=lo, box_hi=hi, **config), p)


def test_dem_graph_captured_steps_equal_the_eager_steps(device):
    """``DEMSolver.simulate`` on CUDA: ``cuda_graph_steps`` steps captured once (``_advance`` with its ``capture_if``
    rebuild) and replayed, the remainder eager, with the full contact list and separate kernels CUDA keeps
    (``half_list`` is CPU-only). Here the same branch (``capture_on_cpu``, ``half_list=False``) against the same
    solver launching eagerly (``cuda_graph_steps = 0``): the same kernels in the same order on the same data, so bit
    for bit, list rebuilds inside the graph included; contact onsets equal."""
    require_graph_conditionals(device)
    graph_steps, n_steps = 25, 2 * 25 + 7  # two replays and an eager remainder
    eager = _dem_column(device, sort_every=0, cuda_graph_steps=0, half_list=False)
    graph = _dem_column(device, sort_every=0, cuda_graph_steps=graph_steps, capture_on_cpu=True, half_list=False)
    assert graph._use_graph and not eager._use_graph and not graph.half_list
    for _ in range(20):  # 1140 steps, rebuilds inside the replayed graphs (7 of 57 steps run eagerly)
        eager.simulate(n_steps)
        graph.simulate(n_steps)
    fell_back = graph._graph is None and wp.get_device(device).is_cuda
    assert graph.rebuilds == eager.rebuilds > 8  # the conditional rebuild was taken inside the graph
    a, b = eager.particles.to_numpy(), graph.particles.to_numpy()
    for name in ("x", "v", "omega"):
        assert a[name].tobytes() == b[name].tobytes(), name
    assert graph.onset_counts() == eager.onset_counts() and eager.onset_counts()["collisions"] > 0
    assert graph.steps_done == eager.steps_done == 20 * n_steps
    if fell_back:  # the eager fallback gave the eager answer; the graph itself is the known defect
        pytest.xfail("CUDA: the driver refused the DEM's graph and DEMSolver fell back to eager steps (on the H200 "
                     "with Warp 1.19 the cause was wp.HashGrid.build inside the conditional body, now built outside "
                     "it; python scripts/probe_dem_graph.py names the refused piece)")
    assert graph._graph is not None
    print(f"DEM graph replay vs eager: {graph.rebuilds} list builds, {eager.onset_counts()['collisions']} onsets, "
          "x, v, omega bit for bit")


def test_dem_graph_path_defaults_to_no_sort_and_agrees_with_the_cpu_default(device):
    """The CUDA defaults (full contact list, ``sort_every`` 0 so that the graph can run, captured) against today's
    CPU defaults (half list in two fused passes, a spatial sort every 10 rebuilds, eager): the sort reorders the
    particles, so they may agree only to float32 round-off grown over the run (1e-9 m asked of |x| ~ 0.02 m). 1200
    steps of the stirred column, ~12 list builds: measured equal to the last bit on the CPU."""
    graph = _dem_column(device, capture_on_cpu=True, half_list=False)
    cpu_default = _dem_column(device)
    on_cuda = wp.get_device(device).is_cuda
    expect_sort = 0 if on_cuda and wp.is_conditional_graph_supported() else 10
    assert graph.sort_every == 0 and graph._use_graph and not graph.half_list
    assert cpu_default.sort_every == expect_sort and cpu_default.half_list == (not on_cuda)
    for solver in (graph, cpu_default):
        solver.simulate(1200)
    assert cpu_default.rebuilds > 10  # a second sort came (every 10 list builds, the first at construction)
    a, b = graph.particles.to_numpy(), cpu_default.particles.to_numpy()  # original order
    dx = float(np.abs(a["x"] - b["x"]).max())
    dv = float(np.abs(a["v"] - b["v"]).max())
    print(f"graph (no sort) vs CPU default (sort every 10): max |dx| = {dx:.2e} m, max |dv| = {dv:.2e} m/s")
    assert dx <= 1e-9 and dv <= 1e-6


def test_the_cpu_only_half_list_is_refused_on_cuda_and_the_cpu_default(device):
    """``DEMConfig.half_list`` (each pair once, forces scattered to both spheres in one fused pass) relies on the
    CPU running threads in index order; on CUDA it is refused with a message (DEMSolver and
    ``launch_forces_kick``), on the CPU it is the default. Equality with the full list: the graph tests above."""
    from hel_warp.errors import ConfigError

    if wp.get_device(device).is_cuda:
        with pytest.raises(ConfigError, match="half_list"):
            _dem_column(device, half_list=True)
        assert not _dem_column(device).half_list
    else:
        assert _dem_column(device).half_list and _dem_column(device, half_list=True).half_list


# ------------------------------------------------------------------------------ gas: warp.optim.linear.cg
def _projection_problem(device, linear_solver, preconditioner):
    """The closed L-shaped cavity of tests/test_gas.py with random face velocities and eps_f: one projection."""
    from hel_warp.gas.solver import GasConfig, GasField, GasSolver
    from hel_warp.gas.grid import Box, Channel, Geometry, Grid

    rng = np.random.default_rng(1)
    grid = Grid(spacing=1e-3, shape=(12, 10, 8))
    geometry = Geometry(shapes=(Box(lo=(1e-3, 1e-3, 1e-3), hi=(7e-3, 9e-3, 7e-3)),
                                Channel(start=(4e-3, 5e-3, 4e-3), end=(11e-3, 8e-3, 4e-3), width=3.5e-3, height=5e-3)))
    domain = geometry.build(grid, device=device)
    solver = GasSolver(domain, GasConfig(pressure_tolerance=1e-6, linear_solver=linear_solver,
                                         pressure_preconditioner=preconditioner,
                                         pressure_preconditioner_relaxation=0.0), device=device)
    gas = GasField(domain, device=device)
    gas.set_face_velocity([rng.normal(size=a.shape) for a in gas.face_arrays()])
    gas.cell_eps_s.assign(rng.uniform(0.0, 0.7, size=grid.shape).astype(np.float32))
    solver.update_cell_state(gas)
    fluid = domain.cell_fluid.numpy().astype(bool)
    eps_f = gas.cell_eps_f.numpy().astype(np.float64)
    change = rng.uniform(-0.05, 0.05, size=grid.shape)
    change = np.where(fluid, change - change[fluid].mean(), 0.0)  # zero-mean: the closed cavity's problem is solvable
    gas.cell_eps_f_prev.assign((eps_f - change).astype(np.float32))
    return grid, fluid, solver, gas


@pytest.mark.parametrize("preconditioner", ["multigrid", "ic"])
def test_warp_cg_with_our_preconditioner_equals_the_native_cg(device, preconditioner):
    """``GasConfig.linear_solver = 'auto'`` takes warp.optim.linear.cg on CUDA (M = our aggregation-multigrid V-cycle,
    or Jacobi where the CPU uses IC) and the native Warp-kernel PCG on the CPU. Both here on the same projection.

    Each stops at ||r|| <= tol ||b|| (r = (rho h^2/dt) x the continuity residual), so the difference of the two
    projected fields has a continuity residual of at most 2 tol ||b|| (plus float32 rounding of the stored faces,
    ~1e-7 |u|/h per cell), and both leave <= tol of the residual before. Measured on the CPU: with the V-cycle the
    two give the same float64 pressure bit for bit (warp's cg reports its iterations rounded up to its check_every
    of 10: 10 where the native CG took 5, yet the same iterate); Jacobi vs IC(0) 1.2e-6 of max |u|."""
    from tests.test_gas import continuity_residual

    dt, tol = 1e-3, 1e-6
    fields = {}
    for linear_solver in ("warp", "native"):
        grid, fluid, solver, gas = _projection_problem(device, linear_solver, preconditioner)
        assert solver.linear_solver == linear_solver
        eps_f, eps_prev = (a.numpy().astype(np.float64) for a in (gas.cell_eps_f, gas.cell_eps_f_prev))
        before = continuity_residual(grid, fluid, gas.face_arrays(), eps_f, eps_prev, dt)
        before = np.where(fluid, before - before[fluid].mean(), 0.0)
        solver.project(gas, dt)
        faces = [a.astype(np.float64) for a in gas.face_arrays()]
        after = continuity_residual(grid, fluid, faces, eps_f, eps_prev, dt)
        fields[linear_solver] = (faces, gas.cell_pressure.numpy().astype(np.float64), before, after,
                                 solver.last_iterations["pressure"])
    (u_w, p_w, before, after_w, it_w), (u_n, p_n, _, after_n, it_n) = fields["warp"], fields["native"]
    u_max = max(np.abs(a).max() for a in u_n)
    rounding = 4 * 6e-8 * u_max / grid.spacing * math.sqrt(fluid.sum())
    b = np.linalg.norm(before)
    assert np.linalg.norm(after_w) <= tol * b + rounding and np.linalg.norm(after_n) <= tol * b + rounding
    # the difference field: div(eps_f (u_w - u_n)) alone (the eps_f change cancels)
    diff = continuity_residual(grid, fluid, [a - c for a, c in zip(u_w, u_n)], eps_f, eps_f, dt)
    assert np.linalg.norm(diff) <= 2 * tol * b + 2 * rounding, (np.linalg.norm(diff), b)
    du = max(np.abs(a - c).max() for a, c in zip(u_w, u_n)) / u_max
    p_w, p_n = p_w[fluid] - p_w[fluid].mean(), p_n[fluid] - p_n[fluid].mean()  # p is defined up to a constant
    dp = np.abs(p_w - p_n).max() / np.abs(p_n).max()
    print(f"{preconditioner}: warp cg {it_w} / native {it_n} iterations; max |u_warp - u_native| / max |u| = "
          f"{du:.2e}; |div diff| / |div before| = {np.linalg.norm(diff) / b:.2e}; pressure (mean removed) {dp:.2e}")
    assert du <= 1e-4


# ------------------------------------------------------------------------------ forest: the CUDA launch shape
def test_forest_at_the_cuda_rows_per_thread_equals_the_cpu_default_and_xgboost(device, trained_models):
    """``ForestPredictor`` walks one row per thread on CUDA and 64 on the CPU (explicit layout); the perfect layout
    (the engine's batched rounds) has one shape on both. Every launch shape gives XGBoost's own prediction, bit for
    bit (the thresholds are folded so float32 branches as XGBoost does; the leaf sums in the same order)."""
    from hel_warp.collisions.forest import ForestPredictor, load_forest
    from surrogate.artifact import load_artifact
    from surrogate.features import form_rows, synthetic_collisions

    model_dir = trained_models["contact"]
    art = load_artifact(model_dir, boosters=True)
    flat = load_forest(model_dir)
    rows = form_rows("contact", synthetic_collisions(3000, seed=4, central_fraction=0.5))
    raw = np.ascontiguousarray(rows.features, dtype=np.float32)
    ref = art.predict(raw)
    outs = {}
    for layout, rows_per_thread in (("explicit", 1), ("explicit", 64), ("perfect", None)):
        predictor = ForestPredictor(flat, device=device, layout=layout, rows_per_thread=rows_per_thread)
        outs[(layout, rows_per_thread)] = predictor.predict_features(raw)
    for key, out in outs.items():
        assert np.array_equal(out, outs[("explicit", 1)]), key
    print(f"forest: {len(raw)} rows, explicit 1 / 64 rows per thread and perfect equal; max |ours - XGBoost| = "
          f"{np.abs(outs[('explicit', 1)] - ref).max():.1e}")
    assert np.abs(outs[("explicit", 1)] - ref).max() <= 2 ** -20 * max(1.0, np.abs(ref).max()), \
        np.abs(outs[("explicit", 1)] - ref).max()


def test_bench_forest_runs_its_xgboost_cuda_branch_and_says_where_xgboost_ran(tmp_path, trained_models):
    """scripts/bench_forest.py ``--xgboost-device cuda`` sets XGBoost's CUDA predictor and passes it the rows the
    same way on any machine; without a GPU (or with an XGBoost built without CUDA, the xgboost-cpu wheel) XGBoost
    falls back to its CPU predictor, which the result names (``xgboost_device_used``), so a GPU run cannot silently
    time the CPU. The figures agree with our forest."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, str(root / "scripts" / "bench_forest.py"), "--model", trained_models["contact"],
                          "--samples", "2000", "--repeats", "1", "--xgboost-device", "cuda", "--json"],
                         capture_output=True, text=True, cwd=root)
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["xgboost_device_requested"] == "cuda"
    import xgboost

    expected = "cuda" if wp.is_cuda_available() and xgboost.build_info().get("USE_CUDA", False) else "cpu"
    assert result["xgboost_device_used"].startswith(expected), result["xgboost_device_used"]
    assert result["max_abs_diff_vs_xgboost"] <= 1e-5 and result["samples"] == 2000


# ------------------------------------------------------------------------------ swept rounds: capture_while
def _periodic_gas(n, eps, seed=2, theta=1.0):
    rng = np.random.default_rng(seed)
    side = (n * math.pi * D**3 / 6.0 / eps) ** (1.0 / 3.0)
    k = int(math.ceil(n ** (1.0 / 3.0)))
    g = (np.arange(k) + 0.5) * side / k
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)[:n]
    x = np.mod(x + rng.uniform(-0.5, 0.5, x.shape) * (side / k - 1.01 * D), side)
    v = rng.normal(0.0, math.sqrt(theta), (n, 3))
    return x, v - v.mean(axis=0), side


@pytest.mark.parametrize("batched", [True, False])
def test_swept_rounds_captured_as_a_graph_loop_equal_the_eager_rounds(device, trained_models, monkeypatch, batched):
    """kernels/collide.py ``resolve_swept`` writes its event rounds as ``wp.capture_while`` so that on CUDA the whole
    loop, the batched forest of each round included, can be one graph (a while node) instead of a host sync per
    round. Here the call captured into a graph and replayed, against the same call run eagerly (the host loop every
    device takes today): bit for bit, and the same counts, on a dense periodic gas with chains of collisions."""
    import kernels.collide as kc
    from hel_warp.collisions.models import SurrogateCollision
    from hel_warp.parcels.particles import Particles

    require_graph_conditionals(device)
    eager_resolve = kc.resolve_swept
    replays = []

    def captured_resolve(*args, **kwargs):
        dev = args[2].device
        with wp.ScopedCapture(device=dev) as capture:
            eager_resolve(*args, **kwargs)
        wp.capture_launch(capture.graph)
        replays.append(1)

    x, v, side = _periodic_gas(1000, 0.05)
    results = []
    for resolve in (eager_resolve, captured_resolve):
        monkeypatch.setattr(kc, "resolve_swept", resolve)
        p = Particles.from_numpy(x, 0.5 * D, v=v, density=RHO, check_overlap=False, device=device)
        strategy = SurrogateCollision(model_dir=trained_models["contact"], periodic_box=(side,) * 3, batched=batched,
                                      ordering="parallel")  # the rounds (a GPU's resolution), not the CPU's queue
        strategy.collide(p, 2e-4)
        assert (strategy.batch_forest is not None) == batched
        results.append((p.v.numpy().copy(), strategy.swept.t_last.numpy().copy(), strategy.counts()))
    (v_eager, t_eager, c_eager), (v_graph, t_graph, c_graph) = results
    assert len(replays) == c_graph["windows"]  # one capture per window of the step
    assert c_eager["collisions"] > 100 and c_eager["rounds"] > 3  # several rounds: the loop really loops
    assert c_graph == c_eager
    assert np.array_equal(v_graph, v_eager) and np.array_equal(t_graph, t_eager)
    print(f"swept rounds (batched={batched}): captured = eager, {c_eager['collisions']} collisions in "
          f"{c_eager['rounds']} rounds, {c_eager['surrogate_calls']} surrogate calls")


# ------------------------------------------------------------------------------ cell rounds: capture_while
def test_cell_rounds_captured_as_a_graph_loop_equal_the_eager_rounds(device, trained_models, monkeypatch):
    """kernels/cell_collide.py ``collide_cells`` (parcels of weight > 1 collide per cell) runs its batched
    forest rounds as ``wp.capture_while`` too, then finishes the dense cells inline. The call captured into a graph
    and replayed, against the same call eager: bit for bit, and the same counts, two steps of a dense gas of
    weight-8 parcels."""
    import kernels.cell_collide as kcc
    from hel_warp.collisions.models import SurrogateCollision
    from hel_warp.parcels.particles import Particles

    require_graph_conditionals(device)
    eager_collide = kcc.collide_cells
    replays = []

    def captured_collide(*args, **kwargs):
        with wp.ScopedCapture(device=args[2].device) as capture:
            eager_collide(*args, **kwargs)
        wp.capture_launch(capture.graph)
        replays.append(1)

    rng = np.random.default_rng(11)
    n, eps = 1500, 0.05
    side = (8 * n * math.pi * D**3 / (6.0 * eps)) ** (1.0 / 3.0)
    x, v = rng.uniform(0.0, side, size=(n, 3)), rng.normal(size=(n, 3))
    results = []
    for collide in (eager_collide, captured_collide):
        monkeypatch.setattr(kcc, "collide_cells", collide)
        p = Particles.from_numpy(x, 0.5 * D, v=v, density=RHO, weight=8.0, check_overlap=False, device=device)
        strategy = SurrogateCollision(model_dir=trained_models["contact"], detection="cell", periodic_box=(side,) * 3,
                                      seed=3)
        for _ in range(2):
            strategy.collide(p, 1e-3)
        assert strategy.batch_forest is not None
        results.append((p.v.numpy().copy(), strategy.counts()))
    assert len(replays) >= 2
    (v_eager, c_eager), (v_graph, c_graph) = results
    assert c_eager["rounds"] > 1 and c_eager["collisions"] > 100  # the loop really loops
    assert c_graph == c_eager and np.array_equal(v_graph, v_eager)
    print(f"cell rounds: captured = eager, {c_eager['collisions']} collisions, {c_eager['rounds']} batched rounds")


# ------------------------------------------------------------------------------ the swept search's cell list
def test_cell_list_built_on_the_device_is_the_stable_sort_by_cell_of_a_brute_force(device):
    """kernels/cell_list.py ``build_cell_list`` sorts with ``wp.utils.radix_sort_pairs`` and scans with
    ``wp.utils.array_scan``: CUB's radix sort and scan on CUDA, Warp's host loops on the CPU. The swept rounds
    rely on the order it documents (by cell, x fastest; within a cell by point index, dead points last), so the
    structure built on the device must equal numpy's stable argsort of the keys and the exclusive cumulative sum
    of the counts, exactly. Points are jittered by at most 0.3 cell widths about cell centres, so each key is
    unambiguous in any rounding (no point within 0.2 widths of a face). Then the searches through it against the
    O(N^2) brute force of tests/test_cell_list.py (open and periodic), on the device."""
    from kernels.cell_list import DEAD_CELL_KEY, CellList, build_cell_list
    from tests.test_cell_list import brute_force, search

    rng = np.random.default_rng(21)
    n, dims, width = 3000, (7, 5, 6), 1e-3
    origin = np.array([-2e-3, 1e-3, 0.5e-3])
    cell = np.stack([rng.integers(0, d, n) for d in dims], axis=1)  # several points per cell: ties to break
    points = (origin + (cell + 0.5 + rng.uniform(-0.3, 0.3, (n, 3))) * width).astype(np.float32)
    alive = (rng.uniform(size=n) > 0.15).astype(np.int32)
    cells = CellList()
    cells.origin, cells.inv_width, cells.dims, cells.periodic = tuple(origin), 1.0 / width, dims, 0
    total = int(np.prod(dims))
    cells.cell_start = wp.zeros(total + 1, dtype=wp.int32, device=device)
    cells.slot_key = wp.zeros(2 * n, dtype=wp.int32, device=device)
    cells.slot_point = wp.zeros(2 * n, dtype=wp.int32, device=device)
    cells.slot_position = wp.zeros(n, dtype=wp.vec3, device=device)
    build_cell_list(cells, wp.array(points, dtype=wp.vec3, device=device), wp.array(alive, dtype=wp.int32,
                    device=device), wp.zeros(total + 1, dtype=wp.int32, device=device))
    # reference: the key of every point (x fastest), dead ones after every cell; stable sort; exclusive scan
    key = np.where(alive != 0, (cell[:, 2] * dims[1] + cell[:, 1]) * dims[0] + cell[:, 0], int(DEAD_CELL_KEY))
    order = np.argsort(key, kind="stable")
    counts = np.bincount(key[alive != 0], minlength=total + 1)
    assert np.array_equal(cells.slot_key.numpy()[:n], key[order])
    assert np.array_equal(cells.slot_point.numpy()[:n], order)
    assert np.array_equal(cells.cell_start.numpy(), np.concatenate([[0], np.cumsum(counts)[:-1]]))
    assert int(cells.cell_start.numpy()[-1]) == int(alive.sum())
    assert np.array_equal(cells.slot_position.numpy(), points[order])
    assert counts.max() >= 4  # within-cell order really tested
    # the searches through the list, on the device, against the brute force
    for periodic_side in (None, 0.01):
        pts = rng.uniform(0.0, 0.01, size=(1200, 3)).astype(np.float32)
        live = (rng.uniform(size=len(pts)) > 0.1).astype(np.int32)
        with wp.ScopedDevice(device):
            _, count, index_sum, _ = search(pts, live, 1.1e-3, 5e-4, periodic_side)
        ref_count, ref_sum = brute_force(pts, live, 1.1e-3, periodic_side)
        on = live != 0
        assert np.array_equal(count[on], ref_count[on]) and np.array_equal(index_sum[on], ref_sum[on])
    print(f"cell list on {device}: {n} points ({int((alive == 0).sum())} dead), up to {counts.max()} per cell, "
          "= numpy's stable sort and exclusive scan exactly; searches = brute force (open, periodic)")


# ------------------------------------------------------------------------------ swept HEL step: kick, walls
@pytest.mark.parametrize("wall_contact", ["surface", "point"])
def test_swept_hel_steps_kick_first_with_wall_events_captured_equal_the_eager_steps(device, trained_models,
                                                                                   monkeypatch, wall_contact):
    """The rig's surrogate path (cases/colliding_streams.py with ``--collisions surrogate``, the gpu_check's
    ``rig_surrogate`` on CUDA): in a ``HelSolver`` with walls, ``SurrogateCollision.accelerate`` pushes the
    velocities first (``kick_first``), the swept rounds resolve collisions and wall events (``swept_resolve_walls``)
    in time order, with the batched forest, and ``advance`` drifts the parcels to their paths' ends
    (``drift_swept``). The rounds (``resolve_swept``) captured into a graph and replayed (the while node a CUDA
    graph would take) against the same steps eager: positions, velocities and every count bit for bit, over two
    HEL steps of 315 um parcels in the closed box of tests/test_hel_step.py, the walls met by the parcels' surface
    (the rig's default) or their centre."""
    import kernels.collide as kc
    from hel_warp.collisions.models import SurrogateCollision
    from tests.test_hel_step import BOX_HI, make_solver

    require_graph_conditionals(device)
    eager_resolve, eager_drift = kc.resolve_swept, kc.launch_drift_swept
    calls = {"replays": 0, "drifts": 0}

    def captured_resolve(*args, **kwargs):
        with wp.ScopedCapture(device=args[2].device) as capture:
            eager_resolve(*args, **kwargs)
        wp.capture_launch(capture.graph)
        calls["replays"] += 1

    def counted_drift(*args, **kwargs):
        calls["drifts"] += 1
        return eager_drift(*args, **kwargs)

    monkeypatch.setattr(kc, "launch_drift_swept", counted_drift)
    rng = np.random.default_rng(8)
    radius = 0.5 * D
    x = rng.uniform([1.5 * radius] * 3, np.asarray(BOX_HI) - 1.5 * radius, (6000, 3))
    keep = np.ones(len(x), bool)
    for i in range(len(x)):  # a non-overlapping start
        if keep[i]:
            keep &= (np.linalg.norm(x - x[i], axis=1) >= 2.02 * radius) | (np.arange(len(x)) <= i)
    x = x[keep][:1500]
    v = rng.normal(0.0, 1.5, (len(x), 3))
    results = []
    with wp.ScopedDevice(device):
        for resolve in (eager_resolve, captured_resolve):
            monkeypatch.setattr(kc, "resolve_swept", resolve)
            strategy = SurrogateCollision(model_dir=trained_models["contact"], detection="swept", ordering="parallel")
            assert strategy.kick_first and strategy.wall_events
            solver = make_solver(x=x, v=v, radius=radius, density=RHO, collision=strategy, wall_contact=wall_contact)
            assert solver.wall_params.surface == (wall_contact == "surface")
            assert solver.pool.particles.device == wp.get_device(device)
            counts = {"collisions": 0, "wall_events": 0, "rounds": 0, "windows": 0}
            for _ in range(2):
                solver.step()
                for key in counts:
                    counts[key] += strategy.counts()[key]
            assert strategy.batch_forest is not None
            p = solver.pool.particles
            results.append((p.x.numpy().copy(), p.v.numpy().copy(), counts))
    (x_eager, v_eager, c_eager), (x_graph, v_graph, c_graph) = results
    # every step took the kick-first path, captured once per window of the step
    assert calls == {"replays": c_graph["windows"], "drifts": 4}
    assert c_eager["collisions"] > 20 and c_eager["wall_events"] > 20 and c_eager["rounds"] > 4
    assert c_graph == c_eager
    assert np.array_equal(x_graph, x_eager) and np.array_equal(v_graph, v_eager)
    print(f"swept HEL steps (kick first, {wall_contact} wall events) captured = eager: {c_eager}")


# ------------------------------------------------------------------------------ swept rounds: thread order
@pytest.mark.parametrize("space", ["periodic", "walls"])
def test_swept_rounds_do_not_depend_on_which_thread_holds_which_parcel(device, trained_models, space):
    """A GPU runs a launch's threads in no fixed order; the CPU runs them in index order. The swept rounds are
    written so that no result depends on it: events go to both parcels by an int64 atomic_min on (time, partner),
    the batched forest's rows, the wall events' rows and the large-parcel list are filled by atomic counters
    whose order changes no outcome. The CPU's proxy for another thread order: the same parcels under other
    labels (a random permutation: every launch then visits them in another order, the cell list holds them in
    another order within a cell). Reference: the unpermuted call, mapped back: measured equal bit for bit, counts
    included (a race between threads of one launch, invisible to the CPU's fixed order, would show here as a
    difference under some labelling)."""
    from hel_warp.collisions.models import SurrogateCollision
    from hel_warp.parcels.particles import Particles
    from tests.test_swept_walls import SIDE, box_walls

    if space == "periodic":
        x, v, side = _periodic_gas(1000, 0.05)
        box, dt = (side,) * 3, 2e-4
    else:  # 800 parcels in the walled box [0, SIDE]^3, fast enough that many meet a wall within the step
        x, v, _ = _periodic_gas(800, 0.03, seed=6, theta=4.0)
        x = x * (SIDE - 2 * D) / x.max() + D
        box, dt = None, 1e-3
    perm = np.random.default_rng(3).permutation(len(x))
    results = []
    for order in (np.arange(len(x)), perm):
        p = Particles.from_numpy(x[order], 0.5 * D, v=v[order], density=RHO, check_overlap=False, device=device)
        strategy = SurrogateCollision(model_dir=trained_models["contact"], periodic_box=box, detection="swept")
        if box is None:
            strategy.set_walls(*box_walls())
        strategy.collide(p, dt)
        v_back = np.empty((len(x), 3), np.float32)
        v_back[order] = p.v.numpy()
        t_back = np.empty(len(x), np.float32)
        t_back[order] = strategy.swept.t_last.numpy()
        results.append((v_back, t_back, strategy.counts()))
    (v_a, t_a, c_a), (v_b, t_b, c_b) = results
    assert c_a["collisions"] > 50 and c_a["rounds"] > 2
    if space == "walls":
        assert c_a["wall_events"] > 20
    same_counts = {k: c_a[k] for k in ("collisions", "surrogate_calls", "rounds", "wall_events", "detected_pairs")}
    assert {k: c_b[k] for k in same_counts} == same_counts
    assert np.array_equal(v_a, v_b) and np.array_equal(t_a, t_b)
    print(f"swept rounds ({space}) under permuted labels = unpermuted: {same_counts}")


# ------------------------------------------------------------------------------ deposition: deterministic atomics
def test_deposit_on_the_device_is_run_to_run_exact_and_equals_the_cpu(device):
    """kernels/deposit.py sets Warp's ``deterministic`` module option: on CUDA its float atomics then launch
    through Warp's scatter-sort-reduce (``launch_deterministic``, CUDA only), summing each cell's contributions in
    thread-index order; the CPU runs the threads in that order anyway. Run twice on the device: bit for bit; against
    the same deposit on the CPU: equal to float64 round-off of the per-parcel weights (the CUDA compiler may fuse
    multiply-adds; 1e-12 of the largest cell value asked, measured 0 on the CPU)."""
    if not str(device).startswith("cuda"):
        pytest.skip("a device check: on the CPU it would compare the CPU with itself (HEL_WARP_DEVICE=cuda on a GPU)")
    from tests.test_coupling import _deposit_random

    names = ("cell_solid_volume", "cell_momentum_source", "cell_drag_coeff", "cell_solid_momentum")
    runs = []
    for dev in (device, device, "cpu"):
        with wp.ScopedDevice(dev):
            _, fields, _, _ = _deposit_random(seed=11, n=3000)
            runs.append({name: getattr(fields, name).numpy().astype(np.float64) for name in names})
    first, again, cpu = runs
    worst = 0.0
    for name in names:
        assert np.array_equal(first[name], again[name]), name
        scale = np.abs(cpu[name]).max()
        worst = max(worst, np.abs(first[name] - cpu[name]).max() / scale)
        assert scale > 0 and np.abs(first[name] - cpu[name]).max() <= 1e-12 * scale, name
    print(f"deposit on {device}: twice bit for bit; vs the CPU max |diff| / max |cell| = {worst:.1e}")

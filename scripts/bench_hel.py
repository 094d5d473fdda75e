"""Cost of the HEL step's parts: gas step per cell, parcel deposit + interpolate + push per parcel.

- Gas: ``GasSolver.step`` on closed cubic boxes of ~1e4 and ~1e5 cells (``--cells``), with a fresh
  random solid fraction (0-0.3) and particle momentum source before every repeat so that every
  pressure / viscous solve does real CG work; median wall clock of ``--repeats`` steps, per cell,
  and the CG iterations of the pressure solve (CG iterations grow with the grid, so the cost per cell
  is not expected to stay flat).
- Gas on the rig's own grid (``cases/colliding_streams.py``, default size: 160 x 64 x 10 cells, 34,768 of
  them fluid): ``GasSolver.step`` on the rig's flow after its gas warm-up (``--rig-repeats`` steps, the
  eps_s left by the warm-up); median per box cell and per fluid cell (the target: <= 1 us per
  fluid cell), wall-clock and process CPU time (Warp's CPU kernels run on one thread). ``--no-rig`` skips it.
- Parcels: the parcel phase as ``HelSolver.step`` runs it, ``HelSolver.deposit`` + ``interpolate`` +
  ``push`` (with ``HelConfig.coupling = "implicit"``, the default, the push is the implicit drag
  exchange ``coupling.exchange_push``: 3 Picard passes of parcel and cell kernels), for 1e4, 1e5, 1e6
  parcels (``--parcels``) at random positions in a closed box, gas velocity random, no collisions.
  The phase does per-call work on every cell (zeroing, ``finish_cells``, the exchange's cell passes)
  as well as per-parcel work, so it is timed on two kinds of grid:

  * ``ppc``: the grid grows with the parcel count at a constant ``--parcels-per-cell`` (default 8;
    near-cubic shapes chosen so that the actual parcels per cell stays within a few % of it) -- the
    way a real case scales, and the figure for the scaling target (flat within 1.5x per parcel);
  * ``fixed``: one ``--fixed-side``^3 grid (default 32^3) for every count, as the benchmark used to
    run: at small counts the fixed cell work dominates the per-parcel cost;
  * ``ppc rand`` (``--random-order``, off by default): the ``ppc`` grids with the parcel slots left in
    random order (``HelConfig(sort_every=0)``) -- a diagnostic of what unsorted memory costs in cache
    misses of the atomic deposits and the gathers on the larger grids.

  The ``ppc`` and ``fixed`` cases first put the slots in cell order with ``HelSolver.sort_parcels``, as the
  step does every ``HelConfig.sort_every`` (20) steps.
  Parcel state (x, v) is reset before every repeat (outside the timing) so that every repeat does the
  same work; no gas step runs between repeats. The repeats are interleaved over all sizes and grids
  (one round of each, ``--repeats`` times, after one warm-up round), so that load changes on a shared
  machine hit every size alike. Reported: medians (of ``--repeats``, default 7) per sub-step and of the
  sum, per parcel, the ratio of the per-parcel cost to the smallest count, and its max/min over the
  counts; for ``fixed`` also the marginal cost of the added parcels (free of the fixed per-call cell
  work). The SDF wall reflection (``HelSolver.reflect_at_walls``) is timed beside it, not in the sum.

Usage::

    python scripts/bench_hel.py                     # CPU, full size (under a minute on 2 loaded cores)
    python scripts/bench_hel.py --quick             # smoke run (seconds)
    python scripts/bench_hel.py --device cuda       # GPU (timings synchronise the device)
    python scripts/bench_hel.py --json              # one JSON object
    python scripts/bench_hel.py --profile-gas       # CPU time per kernel of the rig's gas step
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

H = 1e-3  # cell size, m
SUB_STEPS = ("deposit", "interpolate", "push")
QUICK = {"cells": [10, 16], "parcels": [2_000, 20_000], "repeats": 2, "fixed_side": 16}


def _sync(device):
    import warp as wp

    if device.is_cuda:
        wp.synchronize_device(device)


def bench_gas(n_side: int, repeats: int, device, seed: int = 0) -> dict:
    from hel_warp.gas.solver import GasConfig, GasField, GasSolver
    from hel_warp.gas.grid import Box, Geometry, Grid

    h = H
    grid = Grid(spacing=h, shape=(n_side,) * 3)
    domain = Geometry(shapes=(Box(lo=(0, 0, 0), hi=(n_side * h,) * 3),)).build(grid, device=device)
    solver = GasSolver(domain, GasConfig(), device=device)
    gas = GasField(domain, device=device)
    rng = np.random.default_rng(seed)
    cells = n_side**3
    times, iterations = [], []
    for r in range(repeats + 1):  # the first call compiles / warms up
        gas.cell_eps_s.assign(rng.uniform(0.0, 0.3, grid.shape).astype(np.float32))
        gas.cell_momentum_source.assign(rng.normal(0.0, 1e-9, grid.shape + (3,)).astype(np.float32))
        _sync(solver.device)
        start = time.perf_counter()
        solver.step(gas, 1e-3)
        _sync(solver.device)
        if r:
            times.append(time.perf_counter() - start)
            iterations.append(solver.last_iterations["pressure"])
    median = statistics.median(times)
    return {"cells": cells, "median_s": median, "per_cell_us": 1e6 * median / cells,
            "pressure_cg_iterations": int(statistics.median(iterations))}


def gas_snapshot(gas):
    """Every array of ``gas`` (a ``GasField``; the x/y/z arrays of its face fields by ``name.x`` ...) and a function
    that copies the values they hold now back into them: the same state before every timed call of an A/B."""
    import warp as wp

    arrays = {}
    for name, value in vars(gas).items():
        if isinstance(value, wp.array):
            arrays[name] = value
        elif hasattr(value, "x") and isinstance(getattr(value, "x"), wp.array):
            for c in "xyz":
                arrays[f"{name}.{c}"] = getattr(value, c)
    saved = {k: wp.clone(a) for k, a in arrays.items()}

    def restore():
        for k, a in arrays.items():
            wp.copy(a, saved[k])

    return arrays, restore


def warm_rig(device):
    """The colliding-streams rig (315 um, 1e-3 s, no collisions) after its gas warm-up: the grid and flow whose gas
    step the rig timings and the gas profile measure."""
    from hel_warp.cli.commands._common import load_case_module

    case = load_case_module("colliding_streams")
    ns = argparse.Namespace(diameter=315e-6, dt=1e-3, collisions="none", end_time=1e-3, particles_per_parcel=1.0,
                            max_particles=None, monodisperse=False, model=None, cells=None, gas_warmup=0.01,
                            output_interval=1e-3, seed=0, device=str(device), detection=None,
                            no_particle_contacts=False)
    rig = case.CollidingStreams(case.make_config(ns))
    rig.warm_up()
    return rig


def bench_rig_gas(repeats: int, device) -> dict:
    """The gas step on the colliding-streams rig's grid and flow (module docstring)."""
    rig = warm_rig(device)
    solver, gas = rig.solver.gas_solver, rig.solver.gas
    dt = rig.solver.config.dt
    fluid = int(solver.domain.cell_fluid.numpy().sum())
    cells = int(np.prod(solver.domain.grid.shape))
    walls, cpus, iterations = [], [], []
    for r in range(repeats + 1):  # the first call warms up
        _sync(solver.device)
        start, cpu = time.perf_counter(), time.process_time()
        solver.step(gas, dt)
        _sync(solver.device)
        if r:
            walls.append(time.perf_counter() - start)
            cpus.append(time.process_time() - cpu)
            iterations.append([solver.last_iterations["pressure"], *solver.last_iterations["viscous"]])
    wall, cpu = statistics.median(walls), statistics.median(cpus)
    return {"grid": list(solver.domain.grid.shape), "cells": cells, "fluid_cells": fluid, "median_s": wall,
            "median_cpu_s": cpu, "per_fluid_cell_us": 1e6 * wall / fluid, "per_fluid_cell_cpu_us": 1e6 * cpu / fluid,
            "per_cell_us": 1e6 * wall / cells, "cg_iterations": [int(statistics.median(c)) for c in zip(*iterations)]}


def profile_rig_gas(rig_steps: int, device, top: int = 20) -> list[dict]:
    """CPU time per kernel of the rig's gas step: ``wp.launch`` wrapped by a timer for ``rig_steps`` steps
    (CPU launches are synchronous, so a launch's CPU time is its kernel plus the host call; recorded launches
    are timed at their replay, ``Launch.launch``; a captured PCG iteration, ``GasSolver._pcg_iteration_graph``, at
    its ``wp.capture_launch``, as one row per system: its kernels run inside the graph). Sorted, largest
    first: where the gas step's time goes."""
    import collections

    import warp as wp

    rig = warm_rig(device)
    solver, gas, dt = rig.solver.gas_solver, rig.solver.gas, rig.solver.config.dt
    stats = collections.defaultdict(lambda: [0, 0.0])
    launch = wp.launch

    def timed_launch(kernel, *a, **k):
        start = time.process_time()
        result = launch(kernel, *a, **k)
        entry = stats[getattr(kernel, "key", str(kernel))]
        entry[0] += 1
        entry[1] += time.process_time() - start
        return result

    from warp._src.context import Launch  # recorded launches (wp.launch(record_cmd=True)) replay through this

    replay = Launch.launch

    def timed_replay(self, *a, **k):
        start = time.process_time()
        result = replay(self, *a, **k)
        entry = stats[self.kernel.key]
        entry[0] += 1
        entry[1] += time.process_time() - start
        return result

    capture_launch = wp.capture_launch

    def timed_capture(graph, *a, **k):
        start = time.process_time()
        result = capture_launch(graph, *a, **k)
        systems = [key[0] for key, g in solver._pcg_graphs.items() if g is graph]
        entry = stats[f"(PCG iteration graph: {systems[0] if systems else '?'})"]
        entry[0] += 1
        entry[1] += time.process_time() - start
        return result

    wp.launch, Launch.launch, wp.capture_launch = timed_launch, timed_replay, timed_capture
    try:
        start = time.process_time()
        for _ in range(rig_steps):
            solver.step(gas, dt)
        total = (time.process_time() - start) / rig_steps
    finally:
        wp.launch, Launch.launch, wp.capture_launch = launch, replay, capture_launch
    rows = [{"kernel": key, "launches_per_step": c / rig_steps, "cpu_ms_per_step": 1e3 * t / rig_steps}
            for key, (c, t) in stats.items()]
    rows.sort(key=lambda r: -r["cpu_ms_per_step"])
    rows.insert(0, {"kernel": "(whole gas step)", "launches_per_step": sum(c for c, _ in stats.values()) / rig_steps,
                    "cpu_ms_per_step": 1e3 * total})
    return rows[: top + 1]


def grid_shape_for(cells: float, max_aspect: float = 2.0) -> tuple[int, int, int]:
    """Near-cubic (nx, ny, nz), longest side at most ``max_aspect`` times the shortest, whose cell count is
    closest to ``cells`` (ties: the more cubic one)."""
    cells = max(float(cells), 1.0)
    side = cells ** (1.0 / 3.0)
    best = None
    lo, hi = max(1, int(side / max_aspect)), int(side * max_aspect) + 1
    for a in range(lo, max(lo, int(side)) + 1):
        for b in range(a, hi + 1):
            for c in {max(b, math.floor(cells / (a * b))), max(b, math.ceil(cells / (a * b)))}:
                if c > max_aspect * a:
                    continue
                key = (abs(a * b * c - cells) / cells, c / a)
                if best is None or key < best[0]:
                    best = (key, (a, b, c))
    if best is None:  # tiny counts: a single cube
        n = max(1, round(side))
        return (n, n, n)
    return best[1]


def make_solver(shape, n: int, device, *, coupling: str, seed: int = 0):
    """A HelSolver on a closed box of ``shape`` cells of H with ``n`` parcels (radius 0.1 mm, 1000 kg/m^3) at
    uniformly random positions; gas velocity random (0.5 m/s rms), grad p' zero. Returns (solver, x, v) with
    the host copies of the initial parcel state."""
    from hel_warp.gas.solver import GasConfig, GasField, GasSolver
    from hel_warp.gas.grid import Box, Geometry, Grid
    from hel_warp.hel import HelConfig, HelSolver
    from hel_warp.parcels.coupling import PushConfig
    from hel_warp.parcels.pool import ParcelPool

    shape = tuple(int(s) for s in shape)
    grid = Grid(spacing=H, shape=shape)
    hi = tuple(s * H for s in shape)
    domain = Geometry(shapes=(Box(lo=(0.0, 0.0, 0.0), hi=hi),)).build(grid, device=device)
    push = PushConfig()
    gas_solver = GasSolver(domain, GasConfig(density=push.fluid_density, viscosity=push.fluid_viscosity),
                           device=device)
    gas = GasField(domain, device=device)
    rng = np.random.default_rng(seed)
    gas.cell_velocity.assign(rng.normal(0.0, 0.5, shape + (3,)).astype(np.float32))
    x = rng.uniform([0.5 * H] * 3, [s - 0.5 * H for s in hi], size=(n, 3)).astype(np.float32)
    v = rng.normal(0.0, 0.1, size=(n, 3)).astype(np.float32)
    pool = ParcelPool.empty(n, device=device)
    p = pool.particles
    p.x.assign(x)
    p.v.assign(v)
    p.radius.assign(np.full(n, 1e-4, np.float32))
    p.density.assign(np.full(n, 1000.0, np.float32))
    p.alive.assign(np.ones(n, np.int32))
    p.particle_id.assign(np.arange(n, dtype=np.int32))
    pool.used = n
    solver = HelSolver(pool=pool, gas_solver=gas_solver, gas=gas, config=HelConfig(push=push, coupling=coupling))
    solver.time_sub_steps = False
    return solver, x, v


def parcel_case(n: int, shape, device, *, coupling: str = "implicit", sort: bool = True, seed: int = 0) -> dict:
    """One timed configuration: a solver with ``n`` parcels on a ``shape`` grid (``make_solver``); with ``sort``
    the slots are first put in cell order by ``HelSolver.sort_parcels``, as the step does every
    ``HelConfig.sort_every`` steps (parcels move less than a cell per step, so the order holds in between);
    without, they stay in random order (diagnostic: the cost of unsorted memory)."""
    solver, x0, v0 = make_solver(shape, n, device, coupling=coupling, seed=seed)
    if sort:
        solver.sort_parcels()
        x0, v0 = solver.pool.particles.x.numpy().copy(), solver.pool.particles.v.numpy().copy()
    calls = {"deposit": solver.deposit, "interpolate": solver.interpolate, "push": solver.push,
             "walls": solver.reflect_at_walls}
    return {"n": n, "shape": tuple(int(s) for s in shape), "solver": solver, "x0": x0, "v0": v0, "calls": calls,
            "times": {name: [] for name in calls}, "totals": []}


def time_round(case: dict, record: bool) -> None:
    """One round of HelSolver.deposit, .interpolate, .push (and .reflect_at_walls, beside, not in the sum)
    from the same initial parcel state; appended to the case's times when ``record``."""
    solver = case["solver"]
    p = solver.pool.particles
    p.x.assign(case["x0"])  # same work every round
    p.v.assign(case["v0"])
    solver.collide()  # 'none': a_coll = 0, as in the step (untimed)
    total = 0.0
    for name, call in case["calls"].items():
        _sync(p.device)
        start = time.perf_counter()
        call()
        _sync(p.device)
        elapsed = time.perf_counter() - start
        if name in SUB_STEPS:
            total += elapsed
        if record:
            case["times"][name].append(elapsed)
    if record:
        case["totals"].append(total)


def case_result(case: dict) -> dict:
    n, shape = case["n"], case["shape"]
    cells = int(np.prod(shape))
    out = {"parcels": n, "grid": list(shape), "cells": cells, "parcels_per_cell": n / cells}
    for name, values in case["times"].items():
        out[f"{name}_ns_per_parcel"] = 1e9 * statistics.median(values) / n
    out["median_s"] = statistics.median(case["totals"])
    out["total_ns_per_parcel"] = 1e9 * out["median_s"] / n
    out["total_min_ns_per_parcel"] = 1e9 * min(case["totals"]) / n
    return out


def _summarise(rows: list[dict]) -> dict:
    base = rows[0]["total_ns_per_parcel"]
    for row in rows:
        row["ratio_per_parcel"] = row["total_ns_per_parcel"] / base
    per_parcel = [row["total_ns_per_parcel"] for row in rows]
    ratio = max(per_parcel) / min(per_parcel)
    return {"rows": rows, "max_over_min": ratio, "flat_within_1_5x": bool(ratio <= 1.5)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu", help="Warp device: cpu or cuda (default cpu)")
    parser.add_argument("--cells", type=int, nargs="+", default=None,
                        help="cube sides of the gas grids (default 22 47: 1.06e4 and 1.04e5 cells)")
    parser.add_argument("--parcels", type=int, nargs="+", default=None,
                        help="parcel counts (default 10000 100000 1000000)")
    parser.add_argument("--parcels-per-cell", type=float, default=8.0,
                        help="parcels per cell of the growing grid (default 8)")
    parser.add_argument("--fixed-side", type=int, default=None,
                        help="cube side of the fixed grid the parcels are also timed on (default 32; 0: skip)")
    parser.add_argument("--coupling", choices=("implicit", "explicit"), default="implicit",
                        help="HelConfig.coupling of the timed push (default implicit, the solver's default)")
    parser.add_argument("--repeats", type=int, default=None, help="timed repeats per size (median reported; "
                        "default 7)")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: gas 10^3 and 16^3 cells, 2e3 and 2e4 parcels, fixed 16^3, 2 repeats "
                             "(options given explicitly win)")
    parser.add_argument("--random-order", action="store_true",
                        help="also time the parcels-per-cell grids with the parcel slots in random order, as "
                             "with HelConfig(sort_every=0) (diagnostic: the cost of unsorted memory)")
    parser.add_argument("--no-rig", action="store_true", help="skip the gas step on the rig's grid")
    parser.add_argument("--profile-gas", action="store_true",
                        help="only print the CPU time per kernel of the rig's gas step (3 steps) and exit")
    parser.add_argument("--rig-repeats", type=int, default=5, help="timed gas steps on the rig's grid (default 5)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    defaults = QUICK if args.quick else {"cells": [22, 47], "parcels": [10_000, 100_000, 1_000_000],
                                         "repeats": 7, "fixed_side": 32}
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if args.parcels_per_cell <= 0 or args.repeats < 1 or min(args.parcels) < 1:
        parser.error("--parcels-per-cell, --repeats and --parcels must be positive")

    from hel_warp._warp import init_warp

    wall_start = time.perf_counter()
    device = init_warp(args.device)
    if args.profile_gas:
        rows = profile_rig_gas(3, device)
        if args.json:
            print(json.dumps(rows))
            return 0
        print(f"{'kernel':>34} {'launches/step':>14} {'CPU ms/step':>12}")
        for r in rows:
            print(f"{r['kernel']:>34} {r['launches_per_step']:>14.0f} {r['cpu_ms_per_step']:>12.2f}")
        return 0
    gas = [bench_gas(n, args.repeats, device) for n in args.cells]
    base_cell = gas[0]["per_cell_us"]
    for g in gas:
        g["ratio_per_cell"] = g["per_cell_us"] / base_cell
    rig_gas = None if args.no_rig else bench_rig_gas(args.rig_repeats, device)
    ppc_label = f"ppc {args.parcels_per_cell:g}"
    specs = {"parcels": (ppc_label, lambda n: grid_shape_for(n / args.parcels_per_cell), True)}
    if args.fixed_side > 0:
        specs["parcels_fixed_grid"] = (f"fixed {args.fixed_side}^3", lambda n: (args.fixed_side,) * 3, True)
    if args.random_order:
        specs["parcels_random_order"] = (f"{ppc_label} rand", specs["parcels"][1], False)
    cases = {key: [parcel_case(n, shape_of(n), device, coupling=args.coupling, sort=sort)
                   for n in args.parcels] for key, (_, shape_of, sort) in specs.items()}
    every = [case for group in cases.values() for case in group]
    for case in every:  # warm-up round (kernel load, first touch of the memory), not counted
        time_round(case, record=False)
    for _ in range(args.repeats):  # interleaved: load changes on a shared machine hit every size alike
        for case in every:
            time_round(case, record=True)
    result = {"device": str(device), "repeats": args.repeats, "coupling": args.coupling, "gas": gas, "rig_gas": rig_gas,
              "parcels_per_cell_target": args.parcels_per_cell}
    variants = {}
    for key, (label, _, _) in specs.items():
        variant = _summarise([case_result(case) for case in cases[key]])
        variant["label"] = label
        if key == "parcels_fixed_grid":
            rows = variant["rows"]
            for prev, row in zip(rows, rows[1:]):  # cost of the added parcels, free of the fixed per-call cell work
                row["marginal_ns_per_parcel"] = (1e9 * (row["median_s"] - prev["median_s"])
                                                 / (row["parcels"] - prev["parcels"]))
        result[key] = variants[label] = variant
    del cases, every
    result["wall_s"] = time.perf_counter() - wall_start
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"device {device}, medians of {args.repeats} repeats")
    print("gas step (GasSolver.step)")
    print(f"{'cells':>10} {'step (s)':>10} {'us/cell':>9} {'ratio':>6} {'CG its':>7}")
    for g in gas:
        print(f"{g['cells']:>10} {g['median_s']:>10.4f} {g['per_cell_us']:>9.3f} {g['ratio_per_cell']:>6.2f} "
              f"{g['pressure_cg_iterations']:>7}")
    if rig_gas is not None:
        r = rig_gas
        print(f"gas step on the rig's grid {'x'.join(map(str, r['grid']))} ({r['cells']} cells, {r['fluid_cells']} fluid): "
              f"{r['median_s']:.4f} s wall, {r['median_cpu_s']:.4f} s CPU; {r['per_fluid_cell_us']:.2f} us wall / "
              f"{r['per_fluid_cell_cpu_us']:.2f} us CPU per fluid cell (target <= 1); CG its p/u/v/w {r['cg_iterations']}")
    print(f"parcel phase (HelSolver.deposit + interpolate + push, coupling {args.coupling}), ns per parcel")
    print(f"{'grid':>12} {'parcels':>9} {'shape':>10} {'ppc':>6} {'sum (s)':>9} {'deposit':>8} {'interp':>8} "
          f"{'push':>8} {'ns/parcel':>10} {'ratio':>6} {'marginal':>9} {'(walls)':>8}")
    for label, variant in variants.items():
        for p in variant["rows"]:
            marginal = p.get("marginal_ns_per_parcel")
            print(f"{label:>12} {p['parcels']:>9} {'x'.join(map(str, p['grid'])):>10} {p['parcels_per_cell']:>6.2f} "
                  f"{p['median_s']:>9.4f} {p['deposit_ns_per_parcel']:>8.1f} {p['interpolate_ns_per_parcel']:>8.1f} "
                  f"{p['push_ns_per_parcel']:>8.1f} {p['total_ns_per_parcel']:>10.1f} {p['ratio_per_parcel']:>6.2f} "
                  f"{'-' if marginal is None else format(marginal, '.1f'):>9} {p['walls_ns_per_parcel']:>8.1f}")
    for label, variant in variants.items():
        print(f"{label}: per-parcel cost max/min over {min(args.parcels):.0e}..{max(args.parcels):.0e} parcels "
              f"{variant['max_over_min']:.2f}x, flat within 1.5x: {variant['flat_within_1_5x']}")
    print(f"wall time {result['wall_s']:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Cost of the HEL step's parts: gas step per cell, parcel deposit + interpolate + push per parcel.

- Gas: ``GasSolver.step`` on closed cubic boxes of ~1e4 and ~1e5 cells (``--cells``), with a fresh
  random solid fraction (0-0.3) and particle momentum source before every repeat so that every
  pressure / viscous solve does real CG work; median wall clock of ``--repeats`` steps, per cell,
  and the CG iterations of the pressure solve (CG iterations grow with the grid, so the cost per cell
  is not expected to stay flat).
- Parcels: ``deposit_parcels``, ``interpolate_gas``, ``push_parcels`` on a fixed 32^3 grid with
  1e4, 1e5, 1e6 parcels (``--parcels``) at random positions; median per call, per parcel, the
  ratio of the per-parcel cost to the smallest count (target: flat within 1.5x) and the marginal
  cost of the added parcels (free of the fixed per-call grid work: zeroing and finishing the cells).
  The SDF wall reflection (``kernels/reflect.py``) is timed beside it, not in the sum.

Usage::

    python scripts/bench_hel.py                     # CPU
    python scripts/bench_hel.py --device cuda       # GPU (timings synchronise the device)
    python scripts/bench_hel.py --json              # one JSON object
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np


def _sync(device):
    import warp as wp

    if device.is_cuda:
        wp.synchronize_device(device)


def bench_gas(n_side: int, repeats: int, device, seed: int = 0) -> dict:
    import warp as wp

    from hel_warp.gas import GasConfig, GasField, GasSolver
    from hel_warp.grid import Box, Geometry, Grid

    h = 1e-3
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


def bench_parcels(n: int, repeats: int, device, n_side: int = 32, seed: int = 0) -> dict:
    import warp as wp

    from hel_warp.coupling import CouplingFields, GridSpec, PushConfig, deposit_parcels, interpolate_gas, push_parcels
    from hel_warp.particles import Particles

    h = 1e-3
    grid = GridSpec(origin=(0.0, 0.0, 0.0), spacing=h, shape=(n_side,) * 3)
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.5 * h, (n_side - 0.5) * h, size=(n, 3))
    parts = Particles.from_numpy(x, 1e-4, v=rng.normal(0.0, 0.1, size=(n, 3)), check_overlap=False, device=device)
    fields = CouplingFields.allocate(grid, n, device=parts.device)
    cell_velocity = wp.array(rng.normal(0, 0.5, (n_side,) * 3 + (3,)).astype(np.float32), dtype=wp.vec3,
                             device=parts.device)
    cell_grad_p = wp.zeros((n_side,) * 3, dtype=wp.vec3, device=parts.device)
    params = PushConfig().params(1e-5)  # short step: parcels stay in the box over the repeats
    from hel_warp.grid import Box, Geometry
    from kernels.reflect import make_wall_params, reflect_at_walls

    shapes = Geometry(shapes=(Box(lo=(0.0, 0.0, 0.0), hi=(n_side * h,) * 3),)).shapes_struct(parts.device)
    wall_params, hits = make_wall_params(), wp.zeros(1, dtype=wp.int32, device=parts.device)
    subs = {"deposit": lambda: deposit_parcels(grid, parts, fields),
            "interpolate": lambda: interpolate_gas(grid, parts, cell_velocity, cell_grad_p, fields),
            "push": lambda: push_parcels(parts, fields, params),
            "walls": lambda: reflect_at_walls(shapes, wall_params, parts.alive, parts.x, parts.v, hits)}
    times = {name: [] for name in subs}
    totals = []
    for r in range(repeats + 1):
        total = 0.0
        for name, call in subs.items():
            _sync(parts.device)
            start = time.perf_counter()
            call()
            _sync(parts.device)
            elapsed = time.perf_counter() - start
            if name != "walls":  # the total is deposit + interpolate + push
                total += elapsed
            if r:
                times[name].append(elapsed)
        if r:
            totals.append(total)
    out = {"parcels": n}
    for name, values in times.items():
        out[f"{name}_ns_per_parcel"] = 1e9 * statistics.median(values) / n
    out["median_s"] = statistics.median(totals)
    out["total_ns_per_parcel"] = 1e9 * out["median_s"] / n
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu", help="Warp device: cpu or cuda (default cpu)")
    parser.add_argument("--cells", type=int, nargs="+", default=[22, 47],
                        help="cube sides of the gas grids (default 22 47: 1.06e4 and 1.04e5 cells)")
    parser.add_argument("--parcels", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats per size (median reported)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)

    from hel_warp._warp import init_warp

    device = init_warp(args.device)
    gas = [bench_gas(n, args.repeats, device) for n in args.cells]
    parcels = [bench_parcels(n, args.repeats, device) for n in args.parcels]
    base_cell, base_parcel = gas[0]["per_cell_us"], parcels[0]["total_ns_per_parcel"]
    for g in gas:
        g["ratio_per_cell"] = g["per_cell_us"] / base_cell
    for p in parcels:
        p["ratio_per_parcel"] = p["total_ns_per_parcel"] / base_parcel
    for prev, p in zip(parcels, parcels[1:]):  # cost of the added parcels, free of the fixed per-call grid work
        p["marginal_ns_per_parcel"] = 1e9 * (p["median_s"] - prev["median_s"]) / (p["parcels"] - prev["parcels"])
    result = {"device": str(device), "repeats": args.repeats, "gas": gas, "parcels": parcels,
              "parcel_cost_flat_within_1_5x": bool(max(p["ratio_per_parcel"] for p in parcels) <= 1.5
                                                   and min(p["ratio_per_parcel"] for p in parcels) >= 1 / 1.5)}
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"device {device}, medians of {args.repeats} repeats")
    print(f"{'gas cells':>10} {'step (s)':>10} {'us/cell':>9} {'ratio':>6} {'CG its':>7}")
    for g in gas:
        print(f"{g['cells']:>10} {g['median_s']:>10.4f} {g['per_cell_us']:>9.3f} {g['ratio_per_cell']:>6.2f} "
              f"{g['pressure_cg_iterations']:>7}")
    print(f"{'parcels':>10} {'sum (s)':>10} {'deposit':>9} {'interp':>9} {'push':>9} {'ns/parcel':>10} "
          f"{'ratio':>6} {'marginal':>9} {'(walls)':>8}")
    for p in parcels:
        print(f"{p['parcels']:>10} {p['median_s']:>10.4f} {p['deposit_ns_per_parcel']:>9.1f} "
              f"{p['interpolate_ns_per_parcel']:>9.1f} {p['push_ns_per_parcel']:>9.1f} "
              f"{p['total_ns_per_parcel']:>10.1f} {p['ratio_per_parcel']:>6.2f} "
              f"{p.get('marginal_ns_per_parcel', float('nan')):>9.1f} {p['walls_ns_per_parcel']:>8.1f}")
    print(f"parcel cost per parcel flat within 1.5x: {result['parcel_cost_flat_within_1_5x']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Benchmark: particle-steps per second of our N-body DEM vs Warp's own ``example_dem`` (same run, same N).

Ours: ``hel_warp.dem.DEMSolver`` on a dense bed — monodisperse 6 mm polyethylene spheres
(``Material()`` with e = 0.5, mu = 0.3) on a simple cubic lattice of spacing 0.9998 d in a closed
box under gravity, so every sphere presses on its six lattice neighbours from the first step (the
overlap, 1.2 um, is that of the static load at the bottom of a 1e5-sphere bed); dt from eq. (12).
Timed: ``simulate(k)`` (neighbour-list checks and rebuilds, Hertz-Mindlin contacts with history,
walls, velocity Verlet), median of repeats.

Warp: ``warp/examples/core/example_dem.py``, its ``Example`` class imported from the installed
package, its particle lattice (spacing ~2r + jitter) cut to N particles. Timed: its
``simulate()`` (apply_forces + integrate per substep) with the hash-grid build amortised over 64
substeps as in the example's ``step()``.

Both are timed in wall-clock and in process CPU time (Warp runs CPU kernels on one thread, so
CPU time is the one-core cost even on a shared machine); the ratios use CPU time.
Printed: medians, ours/Warp, cost per particle-step (ns) and its flatness (max/min over sizes),
and the comparison with LAMMPS ``gran/hooke/history`` at 1.16e7 particle-steps/s/core (LAMMPS
benchmark "chute", see https://docs.lammps.org/Speed_bench.html).

Measured (2026-11-23, shared 2-core CPU machine, load ~6.5; CPU-time rates, particle-steps/s):
N = 1e4 / 1e5 / 1e6: ours 3.72e6 / 3.03e6 / 3.22e6 (269 / 330 / 311 ns per particle-step, flatness
1.23), Warp example 9.5e5 / 8.9e5 / 8.1e5, ours/Warp 3.9x / 3.4x / 4.0x; LAMMPS ratio 0.32x. The
dense bed barely moves, so one list build served all timed steps (the settling column rebuilds
every ~200 steps; a build costs ~0.7-0.9 us per particle). Spatial sort, 3e5 spheres in random
memory order: 1250 ns per particle-step without, 385 ns with ``--sort-every 1``.

Usage::

    python scripts/bench_dem.py                         # 1e4, 1e5, 1e6 on the CPU (a few minutes)
    python scripts/bench_dem.py --sizes 10000 100000    # fewer sizes
    python scripts/bench_dem.py --device cuda           # on a GPU
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import statistics
import sys
import time

import numpy as np


LAMMPS_CHUTE = 1.16e7
"""LAMMPS gran/hooke/history particle-steps per second per CPU core (chute benchmark)."""


def build_ours(n: int, device: str, sort_every: int, capacity: int, shuffle: bool = False):
    from hel_warp.dem import DEMConfig, DEMSolver
    from hel_warp.material import Material
    from hel_warp.particles import Particles, lattice_positions

    d = 6e-3
    per_side = max(2, int(round(n ** (1.0 / 3.0))))
    layers = int(math.ceil(n / per_side**2))
    lo = (0.0, 0.0, 0.0)
    spacing = (1.0 - 2e-4) * d  # every lattice neighbour touches (overlap 1.2 um ~ static load of the bed)
    hi = (per_side * d, per_side * d, (layers + 2) * d)
    x = lattice_positions(n, spacing, lo, hi) + 0.5 * (d - spacing)  # first layer just touches the walls
    if shuffle:  # memory order unrelated to space: what spatial sorting is for
        x = x[np.random.default_rng(0).permutation(n)]
    material = Material(restitution=0.5, friction=0.3)
    particles = Particles.from_numpy(x, 0.5 * d, density=material.density, check_overlap=False, device=device)
    config = DEMConfig(material=material, box_lo=lo, box_hi=hi, sort_every=sort_every, contact_capacity=capacity)
    return DEMSolver(config, particles)


def time_ours(n: int, device: str, repeats: int, budget_s: float, sort_every: int, capacity: int,
              shuffle: bool = False) -> dict:
    import warp as wp

    solver = build_ours(n, device, sort_every, capacity, shuffle)
    solver.simulate(5)  # compile + first rebuilds
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    solver.simulate(5)
    wp.synchronize_device(device)
    per_step = (time.perf_counter() - t0) / 5
    k = max(20, int(budget_s / repeats / per_step))
    wall, cpu = [], []
    for _ in range(repeats):
        wp.synchronize_device(device)
        t0, c0 = time.perf_counter(), time.process_time()
        solver.simulate(k)
        wp.synchronize_device(device)
        wall.append(n * k / (time.perf_counter() - t0))
        cpu.append(n * k / (time.process_time() - c0))
    pairs = len(solver.touching_pairs()[0])
    return {"rate": statistics.median(cpu), "rate_wall": statistics.median(wall), "rates_cpu": cpu, "rates_wall": wall,
            "steps_per_repeat": k, "rebuilds": solver.rebuilds, "steps": solver.steps_done,
            "contacts_per_particle": 2.0 * pairs / n, "dt": solver.dt}


def time_warp_example(n: int, device: str, repeats: int, budget_s: float) -> dict:
    import warp as wp
    from warp.examples.core.example_dem import Example

    class SizedExample(Example):
        """Warp's example with its lattice (aspect 1:2:1) cut to ``count`` particles."""

        count = n

        def particle_grid(self, dim_x, dim_y, dim_z, lower, radius, jitter):
            nx = max(2, int(round((self.count / 2.0) ** (1.0 / 3.0))))
            ny = int(math.ceil(self.count / (nx * nx)))
            return super().particle_grid(nx, ny, nx, lower, radius, jitter)[: self.count]

    with wp.ScopedDevice(device):
        example = SizedExample(stage_path=None)
        example.use_graph_capture = False
        frame_substeps = example.sim_substeps  # 64 substeps per grid build in the example
        example.grid.build(example.x, example.grid_cell_size)
        example.sim_substeps = 1
        example.simulate()  # warm-up
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        example.simulate()
        wp.synchronize_device(device)
        per_substep = time.perf_counter() - t0
        k = max(1, int(budget_s / repeats / per_substep))
        example.sim_substeps = k
        timings = {"build_wall": [], "build_cpu": [], "sub_wall": [], "sub_cpu": []}
        for _ in range(repeats):
            wp.synchronize_device(device)
            t0, c0 = time.perf_counter(), time.process_time()
            example.grid.build(example.x, example.grid_cell_size)
            wp.synchronize_device(device)
            t1, c1 = time.perf_counter(), time.process_time()
            example.simulate()
            wp.synchronize_device(device)
            timings["build_wall"].append(t1 - t0)
            timings["build_cpu"].append(c1 - c0)
            timings["sub_wall"].append((time.perf_counter() - t1) / k)
            timings["sub_cpu"].append((time.process_time() - c1) / k)
    med = {key: statistics.median(v) for key, v in timings.items()}
    return {"rate": n / (med["sub_cpu"] + med["build_cpu"] / frame_substeps),
            "rate_wall": n / (med["sub_wall"] + med["build_wall"] / frame_substeps),
            "substeps_per_repeat": k, **med}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000],
                        help="particle counts (default 1e4 1e5 1e6)")
    parser.add_argument("--device", default="cpu", help="Warp device (default cpu)")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats per size (default 5)")
    parser.add_argument("--budget", type=float, default=6.0, help="seconds of timed work per size and code (default 6)")
    parser.add_argument("--sort-every", type=int, default=None,
                        help="our spatial sort every k rebuilds (default: the solver default, 10 on the CPU)")
    parser.add_argument("--capacity", type=int, default=16, help="our contact-list capacity (default 16)")
    parser.add_argument("--shuffle", action="store_true",
                        help="our particles in random memory order (to measure --sort-every)")
    parser.add_argument("--skip-warp", action="store_true", help="time ours only")
    parser.add_argument("--json", help="also write the results to this JSON file")
    args = parser.parse_args(argv)

    from hel_warp._warp import init_warp

    init_warp(args.device)
    results = []
    print(f"device {args.device}; {args.repeats} repeats, ~{args.budget:.0f} s of timed work per size and code")
    print("rates in particle-steps/s from CPU time (wall-clock in brackets); ns per particle-step from CPU time")
    print(f"{'N':>9} {'ours':>22} {'warp example':>22} {'ours/warp':>9} {'ours ns':>8} {'warp ns':>8} "
          f"{'contacts/p':>10} {'rebuilds/steps':>15}")
    for n in args.sizes:
        ours = time_ours(n, args.device, args.repeats, args.budget, args.sort_every, args.capacity, args.shuffle)
        warp_ex = None
        if not args.skip_warp:
            with contextlib.redirect_stdout(io.StringIO()):  # the example's ScopedTimer prints
                warp_ex = time_warp_example(n, args.device, args.repeats, args.budget)
        row = {"n": n, "ours": ours, "warp_example": warp_ex}
        results.append(row)
        wr = warp_ex["rate"] if warp_ex else float("nan")
        wrw = warp_ex["rate_wall"] if warp_ex else float("nan")
        print(f"{n:>9} {ours['rate']:>10.4g} ({ours['rate_wall']:>9.4g}) {wr:>10.4g} ({wrw:>9.4g}) "
              f"{ours['rate'] / wr:>9.2f} {1e9 / ours['rate']:>8.1f} {1e9 / wr:>8.1f} "
              f"{ours['contacts_per_particle']:>10.2f} {ours['rebuilds']:>7}/{ours['steps']:<7}", flush=True)
    costs = [1e9 / r["ours"]["rate"] for r in results]
    flat = max(costs) / min(costs)
    print(f"ours: cost per particle-step {min(costs):.1f}..{max(costs):.1f} ns, flatness max/min = {flat:.2f} "
          f"over N = {args.sizes[0]:.0e}..{args.sizes[-1]:.0e} (target <= 1.5)")
    if not args.skip_warp:
        ratios = [r["ours"]["rate"] / r["warp_example"]["rate"] for r in results]
        print(f"ours / Warp example_dem: {', '.join(f'{x:.1f}x' for x in ratios)} (target >= 3x)")
    best = max(r["ours"]["rate"] for r in results)
    print(f"vs LAMMPS gran/hooke/history {LAMMPS_CHUTE:.3g} particle-steps/s/core: ours best {best:.3g} "
          f"= {best / LAMMPS_CHUTE:.2f}x (ours: one Warp CPU thread, Hertz-Mindlin with history, full contact list)")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())

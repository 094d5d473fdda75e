"""Benchmark: our N-body DEM against LIGGGHTS on one core, the same beds in the same run.

Cases (monodisperse 6 mm spheres, ``Material(restitution=0.5, friction=0.3)``, walls of the same
material on the six faces of the box, gravity, dt of eq. (12), skin 0.3 r; velocity Verlet):

- ``static``: a dense bed, simple cubic lattice of spacing 0.9998 d, so every sphere presses on its
  six lattice neighbours from the first step (the overlap, 1.2 um, is that of the static load at the
  bottom of a 1e5-sphere bed); the bed rings; one list build serves all steps.
- ``fall``: the spheres on a loose lattice (1.5 d) moving down at 1 m/s with a uniform random
  +-0.5 m/s on each component (seed 0): they collide and the list is rebuilt every ~100 steps.
- ``fall-dense``: the same at 1.1 d (collisional from the start).

LIGGGHTS (3.8, the Debian package ``liggghts``; ``apt-get install liggghts``) runs the same case in a
subprocess, one MPI rank: ``pair_style gran model hertz tangential history`` with ``limitForce on``
(the normal force clipped at zero, as ours) and ``tangential_damping off`` (our c_t = 0), walls
``fix wall/gran`` of the same model, ``fix nve/sphere``, ``neigh_modify delay 0`` (a check every step
against skin/2, as ours), the same float32 initial positions and velocities (``read_data``), the same
dt and skin. Its coefficient of restitution is set to the e' whose LIGGGHTS damping
``2 sqrt(5/6) |beta(e')| sqrt(S_n m*)`` equals our calibrated dashpot ``c(e) sqrt(m* k_H) delta^1/4``
(``sqrt(5) beta(e') = c(e)``), so both integrate the same equations. Checked: translational kinetic
energy and the centre-of-mass displacement after the same number of steps agree within 1 % (the
displacement: within 1 % or within one float32 unit in the last place at the box height, whichever is
larger: our positions are float32, and the static bed's centre moves by tens of nanometres; its slow
spheres move by less than the resolution per step, so they stay put where LIGGGHTS's doubles creep).

Timing: ours ``DEMSolver.simulate(steps)`` from the same start (kernels compiled beforehand on a small
bed, never timed); LIGGGHTS its ``run`` (process CPU time of the subprocess minus that of the same
input with ``run 0``, i.e. the set-up; its own "Loop time" is wall-clock and shown beside). Rates are
particle-steps per second of CPU time (Warp runs CPU kernels on one thread); the two codes alternate
repeat by repeat so machine load falls on both; medians and the ratio ours/LIGGGHTS. Without
``liggghts`` on the PATH the comparison is skipped with a note.

Flatness: ours on the static bed at ``--sizes`` (default 1e4, 1e5, 1e6), cost per particle-step and
max/min over the sizes. ``--warp-example`` also times Warp's ``example_dem`` at those sizes.

Usage::

    python scripts/bench_dem.py                                   # LIGGGHTS at 1e5, then 1e4..1e6 (~5 min)
    python scripts/bench_dem.py --cases static fall --sizes 10000 100000
    python scripts/bench_dem.py --peer-n 20000 --repeats 1 --sizes   # a quick look
    python scripts/bench_dem.py --device cuda --sizes 1000000         # on a GPU (LIGGGHTS stays on one core)
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

DIAMETER = 6e-3
"""Sphere diameter of every case, m."""
CASES = {"static": 1.0 - 2e-4, "fall": 1.5, "fall-dense": 1.1}
"""Lattice spacing of each case in diameters."""
DEFAULT_STEPS = {"static": 400, "fall": 4000, "fall-dense": 2000}
FALL_SPEED = 1.0
"""Initial downward speed of the falling beds, m/s."""
FALL_SPREAD = 0.5
"""Half-width of the uniform random velocity added per component in the falling beds, m/s."""


def bed(case: str, n: int, seed: int = 0, offset: float = 0.0) -> dict:
    """Positions (float32-exact), velocities, box and material of a case (module docstring); ``offset`` (m)
    moves the box and the spheres along every axis (a float32 resolution check: the spacing of float32
    numbers grows with the distance from the origin)."""
    from hel_warp.material import Material
    from hel_warp.parcels.particles import lattice_positions

    d = DIAMETER
    spacing = CASES[case] * d
    per_side = max(2, int(round(n ** (1.0 / 3.0))))
    layers = int(math.ceil(n / per_side**2))
    lo = (0.0, 0.0, 0.0)
    hi = (per_side * spacing, per_side * spacing, (layers + 2) * spacing)
    if case == "static":
        hi = (per_side * d, per_side * d, (layers + 2) * d)  # the side walls touch the lattice
    x = lattice_positions(n, spacing, lo, hi) + 0.5 * (d - spacing)  # first layer touches the walls
    v = np.zeros_like(x)
    if case != "static":
        rng = np.random.default_rng(seed)
        v = rng.uniform(-FALL_SPREAD, FALL_SPREAD, size=x.shape)
        v[:, 2] -= FALL_SPEED
    material = Material(restitution=0.5, friction=0.3)
    x = x + offset
    lo, hi = tuple(v + offset for v in lo), tuple(v + offset for v in hi)
    return {"x": x.astype(np.float32).astype(np.float64), "v": v.astype(np.float32).astype(np.float64),
            "radius": float(np.float32(0.5 * d)), "lo": lo, "hi": hi, "material": material, "case": case}


def build_ours(case: dict, device: str, sort_every=None, capacity: int = 16, shuffle: bool = False):
    from hel_warp.collisions.dem import DEMConfig, DEMSolver
    from hel_warp.parcels.particles import Particles

    x, v = case["x"], case["v"]
    if shuffle:  # memory order unrelated to space: what spatial sorting is for
        order = np.random.default_rng(0).permutation(len(x))
        x, v = x[order], v[order]
    material = case["material"]
    particles = Particles.from_numpy(x, case["radius"], v=v, density=material.density, check_overlap=False,
                                     device=device)
    config = DEMConfig(material=material, wall_material=material, box_lo=case["lo"], box_hi=case["hi"],
                       sort_every=sort_every, contact_capacity=capacity)
    return DEMSolver(config, particles)


def observables(x: np.ndarray, v: np.ndarray, mass: float) -> dict:
    """Translational kinetic energy (J) and centre of mass (m) of equal spheres."""
    return {"ke": 0.5 * mass * float(np.sum(v.astype(np.float64) ** 2)), "com": x.astype(np.float64).mean(axis=0)}


def sphere_mass(case: dict) -> float:
    return case["material"].density * 4.0 / 3.0 * math.pi * case["radius"] ** 3


def warm_up(device: str, capacity: int) -> None:
    """Compile every kernel the timed runs use, on a small bed of each kind (never timed)."""
    for name in ("static", "fall"):
        solver = build_ours(bed(name, 512), device, capacity=capacity)
        solver.simulate(3)


def run_ours(case: dict, steps: int, device: str, capacity: int, sort_every=None) -> dict:
    import warp as wp

    solver = build_ours(case, device, sort_every, capacity)
    wp.synchronize_device(device)
    t0, c0 = time.perf_counter(), time.process_time()
    solver.simulate(steps)
    wp.synchronize_device(device)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    n = solver.particles.count
    obs = observables(solver.particles.x.numpy(), solver.particles.v.numpy(), sphere_mass(case))
    return {"rate": n * steps / cpu, "rate_wall": n * steps / wall, "cpu_s": cpu, "wall_s": wall,
            "rebuilds": solver.rebuilds - 1, "contacts_per_particle": 2.0 * len(solver.touching_pairs()[0]) / n,
            **obs}


# ------------------------------------------------------------------------------------------ LIGGGHTS

def liggghts_restitution(restitution: float) -> float:
    """e' whose LIGGGHTS Hertz damping equals our calibrated one: sqrt(5) beta(e') = c(e) (module docstring),
    beta(e') = |ln e'| / sqrt(ln^2 e' + pi^2)."""
    from hel_warp.collisions.contact_law import damping_coefficient

    beta = float(damping_coefficient(restitution)) / math.sqrt(5.0)
    return math.exp(-math.pi * beta / math.sqrt(1.0 - beta * beta))


def write_liggghts_case(case: dict, steps: int, dt: float, skin: float, folder: str) -> str:
    """Data file and input script of a case; returns the input path."""
    x, v, r = case["x"], case["v"], case["radius"]
    lo, hi = case["lo"], case["hi"]
    m = case["material"]
    data = os.path.join(folder, "bed.data")
    ids = np.arange(1, len(x) + 1)
    with open(data, "w") as fh:
        fh.write(f"hel_warp bench_dem {case['case']}\n\n{len(x)} atoms\n1 atom types\n\n")
        for a, name in enumerate("xyz"):
            fh.write(f"{lo[a]!r} {hi[a]!r} {name}lo {name}hi\n")
        fh.write("\nAtoms\n\n")
        atoms = np.column_stack([ids, np.ones_like(ids), np.full(len(x), 2.0 * r), np.full(len(x), m.density), x])
        np.savetxt(fh, atoms, fmt=["%d", "%d", "%.17g", "%.17g", "%.17g", "%.17g", "%.17g"])
        fh.write("\nVelocities\n\n")
        np.savetxt(fh, np.column_stack([ids, v, np.zeros_like(v)]), fmt=["%d"] + ["%.17g"] * 6)
    model = "model hertz tangential history"
    options = "limitForce on tangential_damping off"
    walls = "\n".join(
        f"fix w{name}{side} all wall/gran {model} primitive type 1 {name}plane {value!r} {options}"
        for name, lo_a, hi_a in zip("xyz", lo, hi) for side, value in (("lo", lo_a), ("hi", hi_a)))
    script = f"""atom_style granular
atom_modify map array
boundary f f f
newton off
communicate single vel yes
units si
read_data {data}
neighbor {skin!r} bin
neigh_modify delay 0
fix m1 all property/global youngsModulus peratomtype {m.youngs_modulus!r}
fix m2 all property/global poissonsRatio peratomtype {m.poisson_ratio!r}
fix m3 all property/global coefficientRestitution peratomtypepair 1 {liggghts_restitution(m.restitution)!r}
fix m4 all property/global coefficientFriction peratomtypepair 1 {m.friction!r}
pair_style gran {model} {options}
pair_coeff * *
timestep {dt!r}
fix gravi all gravity 9.81 vector 0.0 0.0 -1.0
{walls}
fix integr all nve/sphere
variable kinetic equal ke
variable xc equal xcm(all,x)
variable yc equal xcm(all,y)
variable zc equal xcm(all,z)
thermo_style custom step atoms ke
thermo {max(steps, 1)}
run {steps}
print "HEL_RESULT ${{kinetic}} ${{xc}} ${{yc}} ${{zc}} $(atoms)"
"""
    path = os.path.join(folder, f"in.{case['case']}.{steps}")
    with open(path, "w") as fh:
        fh.write(script)
    return path


def run_liggghts(executable: str, script: str, folder: str) -> dict:
    """Run LIGGGHTS on one process; child CPU time, its loop time, list builds and the final observables."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen([executable, "-in", script, "-echo", "none", "-log", "none"], cwd=folder,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out, _ = proc.communicate()
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)  # the waited child's own CPU time (user + sys)
    usage = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if proc.returncode != 0 or "HEL_RESULT" not in out:
        raise RuntimeError(f"liggghts failed (exit {proc.returncode}):\n{out[-3000:]}")
    result = {"wall_s": wall, "cpu_s": usage, "output": out}
    for line in out.splitlines():
        if line.startswith("HEL_RESULT"):
            ke, xc, yc, zc, atoms = (float(s) for s in line.split()[1:6])
            result.update(ke=ke, com=np.array([xc, yc, zc]), atoms=int(atoms))
        elif line.startswith("Loop time of"):
            result["loop_wall_s"] = float(line.split()[3])
        elif line.startswith("Neighbor list builds"):
            result["rebuilds"] = int(line.split("=")[1])
        elif line.startswith("Dangerous builds"):
            result["dangerous"] = int(line.split("=")[1])
    return result


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




def compare_case(name: str, n: int, steps: int, args, executable: str | None) -> dict:
    """Ours and LIGGGHTS alternately on one case; medians, ratio and the physical agreement."""
    case = bed(name, n, offset=args.offset)
    mass = sphere_mass(case)
    start = observables(case["x"], case["v"], mass)
    ours_runs, peer_runs, setup = [], [], None
    with tempfile.TemporaryDirectory(prefix="bench_dem_") as folder:
        if executable:
            dt = case["material"].time_step(case["radius"]).chosen
            skin = 0.3 * case["radius"]
            run_script = write_liggghts_case(case, steps, dt, skin, folder)
            setup = run_liggghts(executable, write_liggghts_case(case, 0, dt, skin, folder), folder)
        for _ in range(args.repeats):
            ours_runs.append(run_ours(case, steps, args.device, args.capacity, args.sort_every))
            if executable:
                peer_runs.append(run_liggghts(executable, run_script, folder))
    med = statistics.median
    row = {"case": name, "n": len(case["x"]), "steps": steps,
           "ours": {"rate": med(r["rate"] for r in ours_runs), "rate_wall": med(r["rate_wall"] for r in ours_runs),
                    "rebuilds": ours_runs[0]["rebuilds"], "contacts_per_particle": ours_runs[-1]["contacts_per_particle"],
                    "ke": ours_runs[0]["ke"], "com": ours_runs[0]["com"].tolist(),
                    "rates": [r["rate"] for r in ours_runs]}}
    if executable:
        count = len(case["x"]) * steps
        loop_cpu = [r["cpu_s"] - setup["cpu_s"] for r in peer_runs]
        lg = peer_runs[0]
        ke_diff = ours_runs[0]["ke"] / lg["ke"] - 1.0
        d_ours = ours_runs[0]["com"] - start["com"]
        d_peer = lg["com"] - start["com"]
        com_diff = float(np.linalg.norm(d_ours - d_peer) / max(np.linalg.norm(d_peer), 1e-300))
        row["liggghts"] = {"rate": med(count / c for c in loop_cpu),
                           "rate_wall": med(count / r["loop_wall_s"] for r in peer_runs),
                           "rates": [count / c for c in loop_cpu], "setup_cpu_s": setup["cpu_s"],
                           "rebuilds": lg["rebuilds"], "dangerous": lg.get("dangerous"), "ke": lg["ke"],
                           "com": lg["com"].tolist(), "restitution": liggghts_restitution(case["material"].restitution)}
        row["ratio"] = row["ours"]["rate"] / row["liggghts"]["rate"]
        row["ratios_per_repeat"] = [o["rate"] / (count / c) for o, c in zip(ours_runs, loop_cpu)]
        row["ke_rel_diff"] = ke_diff
        row["com_shift_rel_diff"] = com_diff
        row["com_rel_diff"] = float(np.max(np.abs(ours_runs[0]["com"] / lg["com"] - 1.0)))
        # our positions are float32: a shift below one unit in the last place at the box height is unresolved
        row["com_shift_abs_diff_m"] = float(np.linalg.norm(d_ours - d_peer))
        row["float32_resolution_m"] = float(np.spacing(np.float32(max(case["hi"]))))
        row["agree"] = abs(ke_diff) <= 0.01 and (com_diff <= 0.01
                                                 or row["com_shift_abs_diff_m"] <= row["float32_resolution_m"])
    return row


def time_ours_static(n: int, args) -> dict:
    """Ours on the static bed of n spheres: CPU-time rate, median of repeats of k steps (the flatness sweep)."""
    import warp as wp

    solver = build_ours(bed("static", n), args.device, args.sort_every, args.capacity, args.shuffle)
    device = args.device
    solver.simulate(5)
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    solver.simulate(5)
    wp.synchronize_device(device)
    per_step = (time.perf_counter() - t0) / 5
    k = max(20, int(args.budget / args.repeats / per_step))
    wall, cpu = [], []
    for _ in range(args.repeats):
        wp.synchronize_device(device)
        t0, c0 = time.perf_counter(), time.process_time()
        solver.simulate(k)
        wp.synchronize_device(device)
        wall.append(n * k / (time.perf_counter() - t0))
        cpu.append(n * k / (time.process_time() - c0))
    return {"rate": statistics.median(cpu), "rate_wall": statistics.median(wall), "rates_cpu": cpu,
            "steps_per_repeat": k, "rebuilds": solver.rebuilds, "steps": solver.steps_done}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", nargs="*", default=["static", "fall"], choices=sorted(CASES),
                        help="beds timed against LIGGGHTS (default static fall)")
    parser.add_argument("--peer-n", type=int, default=100_000, help="spheres in the LIGGGHTS comparison (default 1e5)")
    parser.add_argument("--static-steps", type=int, default=DEFAULT_STEPS["static"])
    parser.add_argument("--fall-steps", type=int, default=DEFAULT_STEPS["fall"], help="steps of fall and fall-dense")
    parser.add_argument("--sizes", type=int, nargs="*", default=[10_000, 100_000, 1_000_000],
                        help="our static bed at these counts for the flatness of the cost (default 1e4 1e5 1e6; "
                             "none to skip)")
    parser.add_argument("--device", default="cpu", help="Warp device of ours (default cpu)")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats per case and code (default 3)")
    parser.add_argument("--budget", type=float, default=6.0, help="seconds of timed work per size in the sweep")
    parser.add_argument("--sort-every", type=int, default=None,
                        help="our spatial sort every k rebuilds (default: the solver default, 10 on the CPU)")
    parser.add_argument("--capacity", type=int, default=16, help="our contact-list capacity (default 16)")
    parser.add_argument("--shuffle", action="store_true", help="sweep: our spheres in random memory order")
    parser.add_argument("--offset", type=float, default=0.0,
                        help="move the compared beds this far from the origin, m (float32 resolution check)")
    parser.add_argument("--liggghts", default=shutil.which("liggghts"), help="LIGGGHTS executable (default: PATH)")
    parser.add_argument("--warp-example", action="store_true", help="also time Warp's example_dem in the sweep")
    parser.add_argument("--json", help="also write the results to this JSON file")
    args = parser.parse_args(argv)

    from hel_warp._warp import init_warp

    init_warp(args.device)
    load = os.getloadavg()
    print(f"device {args.device}; load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} cores; "
          f"{args.repeats} repeats; rates in particle-steps/s of CPU time (wall-clock in brackets)")
    warm_up(args.device, args.capacity)
    results = {"load": load, "cases": [], "sweep": []}
    if args.cases:
        if not args.liggghts:
            print("LIGGGHTS not found on the PATH (apt-get install liggghts): timing ours alone")
        print(f"{'case':>10} {'N':>7} {'steps':>5} {'ours':>20} {'LIGGGHTS':>20} {'ours/LG':>7} "
              f"{'rebuilds':>9} {'KE diff':>8} {'COM shift diff':>14}")
    for name in args.cases:
        steps = args.static_steps if name == "static" else args.fall_steps
        row = compare_case(name, args.peer_n, steps, args, args.liggghts)
        results["cases"].append(row)
        o = row["ours"]
        if "liggghts" in row:
            lg = row["liggghts"]
            print(f"{name:>10} {row['n']:>7} {steps:>5} {o['rate']:>9.3g} ({o['rate_wall']:>8.3g}) "
                  f"{lg['rate']:>9.3g} ({lg['rate_wall']:>8.3g}) {row['ratio']:>7.2f} "
                  f"{o['rebuilds']:>4}/{lg['rebuilds']:<4} {100 * row['ke_rel_diff']:>7.2f}% "
                  f"{100 * row['com_shift_rel_diff']:>13.2f}% ({1e9 * row['com_shift_abs_diff_m']:.1f} nm, "
                  f"float32 ulp {1e9 * row['float32_resolution_m']:.1f} nm)  "
                  f"{'agree' if row['agree'] else 'DISAGREE'}", flush=True)
        else:
            print(f"{name:>10} {row['n']:>7} {steps:>5} {o['rate']:>9.3g} ({o['rate_wall']:>8.3g}) {'-':>20}", flush=True)
    if args.cases and args.liggghts:
        print("ours/LG: median of CPU-time rates; per repeat: "
              + "; ".join(f"{r['case']} " + " ".join(f"{x:.2f}" for x in r["ratios_per_repeat"])
                          for r in results["cases"])
              + f". LIGGGHTS e' = {results['cases'][0]['liggghts']['restitution']:.4f} (our calibrated e = 0.5)")

    if args.sizes:
        print(f"\nflatness: ours on the static bed; {'N':>8} {'ours':>20} {'ns/step':>8}"
              + (f" {'warp example':>20} {'ours/warp':>9}" if args.warp_example else ""))
    for n in args.sizes:
        ours = time_ours_static(n, args)
        row = {"n": n, "ours": ours}
        line = f"{'':>36}{n:>8} {ours['rate']:>9.3g} ({ours['rate_wall']:>8.3g}) {1e9 / ours['rate']:>8.1f}"
        if args.warp_example:
            with contextlib.redirect_stdout(io.StringIO()):  # the example's ScopedTimer prints
                row["warp_example"] = time_warp_example(n, args.device, args.repeats, args.budget)
            line += f" {row['warp_example']['rate']:>9.3g} ({row['warp_example']['rate_wall']:>8.3g}) " \
                    f"{ours['rate'] / row['warp_example']['rate']:>9.2f}"
        results["sweep"].append(row)
        print(line, flush=True)
    if args.sizes:
        costs = [1e9 / r["ours"]["rate"] for r in results["sweep"]]
        print(f"cost per particle-step {min(costs):.1f}..{max(costs):.1f} ns, max/min = {max(costs) / min(costs):.2f} "
              f"over N = {args.sizes[0]:.0e}..{args.sizes[-1]:.0e} (target <= 1.5)")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1, default=lambda a: a.tolist() if hasattr(a, "tolist") else str(a))
    return 0


if __name__ == "__main__":
    sys.exit(main())

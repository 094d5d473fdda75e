"""Settling column: N polyethylene spheres fall from a loose lattice onto the floor of a closed box.

Material: the project's polyethylene (``Material()``: rho = 1000 kg/m^3, E = 0.5 GPa, nu = 0.4)
with e = 0.5 and mu = 0.3, spheres of diameter 6 mm (``--diameter``), 5 % polydisperse.
Why this choice: the DEM step of eq. (12) grows with size and falls with stiffness
(Rayleigh step ~ r sqrt(rho/G)); 6 mm polyethylene gives dt = 4.7e-6 s, so the column settles
(fall of ~0.1 m + relaxation, about 0.3 s) in ~6e4 steps — feasible on a CPU at 1e5 spheres —
while keeping real material constants (mm glass beads, E = 63 GPa, would need ~1.5e6 steps).
The initial lattice spacing is 1.1 d with a jitter of 0.05 d (no initial overlap); the square box
is sized so the lattice is about as tall as it is wide.

CI size (default, a few seconds)::

    hel-warp dem settling_column --particles 2000 --end-time 0.02 --out runs/settling_ci

Full size (>= 1e5 spheres; 66,700 steps, ~40 min on one uncontended CPU core at the measured
2.5-4e6 particle-steps/s of scripts/bench_dem.py)::

    hel-warp dem settling_column --particles 100000 --end-time 0.3 --snapshots 30 --out runs/settling

Writes ``OUT/run.zarr`` (snapshots of x, v, omega, radius, ... with the resolved config as
attrs) and ``OUT/vtk/particles_XXXX.vtp`` + ``OUT/vtk/particles.pvd`` (open the .pvd in ParaView,
glyph the points with the ``radius`` array). ``check()`` asserts physical facts at the end.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

if str(Path(__file__).resolve().parents[1]) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from hel_warp.errors import finite_float

    parser.add_argument("--particles", type=int, default=2000, help="number of spheres (default 2000)")
    parser.add_argument("--end-time", type=finite_float, default=0.02, help="simulated time, s (default 0.02)")
    parser.add_argument("--out", default="runs/settling_column", help="output directory (default runs/settling_column)")
    parser.add_argument("--device", default="cpu", help="Warp device: cpu or cuda (default cpu)")
    parser.add_argument("--diameter", type=finite_float, default=6e-3, help="mean sphere diameter, m (default 6e-3)")
    parser.add_argument("--snapshots", type=int, default=5, help="snapshots written after t = 0 (default 5)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the jitter and size spread (default 0)")
    parser.add_argument("--no-vtk", action="store_true", help="write run.zarr only")


def build(args):
    """The solver of the settling column (particles on a jittered lattice in a closed box)."""
    from hel_warp._warp import init_warp
    from hel_warp.collisions.dem import DEMConfig, DEMSolver
    from hel_warp.errors import ConfigError
    from hel_warp.material import Material
    from hel_warp.parcels.particles import Particles, lattice_positions

    init_warp(args.device)
    if args.particles < 1:
        raise ConfigError(f"--particles must be >= 1 (got {args.particles})")
    d = args.diameter
    if not d > 0:
        raise ConfigError(f"--diameter must be > 0 (got {d})")
    rng = np.random.default_rng(args.seed)
    radius = 0.5 * d * (1.0 + 0.05 * rng.uniform(-1.0, 1.0, args.particles))
    spacing = 1.1 * float(2.0 * radius.max())
    per_side = max(2, int(math.ceil(args.particles ** (1.0 / 3.0))))
    width = per_side * spacing
    layers = int(math.ceil(args.particles / per_side**2))
    lo = (0.0, 0.0, 0.0)
    hi = (width, width, (layers + 1) * spacing)
    x = lattice_positions(args.particles, spacing, lo, hi, jitter=0.05 * d, seed=args.seed)
    material = Material(density=1000.0, youngs_modulus=5e8, poisson_ratio=0.4, restitution=0.5, friction=0.3)
    particles = Particles.from_numpy(x, radius, density=material.density, box_lo=lo, box_hi=hi, device=args.device)
    config = DEMConfig(material=material, box_lo=lo, box_hi=hi, gravity=(0.0, 0.0, -9.81))
    return DEMSolver(config, particles)


def check(solver, n_initial: int) -> list[str]:
    """Physical facts at the end of the run; returns the list of violations (empty = pass).

    - the particle count is conserved and every particle is alive;
    - every position and velocity is finite;
    - no sphere penetrates a wall by more than 5 % of its radius (the static Hertz overlap at the
      bottom of a 1e5-sphere column is far below that; a larger value means a sphere went through);
    """
    data = solver.particles.to_numpy()
    errors = []
    if data["x"].shape[0] != n_initial or not np.all(data["alive"] == 1):
        errors.append(f"particle count not conserved: {int(data['alive'].sum())} alive of {n_initial}")
    if not (np.all(np.isfinite(data["x"])) and np.all(np.isfinite(data["v"]))):
        errors.append("non-finite positions or velocities")
    lo, hi = np.asarray(solver.config.box_lo), np.asarray(solver.config.box_hi)
    r = data["radius"][:, None]
    depth = np.maximum(lo - (data["x"] - r), (data["x"] + r) - hi).max(axis=1)
    worst = int(np.argmax(depth / data["radius"]))
    if depth[worst] > 0.05 * data["radius"][worst]:
        errors.append(f"particle {worst} penetrates a wall by {depth[worst]:.3e} m "
                      f"({depth[worst] / data['radius'][worst]:.1%} of its radius)")
    return errors


def run(args, *, progress: bool = True) -> int:
    from hel_warp.collisions.dem import run_with_output
    from hel_warp.runs.io import RunWriter

    solver = build(args)
    n = solver.particles.count
    writer = RunWriter(args.out, config={"case": "settling_column", "args": vars(args), **solver.resolved_config()},
                       vtk=not args.no_vtk)
    steps = run_with_output(solver, end_time=args.end_time, writer=writer, snapshots=args.snapshots,
                            progress=progress)
    errors = check(solver, n)
    data = solver.particles.to_numpy()
    mass = solver.particles.mass_numpy()
    kinetic = 0.5 * float(np.sum(mass * np.sum(data["v"].astype(np.float64) ** 2, axis=1)))
    print(f"settling_column: {n} spheres, {steps} steps of {solver.dt:.3e} s, t = {solver.time:.4f} s, "
          f"{solver.rebuilds} list rebuilds, kinetic energy {kinetic:.3e} J, top of bed "
          f"{float((data['x'][:, 2] + data['radius']).max()):.4f} m -> {args.out}")
    for e in errors:
        print(f"check failed: {e}", file=sys.stderr)
    return 1 if errors else 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_arguments(parser)
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    return run(args, progress=not args.no_progress)


if __name__ == "__main__":
    sys.exit(main())

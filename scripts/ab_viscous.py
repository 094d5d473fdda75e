"""In-process paired A/B of two viscous preconditioners (``GasConfig.viscous_preconditioner``) on the
colliding-streams rig's grid (``bench_hel.warm_rig``): one solver, its config swapped between the two, the same
saved ``GasField`` restored before every timed call; the viscous sub-step (``add_forces_and_diffuse`` after the
cell state and advection) and whole steps, alternated in pairs, process CPU time. Every viscous solve of the
warm-up steps is checked against ||b - A u|| <= viscous_tolerance ||b|| (the true residual, numpy).

    python scripts/ab_viscous.py [pairs] [A] [B]     # defaults: 30 ic0 jacobi
"""
import dataclasses
import os
import statistics
import sys
import time

import numpy as np
import warp as wp
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import hel_warp, bench_hel
print("hel_warp from", os.path.dirname(hel_warp.__file__))

if {"-h", "--help"} & set(sys.argv[1:]):
    print(__doc__)
    sys.exit(0)
pairs = int(sys.argv[1]) if len(sys.argv) > 1 else 30
A_KIND, B_KIND = (sys.argv[2], sys.argv[3]) if len(sys.argv) > 3 else ("ic0", "jacobi")
device = wp.get_device("cpu")
rig = bench_hel.warm_rig(device)
solver, gas, dt = rig.solver.gas_solver, rig.solver.gas, rig.solver.config.dt
solver.step(gas, dt)
fluid = int(solver.domain.cell_fluid.numpy().sum())
configs = {k: dataclasses.replace(solver.config, viscous_preconditioner=k) for k in (A_KIND, B_KIND)}

arrays, restore = bench_hel.gas_snapshot(gas)

# residual check on every viscous solve: true ||b - A u|| / ||b|| in numpy from the compact system
checks = {k: [] for k in configs}
current = ["ic0"]
orig_solve = solver._solve
def checked_solve(system, what, tol, maxiter, *a, **kw):
    it = orig_solve(system, what, tol, maxiter, *a, **kw)
    if CHECK and system in (0, 1, 2):
        n = solver._systems[system][0].shape[0]
        A = solver._stencils[system]
        d, c, nb = A.diag.numpy()[:n], A.coef.numpy()[:n], A.neighbour.numpy()[:n]
        b, x = solver._c_rhs.numpy()[:n], solver._c_x.numpy()[:n]
        ax = d * x - (c * x[nb]).sum(axis=1)
        checks[current[0]].append((system, it, float(np.linalg.norm(b - ax) / np.linalg.norm(b)), tol))
    return it
solver._solve = checked_solve

def one(kind, part):
    current[0] = kind
    solver.config = configs[kind]
    restore()
    if part == "viscous":
        solver.update_cell_state(gas)
        solver.advect(gas, dt)
        t = time.process_time()
        solver.add_forces_and_diffuse(gas, dt)
        return time.process_time() - t
    t = time.process_time()
    solver.step(gas, dt)
    return time.process_time() - t

CHECK = True
outs = {}
for kind in configs:  # warm-up (compiles, captures) and the answers
    for _ in range(2):
        one(kind, "step")
    outs[kind] = [np.array(a, copy=True) for a in gas.face_arrays()] + [gas.cell_pressure.numpy().copy()]
    print(kind, "iterations", solver.last_iterations)
for kind, rows in checks.items():
    for system, it, rel, tol in rows[-3:]:
        print(f"  {kind} component {system}: {it} iterations, true ||b-Au||/||b|| = {rel:.3e} (tol {tol:.3e}) "
              f"{'OK' if rel <= tol else 'FAIL'}")
umax = max(np.abs(a).max() for a in outs[A_KIND][:3])
print(f"max |du| {B_KIND} vs {A_KIND} over face velocities:", max(np.abs(a - b).max() for a, b in zip(outs[A_KIND][:3], outs[B_KIND][:3])),
      "of max |u|", umax, "; max |dp|", np.abs(outs[A_KIND][3] - outs[B_KIND][3]).max(), "of", np.abs(outs[A_KIND][3]).max())
CHECK = False
for part in ("viscous", "step"):
    times = {k: [] for k in configs}
    ratios = []
    for i in range(pairs):
        order = (A_KIND, B_KIND) if i % 2 == 0 else (B_KIND, A_KIND)
        t = {k: one(k, part) for k in order}
        for k in configs:
            times[k].append(t[k])
        ratios.append(t[A_KIND] / t[B_KIND])
    q = statistics.quantiles(ratios, n=4)
    print(f"{part}: load {os.getloadavg()[0]:.2f}; " + "; ".join(
        f"{k} median {1e3*statistics.median(v):.2f} ms (min {1e3*min(v):.2f})" for k, v in times.items())
        + f"; paired ratio {A_KIND}/{B_KIND} median {statistics.median(ratios):.3f} ({q[0]:.3f}-{q[2]:.3f}), {pairs} pairs"
        + (f"; per fluid cell {A_KIND} {1e9*statistics.median(times[A_KIND])/fluid/1e3:.3f} us, {B_KIND} {1e9*statistics.median(times[B_KIND])/fluid/1e3:.3f} us" if part == "step" else ""))

"""In-process paired A/B of the batched native CPU loops (``kernels/gas_cpu.py`` ``ADVECT_KERNELS`` and
``smagorinsky_kernel``, ``BATCH_LANES``) of this tree against those of another revision, on the colliding-streams
rig's grid (``bench_hel.warm_rig``): the other revision's ``kernels/gas_cpu.py`` (``git show REV:kernels/gas_cpu.py``)
is loaded under another module name; the three advection launches alone, the Smagorinsky launch alone and whole gas
steps (one solver whose recorded launches are swapped between the two sets; every other loop is the same code) are
alternated in pairs from the same saved ``GasField``, process CPU time. The outputs are compared bit for bit (the
advected faces, nu_t and kappa, and every face velocity and the cell pressure after a step).

    python scripts/ab_batched.py [pairs] [REV]     # defaults: 100 main
"""
import importlib.util
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import warp as wp

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import bench_hel  # noqa: E402
import hel_warp  # noqa: E402
from kernels import gas as K  # noqa: E402
from kernels import gas_cpu  # noqa: E402

print("hel_warp from", os.path.dirname(hel_warp.__file__))
if {"-h", "--help"} & set(sys.argv[1:]):
    print(__doc__)
    sys.exit(0)
pairs = int(sys.argv[1]) if len(sys.argv) > 1 else 100
rev = sys.argv[2] if len(sys.argv) > 2 else "main"
root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
source = subprocess.run(["git", "-C", root, "show", f"{rev}:kernels/gas_cpu.py"], check=True, capture_output=True,
                        text=True).stdout
with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as file:
    file.write(source)
spec = importlib.util.spec_from_file_location("gas_cpu_before", file.name)
before = importlib.util.module_from_spec(spec)
sys.modules["gas_cpu_before"] = before
spec.loader.exec_module(before)
SWAPPED = ("ADVECT_KERNELS", "smagorinsky_kernel")
variants = {"before": {k: getattr(before, k) for k in SWAPPED}, "after": {k: getattr(gas_cpu, k) for k in SWAPPED}}

device = wp.get_device("cpu")
rig = bench_hel.warm_rig(device)
solver, gas, dt = rig.solver.gas_solver, rig.solver.gas, rig.solver.config.dt
solver.step(gas, dt)
fluid = int(solver.domain.cell_fluid.numpy().sum())
arrays, restore = bench_hel.gas_snapshot(gas)


# the three advection launches of each, into outputs of their own
outputs, kernel_launches, smagorinsky_out = {}, {}, {}
for name, kernels in variants.items():
    out = K.FaceFloat()
    out.x, out.y, out.z = (wp.zeros_like(a) for a in (gas.face_velocity.x, gas.face_velocity.y, gas.face_velocity.z))
    outputs[name] = out
    for axis in range(3):
        faces = solver._solved_faces[axis]
        dim = (faces.shape[0] + K.CPU_BLOCK - 1) // K.CPU_BLOCK
        kernel_launches[name, axis] = wp.launch(
            kernels["ADVECT_KERNELS"][axis], dim=dim, inputs=[K.CPU_BLOCK, solver.grid_info, faces, solver.domain.face_type,
                                            gas.face_velocity, float(dt), out], device=device, record_cmd=True)
    cells = solver._fluid_cells
    smagorinsky_out[name] = [wp.zeros_like(gas.cell_nu_t), wp.zeros_like(solver._cell_kappa)]
    kernel_launches[name, "smagorinsky"] = wp.launch(
        kernels["smagorinsky_kernel"], dim=(cells.shape[0] + K.CPU_BLOCK - 1) // K.CPU_BLOCK,
        inputs=[K.CPU_BLOCK, solver.grid_info, solver._params(1.0), cells, solver.domain.cell_fluid, gas.cell_velocity,
                gas.cell_eps_f, *smagorinsky_out[name]], device=device, record_cmd=True)
for launch in kernel_launches.values():
    launch.launch()
for c in "xyz":
    a, b = (getattr(outputs[k], c).numpy() for k in variants)
    print(f"advected {c} faces: {'bit for bit equal' if np.array_equal(a.view(np.uint32), b.view(np.uint32)) else 'DIFFER'}")
for i, what in enumerate(("nu_t", "kappa")):
    a, b = (smagorinsky_out[k][i].numpy() for k in variants)
    print(f"Smagorinsky {what}: {'bit for bit equal' if np.array_equal(a.view(np.uint32), b.view(np.uint32)) else 'DIFFER'}")

# whole steps: the solver's recorded launches recorded once per variant (gas_cpu.for_device picks the native kernel)
recorded = {}
answers = {}
for name, kernels in variants.items():
    for k, v in kernels.items():
        setattr(gas_cpu, k, v)
    solver._recorded_launches = {}
    for _ in range(2):
        restore()
        solver.step(gas, dt)
    recorded[name] = solver._recorded_launches
    answers[name] = [np.array(a, copy=True) for a in gas.face_arrays()] + [gas.cell_pressure.numpy().copy()]
    print(name, "iterations", solver.last_iterations)
for k, v in variants["after"].items():
    setattr(gas_cpu, k, v)
same = all(np.array_equal(a.view(np.uint32), b.view(np.uint32)) for a, b in zip(answers["before"], answers["after"]))
print("one step from the same state:", "every face velocity and the cell pressure bit for bit equal" if same else
      f"DIFFER: max |du| {max(np.abs(a - b).max() for a, b in zip(answers['before'], answers['after']))}")


def run(name, part):
    restore()
    if part in ("advection", "smagorinsky"):
        start = time.process_time()
        for key in (0, 1, 2) if part == "advection" else ("smagorinsky",):
            kernel_launches[name, key].launch()
        return time.process_time() - start
    solver._recorded_launches = recorded[name]
    start = time.process_time()
    solver.step(gas, dt)
    return time.process_time() - start


for part in ("advection", "smagorinsky", "step"):
    times = {k: [] for k in variants}
    ratios = []
    for i in range(pairs):
        order = ("before", "after") if i % 2 == 0 else ("after", "before")
        t = {k: run(k, part) for k in order}
        for k in variants:
            times[k].append(t[k])
        ratios.append(t["before"] / t["after"])
    q = statistics.quantiles(ratios, n=4)
    print(f"{part}: load {os.getloadavg()[0]:.2f}; " + "; ".join(
        f"{k} median {1e3 * statistics.median(v):.2f} ms (min {1e3 * min(v):.2f})" for k, v in times.items())
        + f"; paired ratio before/after median {statistics.median(ratios):.3f} ({q[0]:.3f}-{q[2]:.3f}), {pairs} pairs"
        + ("; per fluid cell " + ", ".join(f"{k} {1e6 * statistics.median(v) / fluid:.3f} us" for k, v in times.items())
           if part == "step" else ""))

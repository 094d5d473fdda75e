"""Which part of the DEM's conditional rebuild breaks CUDA graph instantiation? One JSON line.

    python scripts/probe_dem_graph.py        # from the repository root, on a machine with a GPU

Each entry captures one piece of ``DEMSolver._rebuild`` (on the tests' stirred column) inside a ``wp.capture_if`` body
(``if_*``) or plainly (``plain_*``), instantiates and launches the graph: "ok" or the error's first line. Last,
``simulate_graph``: a solver with ``cuda_graph_steps`` > 0 (after a refusal it falls back to eager steps, and
``use_graph`` is then False). Seen on an H200 with Warp 1.19: only
``if_hashgrid_build`` and ``if_whole_rebuild`` fail ("Graph creation error: invalid argument").
"""
import json
import os
import sys
import traceback

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import warp as wp  # noqa: E402

wp.config.log_level = wp.LOG_WARNING
wp.init()
dev = "cuda" if wp.is_cuda_available() else "cpu"
from tests.test_device_paths import _dem_column  # noqa: E402

out = {"device": dev}


@wp.kernel
def bump(a: wp.array(dtype=wp.int32)):
    a[0] = a[0] + 1


def trial(name, body, conditional=True):
    flag = wp.zeros(1, dtype=wp.int32, device=dev)
    flag.fill_(1)
    try:
        with wp.ScopedCapture(device=dev) as cap:
            if conditional:
                wp.capture_if(flag, on_true=body)
            else:
                body()
        wp.capture_launch(cap.graph)
        wp.synchronize_device(dev)
        out[name] = "ok"
    except Exception as exc:  # noqa: BLE001
        out[name] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:160]}"


s = _dem_column(dev, sort_every=0, cuda_graph_steps=0, half_list=False)
cnt = wp.zeros(1, dtype=wp.int32, device=dev)
trial("if_kernel", lambda: wp.launch(bump, dim=1, inputs=[cnt], device=dev))
trial("plain_hashgrid_build", lambda: s.grid.build(s.particles.x, s.cell_size), conditional=False)
trial("if_hashgrid_build", lambda: s.grid.build(s.particles.x, s.cell_size))
trial("if_copy_from", lambda: s._old_contacts.copy_from(s.contacts))
trial("plain_copy_from", lambda: s._old_contacts.copy_from(s.contacts), conditional=False)


def contact_list():
    from kernels.contacts import launch_build_contact_list
    launch_build_contact_list(s.grid, s.spheres, s.r_max, s.skin, s.old_rows, s.rows, s.x_at_build, s.overflow,
                              box=s.box, half=s.half_list, packed=s.half_list)


trial("if_contact_list", contact_list)
trial("if_zero", lambda: s.rebuild_flag.zero_())
trial("if_whole_rebuild", s._rebuild)
trial("plain_whole_rebuild", s._rebuild, conditional=False)
try:
    g = _dem_column(dev, sort_every=0, cuda_graph_steps=5, half_list=False)
    g.simulate(12)
    out["simulate_graph"] = f"ok use_graph={g._use_graph} rebuilds={g.rebuilds}"
except Exception:  # noqa: BLE001
    out["simulate_graph"] = traceback.format_exc().splitlines()[-1][:200]
print(json.dumps(out))

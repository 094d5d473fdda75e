"""Where one HEL step's time goes on a device: wall clock against the device's own activity, per kernel.

Builds one of the two cases the weighted parcels' speed figures use, runs a few untimed steps (module loads, first captures,
the release on the rig), then ``--steps`` steps under Warp's activity timing (``wp.timing_begin``: CUDA events
around every kernel launch, graph launch, memcpy and memset, on CUDA only) and prints per run:

- the wall clock per step (median) and the device's busy time per step (the sum of the recorded activities): a wall
  clock far above the busy time means the step waits on the host (launch packing, Python, read-backs), not on the
  GPU;
- the device-to-host copies per step (each one a sync of the host with the device);
- the activities ranked by their time per step (count per step, ms per step, us per call).

Cases:

- ``box``: the particle-dominated cooling box of the DEM / HELSCM ratio (``cases/homogeneous_cooling.py``, eps_s 0.01,
  Theta0 = 1 m^2/s^2, ``--particles`` real particles), HELSCM with cell detection at each ``--weights``;
- ``rig``: the colliding-streams rig (``scripts/bench_rig.py``'s ``build_model``) with each ``--models`` label
  (``ktgf``, ``surrogate_w64``, ...), each ``--linear-solver`` of the gas (``GasConfig.linear_solver``) and each
  ``--pcg-loop`` of the native one (``GasConfig.pcg_device_loop``).

On the CPU the activity timing records nothing: the wall clock and the step counts are still printed (the script's
own test runs it so).

Usage::

    python scripts/profile_step.py box --device cuda --weights 1 64 --model MODEL_DIR
    python scripts/profile_step.py rig --device cuda --models surrogate_w64 --linear-solver warp native --model DIR
    python scripts/profile_step.py rig --device cuda --models ktgf --pcg-loop host device --model DIR
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))


def _box(args, weight: float):
    import tempfile

    from cases import homogeneous_cooling as hc

    parser = argparse.ArgumentParser()
    hc.add_arguments(parser)
    ns = parser.parse_args(["--collisions", "surrogate", "--model", args.model, "--detection", "cell", "--dt", "1e-3",
                            "--solids-fraction", "0.01", "--particles", str(args.particles), "--diameter", "315e-6",
                            "--granular-temperature", "1", "--end-time", f"{(args.warmup + args.steps) * 1e-3:g}",
                            "--particles-per-parcel", f"{weight:g}", "--seed", "1", "--device", args.device,
                            "--out", os.path.join(tempfile.mkdtemp(), "box")])  # nothing is written
    from hel_warp.case.build import build
    from hel_warp.case.models import check_model

    flow = hc.CASE.build(ns)  # the box as the case runs it: its flow, settings and per-step record of the moments
    check_model(ns.model, flow.species_list)
    record = hc.CoolingRecorder(ns._cooling)
    sim = build(flow, hc.CASE.settings(ns, flow), observers=[record])
    record.bind(sim)
    return sim.solver.step


def _rig(args, label: str, solver: str, loop: str = "host"):
    from cases import colliding_streams as case

    import bench_rig

    ns = argparse.Namespace(diameter=315e-6, dt=1e-3, end_time=(args.warmup + args.steps) * 1e-3, model=args.model,
                            paper_model=None, detection="swept", force_model=False, cells=args.cells,
                            max_particles=args.max_particles, device=args.device)
    rig = bench_rig.build_model(case, label, ns)
    rig.gas_solver.linear_solver = solver  # GasConfig.linear_solver, after the set-up (both paths are set up)
    rig.gas_solver.device_loop = loop == "device"  # GasConfig.pcg_device_loop
    rig.solver.time_sub_steps = False  # no sync per phase: the step as a user runs it
    for _ in range(args.release_steps):  # the release: parcels in the rig before the profiled steps
        rig.solver.step()
    return rig.solver.step


def profile(step, args, device) -> dict:
    """``args.warmup`` untimed steps, then ``args.steps`` steps each under the activity timing."""
    import warp as wp

    for _ in range(args.warmup):
        step()
    wp.synchronize_device(device)
    walls, busy, per_name = [], [], {}
    d2h = 0
    for _ in range(args.steps):
        wp.timing_begin(cuda_filter=wp.TIMING_ALL)
        start = time.perf_counter()
        step()
        wp.synchronize_device(device)
        walls.append(time.perf_counter() - start)
        results = wp.timing_end()
        busy.append(sum(r.elapsed for r in results) * 1e-3)
        for r in results:
            count, ms = per_name.get(r.name, (0, 0.0))
            per_name[r.name] = (count + 1, ms + r.elapsed)
            if "DtoH" in r.name or "device to host" in r.name.lower():
                d2h += 1
    n = args.steps
    ranked = sorted(per_name.items(), key=lambda kv: -kv[1][1])
    return {"median_step_s": statistics.median(walls), "median_busy_s": statistics.median(busy),
            "busy_fraction": statistics.median(busy) / statistics.median(walls),
            "activities_per_step": sum(c for c, _ in per_name.values()) / n, "d2h_copies_per_step": d2h / n,
            "top": [{"name": name, "per_step": c / n, "ms_per_step": ms / n, "us_per_call": 1e3 * ms / c}
                    for name, (c, ms) in ranked[: args.top]]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case", choices=("box", "rig"))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--model", required=True, help="contact-form surrogate model directory")
    ap.add_argument("--weights", type=float, nargs="+", default=[1.0, 64.0], help="box: real particles per parcel")
    ap.add_argument("--particles", type=int, default=102400, help="box: real particles")
    ap.add_argument("--models", nargs="+", default=["surrogate_w64"], help="rig: bench_rig labels")
    ap.add_argument("--linear-solver", nargs="+", default=["native"], choices=("warp", "native"),
                    help="rig: the gas's linear solver(s)")
    ap.add_argument("--pcg-loop", nargs="+", default=["host"], choices=("host", "device"),
                    help="rig: the native CG's loop(s): host (a read-back per iteration) or device "
                         "(GasConfig.pcg_device_loop)")
    ap.add_argument("--cells", type=int, default=None, help="rig: shrink the grid (smoke runs)")
    ap.add_argument("--max-particles", type=int, default=None, help="rig: cap the parcels")
    ap.add_argument("--release-steps", type=int, default=6, help="rig: untimed steps of the release")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--top", type=int, default=15)
    ap.add_argument("--stack-every", type=float, default=0.0,
                    help="print every thread's Python stack every S seconds (0: never): where a slow run spends it")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.steps < 1 or args.warmup < 0 or args.release_steps < 0 or args.particles < 2 or args.top < 1:
        ap.exit(2, "profile_step: need --steps >= 1, --warmup >= 0, --release-steps >= 0, --particles >= 2, "
                   "--top >= 1\n")
    if not os.path.isdir(args.model):
        ap.exit(2, f"profile_step: --model {args.model}: no such directory; give a directory written by "
                   "`hel-warp train`\n")
    from hel_warp.errors import HelWarpError

    try:
        return _run(args)
    except HelWarpError as exc:  # ConfigError too: one line, exit 2
        print(f"profile_step: error: {exc}", file=sys.stderr)
        return 2


def _run(args) -> int:
    if args.stack_every > 0:
        import faulthandler

        faulthandler.dump_traceback_later(args.stack_every, repeat=True, file=sys.stderr)
    started = time.perf_counter()

    def say(what: str) -> None:  # progress on stderr, so that a run cut short still says how far it got
        print(f"[profile_step {time.perf_counter() - started:7.1f} s] {what}", file=sys.stderr, flush=True)

    import warp as wp

    from hel_warp._warp import init_warp
    from hel_warp.runs.run import check_device, load_kernels

    check_device(args.device)
    init_warp(args.device)
    say(f"kernels loaded in {load_kernels(args.device):.1f} s")
    device = wp.get_device(args.device)
    runs = []
    if args.case == "box":
        for w in args.weights:
            step = _box(args, w)
            say(f"box W={w:g} set up")
            runs.append({"case": "box", "weight": w, **profile(step, args, device)})
            say(f"box W={w:g} profiled: step {1e3 * runs[-1]['median_step_s']:.2f} ms")
    else:
        for label in args.models:
            for solver in args.linear_solver:
                for loop in args.pcg_loop if solver == "native" else ["host"]:
                    step = _rig(args, label, solver, loop)
                    say(f"rig {label} gas={solver} loop={loop} set up and released")
                    runs.append({"case": "rig", "model": label, "linear_solver": solver, "pcg_loop": loop,
                                 **profile(step, args, device)})
                    say(f"rig {label} gas={solver} loop={loop} profiled: step "
                        f"{1e3 * runs[-1]['median_step_s']:.2f} ms")
    if args.json:
        print(json.dumps({"device": str(device), "runs": runs}, indent=1))
        return 0
    for r in runs:
        what = (f"box W={r['weight']:g}" if r["case"] == "box"
                else f"rig {r['model']} gas={r['linear_solver']} loop={r['pcg_loop']}")
        print(f"== {what} on {device}: step {1e3 * r['median_step_s']:.2f} ms, device busy "
              f"{1e3 * r['median_busy_s']:.2f} ms ({100 * r['busy_fraction']:.0f} %), "
              f"{r['activities_per_step']:.0f} activities and {r['d2h_copies_per_step']:.0f} device-to-host copies per step")
        for t in r["top"]:
            print(f"   {t['ms_per_step']:8.3f} ms {t['per_step']:7.1f}x {t['us_per_call']:9.1f} us  {t['name'][:90]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

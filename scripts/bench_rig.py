"""Wall clock of the collision models on the colliding-streams rig, side by side in one process.

The ratios that judge HELSCM's cost: HELSCM / HEL (``surrogate`` over ``ktgf``, target <= 1.2) and DEM / HELSCM (``dem`` over
``surrogate``, the paper claims two to three orders of magnitude) for the same simulated time, at one particle
size and time step. Every model runs the same case (``cases/colliding_streams.py``: same grid, gas warm-up,
injection, seed) from the release to ``--end-time`` in this one process, round robin (step n of every model, then
step n + 1: a load on the machine falls on all models alike), after an untimed two-step run of each model on a
small grid that loads every kernel module; the steps alone are timed (``HelSolver.step``, synchronised per step
on CUDA), the gas warm-up and set-up are not.
Reported per model: the total step wall clock, the median step, the detected pairs per simulated second, and
the ratios (wall clock, and ``_cpu``: process CPU time, a core's cost whatever the load); then the median of each phase of the step (``HelSolver.timings``, on CUDA a sync per sub-step):
the gas step (and per fluid cell), the parcel phase = deposit + interpolate + push (per parcel-step, parcels
alive at the step; for a strategy with its own ``advance`` the push is its collision step), the collision
step = ``collide`` (+ that ``advance``), the rest (sort, outlets, walls, injection), and the gas step's own phases
(``GasSolver.timings``: cell state, advection, forces and viscous solves, projection). Rerun to judge the noise.

Usage::

    python scripts/bench_rig.py --model MODEL_DIR [--paper-model PAPER_DIR]                  # 315 um, 1e-3 s
    python scripts/bench_rig.py --diameter 475e-6 --dt 1e-4 --end-time 0.005 --model DIR
    python scripts/bench_rig.py --models none ktgf --end-time 0.003 --cells 20000             # smoke run
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

MODELS = ("none", "ktgf", "surrogate", "surrogate-paper", "dem")


def run_label(name: str, weight: float | None) -> str:
    """``surrogate_w8``: the surrogate with cell detection at 8 real particles per parcel (``--weights``)."""
    return name if weight is None else f"{name}_w{weight:g}"


def split_label(label: str):
    """(model, weight or None) of a ``run_label``."""
    name, _, w = label.partition("_w")
    return name, (float(w) if w else None)


def build_model(case, label: str, args):
    """The rig for ``label`` (a model, or ``surrogate_wW``: cell detection at weight W, the same real particles)
    after its gas warm-up (untimed); the release starts with the next step."""
    name, weight = split_label(label)
    detection = (args.detection if name == "surrogate" else None) if weight is None else "cell"
    real = None
    if weight is not None:  # the weight-1 run's real particles in 1/W of the parcels
        real = int(round(case.PAPER_PARTICLES[min(case.PAPER_PARTICLES, key=lambda d: abs(d - args.diameter))]))
        if args.max_particles is not None:  # the cap counts the weight-1 run's parcels (at least 2 of weight W)
            real = min(real, max(args.max_particles, int(2 * weight)))
    ns = argparse.Namespace(diameter=args.diameter, dt=args.dt, collisions=name, end_time=args.end_time,
                            particles_per_parcel=weight or 1.0, real_particles=real, max_particles=None if real
                            else args.max_particles, monodisperse=False,
                            model=(args.paper_model if name == "surrogate-paper" else args.model),
                            cells=args.cells, gas_warmup=0.01, output_interval=args.end_time, seed=0,
                            device=args.device, detection=detection,
                            no_particle_contacts=False)
    config = case.make_config(ns)
    if name.startswith("surrogate"):
        from hel_warp.case.models import check_model

        # the particle size and density (what the rig's check asked of a model to time): a benchmark times the
        # collision path, so a model of other elastic or frictional constants is no reason to refuse it
        check_model(config.model, case.flow_of(config).species_list, force=args.force_model,
                    force_flag="--force-model", check_material=False)
    rig = case.CollidingStreams(config)
    rig.warm_up()
    rig.solver.time_sub_steps = True  # per-phase wall clock (HelSolver.timings)
    return rig


PARCEL_PHASES = ("deposit", "interpolate", "push")
OTHER_PHASES = ("sort_parcels", "remove_at_outlets", "reflect_at_walls", "inject")
GAS_PHASES = ("gas_update_cell_state", "gas_advect", "gas_add_forces_and_diffuse", "gas_project")
"""The gas step's own phases (``GasSolver.timings``), inside ``gas``: where a GPU's gas time goes."""


def phases(solver) -> dict:
    """The last step's wall clock split into gas, parcel phase, collision step and the rest, s."""
    t = solver.timings
    own_advance = getattr(solver.collision, "advance", None) is not None
    parcel = sum(t.get(k, 0.0) for k in PARCEL_PHASES if not (k == "push" and own_advance))
    collision = t.get("collide", 0.0) + (t.get("push", 0.0) if own_advance else 0.0)
    return {"gas": t.get("gas_step", 0.0), "parcel": parcel, "collision": collision,
            "other": sum(t.get(k, 0.0) for k in OTHER_PHASES),
            **{k: t.get(k, 0.0) for k in GAS_PHASES}}


def reserve_deposit_records(names, device) -> None:
    """On CUDA, before any timed step: the tent deposits' deterministic-atomics records sized for the heaviest
    parcel of every run (``kernels.deposit.reserve_records``, which rebuilds that module when the bound grows), and
    the module built, so that no step compiles it. On an H200 without this the weight-8 run took 10.5 s
    for ten steps of median 54 ms: most likely that rebuild (~7 s of NVRTC here) inside its first step."""
    import warp as wp

    from kernels import deposit as D
    from kernels.interp import cloud_support_host, cloud_width_host, spread_half_width_host

    if not wp.get_device(device).is_cuda:
        return
    heaviest = max((split_label(name)[1] or 1.0) for name in names)
    k = max(spread_half_width_host(True, heaviest), cloud_support_host(cloud_width_host(heaviest)))  # either rule
    D.reserve_records(8 * k**3)
    wp.force_load(device=device, modules=[wp.get_module(D.__name__)])


def time_models(case, names, args) -> dict:
    """Step every model's rig to ``args.end_time``, round robin: step n of each model, then step n + 1, so
    that whatever load the machine carries falls on all models alike. Per-step wall clock per model."""
    import warp as wp

    rigs = {name: build_model(case, name, args) for name in names}
    reserve_deposit_records(names, args.device)
    steps = int(round(args.end_time / args.dt))
    walls = {name: [] for name in names}
    cpus = {name: [] for name in names}
    split = {name: [] for name in names}
    alive = {name: [] for name in names}
    detected = dict.fromkeys(names, 0)
    for _ in range(steps):
        for name, rig in rigs.items():
            device = rig.pool.particles.device
            rig.solver.timings.clear()
            parcels = rig.pool.alive_count()  # parcels the step moves (read before the timed step)
            start, cpu = time.perf_counter(), time.process_time()
            rig.solver.step()
            if device.is_cuda:
                wp.synchronize_device(device)
            walls[name].append(time.perf_counter() - start)
            cpus[name].append(time.process_time() - cpu)
            split[name].append(phases(rig.solver))
            alive[name].append(parcels)
            detected[name] += int(rig.solver.collision_counts().get("detected_pairs", 0))
    rows = {}
    for name in names:
        fluid = int(rigs[name].solver.gas_solver.domain.cell_fluid.numpy().sum())
        med = {key: statistics.median(s[key] for s in split[name]) for key in split[name][0]}
        loaded = [s["parcel"] / n for s, n in zip(split[name], alive[name]) if n > 0]
        rows[name] = {"model": name, "steps": steps, "total_s": sum(walls[name]), "total_cpu_s": sum(cpus[name]),
                      "median_step_cpu_s": statistics.median(cpus[name]),
                      "median_step_s": statistics.median(walls[name]),
                      "detected_pairs_per_s": (detected[name] / (steps * args.dt)
                                               if name not in ("none", "ktgf") else None),
                      "parcels": rigs[name].injected, "fluid_cells": fluid,
                      "phase_median_s": med, "gas_us_per_fluid_cell": 1e6 * med["gas"] / fluid,
                      "parcel_us_per_parcel_step": 1e6 * statistics.median(loaded) if loaded else None,
                      "parcels_alive_last": alive[name][-1]}
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--diameter", type=float, default=315e-6, help="particle diameter, m (default 315e-6)")
    parser.add_argument("--dt", type=float, default=1e-3, help="HEL time step, s (default 1e-3)")
    parser.add_argument("--end-time", type=float, default=0.01,
                        help="simulated time after the release, s (default 0.01: the release is over at ~6 ms)")
    parser.add_argument("--models", nargs="+", choices=MODELS, default=None,
                        help="models to time, in this order (default: all that have what they need)")
    parser.add_argument("--model", default=None, help="contact-form surrogate model directory (surrogate)")
    parser.add_argument("--paper-model", default=None, help="paper-form surrogate model directory")
    parser.add_argument("--detection", choices=("swept", "overlap"), default="swept",
                        help="surrogate pair detection (default swept)")
    parser.add_argument("--force-model", action="store_true",
                        help="use a surrogate trained for another mean diameter (e.g. a 315/475 um mixture model "
                             "at 475 um; the rig's own check otherwise refuses it)")
    parser.add_argument("--cells", type=int, default=None, help="shrink the grid to about N cells (smoke runs)")
    parser.add_argument("--max-particles", type=int, default=None, help="cap the parcels released")
    parser.add_argument("--device", default="cpu", help="Warp device (default cpu)")
    parser.add_argument("--weights", type=float, nargs="+", default=None,
                        help="also the surrogate with cell detection at these real particles per parcel (e.g. 1 8 "
                             "64), each with the real particles of the weight-1 runs (--real-particles): rows "
                             "surrogate_wW and the ratio dem_over_helscm_wW")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    models = args.models
    if models is None:
        models = [m for m in MODELS if not (m == "surrogate" and not args.model)
                  and not (m == "surrogate-paper" and not args.paper_model)]
    if "surrogate" in models and not args.model:
        parser.error("--models surrogate needs --model MODEL_DIR")
    if "surrogate-paper" in models and not args.paper_model:
        parser.error("--models surrogate-paper needs --paper-model MODEL_DIR")
    if not (args.end_time > 0 and args.dt > 0 and args.end_time >= args.dt):
        parser.error("need --end-time >= --dt > 0")
    if args.weights:
        if not args.model:
            parser.error("--weights needs --model MODEL_DIR (the surrogate's cell detection)")
        if any(not (w >= 1.0) for w in args.weights):
            parser.error(f"--weights must be >= 1 (got {args.weights})")
        models = list(models) + [run_label("surrogate", w) for w in args.weights]

    for flag, path in (("--model", args.model), ("--paper-model", args.paper_model)):
        if path and not os.path.isfile(os.path.join(path, "metadata.json")):
            parser.error(f"{flag} {path}: no metadata.json there; give a directory written by `hel-warp train`")
    from hel_warp.errors import HelWarpError
    from hel_warp.collisions.forest import quiet_warp
    from hel_warp.cli.commands._common import load_case_module

    quiet_warp()
    case = load_case_module("colliding_streams")
    small = argparse.Namespace(**{**vars(args), "cells": 5000, "max_particles": 40, "end_time": 2 * args.dt})
    try:
        time_models(case, models, small)  # load every kernel module once, untimed: no model pays the first launch
        rows = time_models(case, models, args)
    except HelWarpError as exc:
        print(f"bench_rig: error: {exc}", file=sys.stderr)
        return 2
    ratios = {}
    pairs = {"helscm_over_hel": ("surrogate", "ktgf"), "dem_over_helscm": ("dem", "surrogate"),
             "helscm_paper_over_hel": ("surrogate-paper", "ktgf")}
    for w in args.weights or ():
        pairs[f"dem_over_helscm_w{w:g}"] = ("dem", run_label("surrogate", w))
    for key, (a, b) in pairs.items():
        if a in rows and b in rows:
            ratios[key] = rows[a]["total_s"] / rows[b]["total_s"]
            ratios[key + "_cpu"] = rows[a]["total_cpu_s"] / rows[b]["total_cpu_s"]  # one core's cost: robust to load
    result = {"diameter": args.diameter, "dt": args.dt, "end_time": args.end_time, "device": args.device,
              "models": list(rows.values()), "ratios": ratios}
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"colliding-streams rig, d = {args.diameter * 1e6:.0f} um, dt = {args.dt:g} s, "
          f"{args.end_time:g} s simulated, device {args.device}")
    print(f"{'model':>16} {'steps':>6} {'total (s)':>10} {'CPU (s)':>9} {'median step (s)':>16} {'pairs/s':>10} "
          f"{'parcels':>8}")
    for r in rows.values():
        rate = r["detected_pairs_per_s"]
        print(f"{r['model']:>16} {r['steps']:>6} {r['total_s']:>10.2f} {r['total_cpu_s']:>9.2f} {r['median_step_s']:>16.4f} "
              f"{'-' if rate is None else format(rate, '.3g'):>10} {r['parcels']:>8}")
    print(f"phases, median per step (ms); gas per fluid cell ({next(iter(rows.values()))['fluid_cells']} fluid cells), "
          f"parcel phase per parcel-step (median over the steps with parcels)")
    print(f"{'model':>16} {'gas':>8} {'parcel':>8} {'collision':>10} {'other':>8} {'gas us/cell':>12} "
          f"{'parcel us/parcel':>17}")
    for r in rows.values():
        m = r["phase_median_s"]
        per_parcel = r["parcel_us_per_parcel_step"]
        print(f"{r['model']:>16} {1e3 * m['gas']:>8.2f} {1e3 * m['parcel']:>8.2f} {1e3 * m['collision']:>10.2f} "
              f"{1e3 * m['other']:>8.2f} {r['gas_us_per_fluid_cell']:>12.2f} "
              f"{'-' if per_parcel is None else format(per_parcel, '.3f'):>17}")
    print("gas phases, median per step (ms): cell state, advection, forces + viscous solves, projection")
    for r in rows.values():
        m = r["phase_median_s"]
        print(f"{r['model']:>16} " + " ".join(f"{1e3 * m[k]:>8.2f}" for k in GAS_PHASES))
    for key, value in ratios.items():
        print(f"{key}: {value:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

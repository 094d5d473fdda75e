"""The command line and run loop every case shares.

A case script describes its flow in a ``build(args) -> Flow`` function and hands it to :class:`Case`::

    case = Case("bubbling_bed", build, doc=__doc__, options=options, summary=summary, defaults={"dt": 2e-4})
    main = case.main          # hel-warp run cases/bubbling_bed.py ... calls main(argv)

``Case.main(argv)`` parses the options (the case's own, grouped in ``--help`` as case, physics, numerics, output,
advanced, beside the shared ones below), builds the flow, checks the output directory and the surrogate model,
builds the simulation, warms the gas up, and steps it to ``--end-time`` with ``hel_warp.runs.run.Run`` (snapshots,
per-step series, ``run.zarr``, VTK, atomic checkpoints, ``--resume`` bit for bit), a progress bar, the probes,
the case's ``check`` of physical facts, and a summary (``OUT/summary.json``, one JSON object on stdout with
``--json``). Bad input stops it before anything is written: one line ``hel-warp: error: ...`` on stderr and
exit code 2; a failed check: exit code 1.

Shared options: ``--out DIR``, ``--overwrite`` | ``--resume``, ``--end-time T``, ``--dt DT``, ``--output-interval
T``, ``--checkpoint-interval T``, ``--collisions {none,ktgf,surrogate,surrogate-paper,dem}``, ``--model DIR``,
``--force``, ``--seed S``, ``--device cpu|cuda``, ``--no-vtk``, ``--no-pictures``, ``--no-gas-snapshots``, ``--json``,
``--no-progress``, and for the surrogate ``--detection``, ``--particle-spin``, ``--cell-coarsen``, ``--cell-cfl``,
``--[no-]cell-approaching``, ``--no-packing-stress``; ``--particles-per-parcel W[,W2]`` where the case takes
weights; ``--collision-events PATH`` (every collision of every step to a ``.npz``).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from hel_warp.errors import ConfigError, HelWarpError, finite_float

SUMMARY = "summary.json"
GROUPS = ("case", "physics", "numerics", "output", "advanced")


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit code 2 (as every hel-warp command)
        self.exit(2, f"hel-warp: error: {self.prog}: {message}\n")


def floats(text: str) -> list:
    """argparse type: one or more comma-separated finite numbers."""
    try:
        values = [float(t) for t in str(text).split(",") if t.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of numbers: {text!r}") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected finite numbers, got {text!r}")
    return values


def ints(text: str) -> list:
    """argparse type: one or more comma-separated integers."""
    try:
        return [int(t) for t in str(text).split(",") if t.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of integers: {text!r}") from None


@dataclass
class Run:
    """What a finished (or interrupted) call hands the case's ``summary`` and ``check``: the simulation, the
    run loop, the probe records, the options, and the output directory."""

    sim: object
    runner: object
    probes: object
    args: object
    out: Path
    steps_this_call: int = 0
    loop_s: float = 0.0

    @property
    def solver(self):
        return self.sim.solver

    def series(self, name: str) -> np.ndarray | None:
        """A per-step series of ``run.zarr`` (e.g. ``timing_step``, ``collisions_collisions``)."""
        import zarr

        root = zarr.open_group(str(self.out / "run.zarr"), mode="r")
        series = root["series"]
        return np.asarray(series[name][...]) if name in series else None


@dataclass
class Case:
    """A case's command line (module docstring). ``build(args) -> Flow``; ``options(groups)`` adds the case's
    options to ``groups.case`` / ``.physics`` / ``.numerics`` / ``.output`` / ``.advanced``; ``summary(run) ->
    dict`` adds its figures to the summary; ``check(run) -> list[str]`` its physical facts (failures);
    ``observers(args, flow) -> list`` objects called after every step (``after_step(solver)``, optional
    ``state()`` / ``set_state()`` for the checkpoints); ``report(run, summary) -> str`` its line of text;
    ``finish(run, summary)`` writes its own files (pictures) into the run directory.

    ``defaults``: values of the shared options (``dt``, ``end_time``, ``output_interval``, ``collisions``); a
    shared option without a default is required. ``models``: the collision models the case offers. ``weights``:
    it takes ``--particles-per-parcel`` (one value, or one per species)."""

    name: str
    build: object
    doc: str = ""
    options: object = None
    summary: object = None
    check: object = None
    observers: object = None
    report: object = None
    finish: object = None
    defaults: dict = field(default_factory=dict)
    models: tuple = ("none", "ktgf", "surrogate", "surrogate-paper", "dem")
    weights: bool = True
    gas_snapshots: bool = True

    # ------------------------------------------------------------------ the parser
    def parser(self) -> argparse.ArgumentParser:
        first = (self.doc or self.name).strip().split("\n\n")[0]
        parser = _Parser(prog=self.name, description=first,
                         epilog="Bad input: one line 'hel-warp: error: ...' and exit code 2, nothing written; a "
                                "failed physical check: exit code 1.")
        self.add_arguments(parser)
        return parser

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        """Every option of the case (its own and the shared ones) on ``parser``, in the help's groups."""
        groups = SimpleNamespace(**{g: parser.add_argument_group(f"{g} options") for g in GROUPS})
        d = self.defaults
        if self.options is not None:
            self.options(groups)
        physics, numerics, output, advanced, case = (groups.physics, groups.numerics, groups.output,
                                                     groups.advanced, groups.case)
        physics.add_argument("--collisions", choices=self.models, required="collisions" not in d,
                             default=d.get("collisions"), help="collision model" + _default(d, "collisions"))
        physics.add_argument("--model", default=None,
                             help="surrogate model directory (hel-warp train --out); default for surrogate: one "
                                  "built for this flow's particles on first use and cached")
        if self.weights:
            physics.add_argument("--particles-per-parcel", default=d.get("particles_per_parcel", "1"),
                                 help="real particles per parcel: W, or W1,W2 per species (default "
                                      f"{d.get('particles_per_parcel', 1)})")
        physics.add_argument("--particle-spin", action="store_true",
                             help="surrogate: particle-particle collisions at the contact point, the spins turned")
        numerics.add_argument("--dt", type=finite_float, required="dt" not in d, default=d.get("dt"),
                              help="time step, s" + _default(d, "dt"))
        numerics.add_argument("--detection", choices=("swept", "overlap", "cell"), default=None,
                              help="surrogate pair detection: swept (continuous; default at one particle per "
                                   "parcel), overlap (the paper's end-of-step test), cell (stochastic per collision "
                                   "cell; default for weighted parcels)")
        case.add_argument("--seed", type=int, default=d.get("seed", 0), help="seed of the fills, injectors and "
                                                                             "collision cells (default 0)")
        output.add_argument("--out", required="out" not in d, default=d.get("out"),
                            help="run directory (refused if it exists: --overwrite or --resume)" + _default(d, "out"))
        output.add_argument("--end-time", type=finite_float, required="end_time" not in d, default=d.get("end_time"),
                            help="simulated time to reach, s" + _default(d, "end_time"))
        output.add_argument("--output-interval", type=finite_float, default=d.get("output_interval"),
                            help="time between snapshots (particles, gas, VTK), s (default: "
                                 f"{d.get('output_interval', 'a tenth of --end-time')})")
        output.add_argument("--checkpoint-interval", type=finite_float, default=None,
                            help="time between checkpoints, s (default: at the snapshots, at most one a minute of "
                                 "wall clock; the first and last step always)")
        mode = output.add_mutually_exclusive_group()
        mode.add_argument("--overwrite", action="store_true", help="replace an existing run directory")
        mode.add_argument("--resume", action="store_true", help="continue an existing run directory from its last "
                                                                "checkpoint (bit for bit)")
        output.add_argument("--no-vtk", action="store_true", help="write run.zarr only")
        output.add_argument("--no-pictures", action="store_true",
                            help="skip the case's pictures at the end (the members of a large ensemble: ~1 s each)")
        output.add_argument("--no-gas-snapshots", action="store_true", help="no gas cell fields at the snapshots")
        output.add_argument("--json", action="store_true", help="print the summary as one JSON object (last line)")
        output.add_argument("--no-progress", action="store_true", help="no progress bar")
        output.add_argument("--collision-events", metavar="PATH", default=None,
                            help="save every collision of every step to PATH (.npz; dem contact onsets or the "
                                 "surrogate's resolved collisions)")
        advanced.add_argument("--device", default="cpu", help="Warp device: cpu or cuda (default cpu)")
        advanced.add_argument("--read-back", choices=("auto", "step", "output"), default="auto",
                              help="when the host reads the device: 'step' (each step checks itself), 'output' "
                                   "(a steady step reads nothing; NaN and solver failures reported at the next "
                                   "output), 'auto': output on cuda, step on cpu (default). The same results")
        advanced.add_argument("--force", action="store_true",
                              help="use a surrogate trained for other particles (refused otherwise)")
        advanced.add_argument("--cell-coarsen", type=int, default=None,
                              help="cell detection: grid cells per collision cell and axis (default: the smallest "
                                   "that keeps a weighted pair from saturating)")
        advanced.add_argument("--cell-cfl", type=finite_float, default=None,
                              help="cell detection: largest path of a parcel per collision sub-step, cell edges "
                                   "(default 1)")
        advanced.add_argument("--cell-approaching", action=argparse.BooleanOptionalAction, default=None,
                              help="cell detection: collisions only between parcels that approach (default: on "
                                   "above one particle per parcel)")
        advanced.add_argument("--no-packing-stress", action="store_true",
                              help="cell detection: without the MP-PIC packing stress of dense regions")

    # ------------------------------------------------------------------ the run
    def main(self, argv=None, *, progress: bool | None = None) -> int:
        """Run the case with the options ``argv`` (default: ``sys.argv[1:]``); returns the exit code."""
        parser = self.parser()
        args = parser.parse_args(argv)
        try:
            return self.run(args, progress=progress)
        except (HelWarpError, RuntimeError) as exc:
            from hel_warp.cli import refused

            return refused(exc)

    def __call__(self, argv=None) -> int:
        return self.main(argv)

    def settings(self, args, flow):
        """The run's :class:`~hel_warp.case.build.Settings` from the shared options (checked here)."""
        from hel_warp.case.build import Settings

        if args.end_time is None:
            raise ConfigError("give --end-time (the simulated time to reach, s)")
        if not args.dt > 0:
            raise ConfigError(f"--dt must be > 0 s (got {args.dt:g})")
        if not args.end_time > 0:
            raise ConfigError(f"--end-time must be > 0 s (got {args.end_time:g})")
        if args.end_time < args.dt * (1.0 - 1e-9):
            raise ConfigError(f"--end-time {args.end_time:g} s is shorter than one step (--dt {args.dt:g} s), so the "
                              "run would take no step; give an end time of at least one step")
        for name in ("output_interval", "checkpoint_interval"):
            value = getattr(args, name)
            if value is not None and not value > 0:
                raise ConfigError(f"--{name.replace('_', '-')} must be > 0 s (got {value:g})")
        if args.seed < 0:
            raise ConfigError(f"--seed must be >= 0 (got {args.seed})")
        name = args.collisions
        weights = [s.weight for s in flow.species_list]
        detection = args.detection
        if detection is not None and name != "surrogate":
            raise ConfigError(f"--detection is a surrogate option (got --collisions {name}); surrogate-paper keeps "
                              "the paper's overlap test")
        if args.particle_spin and name != "surrogate":
            raise ConfigError(f"--particle-spin turns the surrogate's collisions at the contact point; --collisions "
                              f"{name} does not use it")
        defaults = flow.collision_defaults.get(name, {})
        auto_cell = detection is None and defaults.get("detection") in (None, "cell") and max(weights) > 1
        uses_cell = name == "surrogate" and (detection == "cell" or defaults.get("detection") == "cell" or auto_cell)
        cell = dict(defaults.get("cell") or {})
        for flag, key, value in (("--cell-coarsen", "coarsen", args.cell_coarsen), ("--cell-cfl", "cfl", args.cell_cfl),
                                 ("--[no-]cell-approaching", "approaching", args.cell_approaching),
                                 ("--no-packing-stress", "packing_stress", False if args.no_packing_stress else None)):
            if value is None:
                continue
            if not uses_cell:
                raise ConfigError(f"{flag} is an option of the surrogate's cell detection (give --detection cell or "
                                  "weighted parcels)")
            cell[key] = value
        if args.cell_coarsen is not None and args.cell_coarsen < 1:
            raise ConfigError(f"--cell-coarsen must be >= 1 grid cell (got {args.cell_coarsen})")
        if args.cell_cfl is not None and not args.cell_cfl > 0:
            raise ConfigError(f"--cell-cfl must be > 0 cell edges per sub-step (got {args.cell_cfl})")
        strategy = {}
        if detection is not None:
            strategy["detection"] = detection
        if cell:
            strategy["cell"] = cell
        if args.collision_events and name in ("none", "ktgf"):
            raise ConfigError(f"--collision-events records the dem and surrogate collisions; --collisions {name} "
                              "resolves none")
        return Settings(collisions=name, dt=float(args.dt), seed=int(args.seed), device=args.device,
                        model=args.model, strategy=strategy, particle_spin=bool(args.particle_spin),
                        particle_contacts=not getattr(args, "no_particle_contacts", False),
                        read_back=getattr(args, "read_back", "auto"))

    def prepare_out(self, args) -> str:
        """'new' or 'resume'; refuses an existing run directory without --overwrite / --resume (nothing written)."""
        path = Path(args.out)
        if not path.exists():
            if args.resume:
                raise ConfigError(f"--resume: run directory {args.out} does not exist")
            return "new"
        if args.resume:
            if not ((path / "checkpoint.npz").exists() or (path / "checkpoint.prev.npz").exists()):
                raise ConfigError(f"--resume: {args.out} holds no checkpoint; rerun with --overwrite")
            return "resume"
        if not args.overwrite:
            raise ConfigError(f"run directory {args.out} exists; pass --overwrite to replace it or --resume to "
                              "continue it")
        if path.is_dir() and any(path.iterdir()) and not ((path / "run.zarr").exists() or (path / SUMMARY).exists()):
            raise ConfigError(f"{args.out} is not a run directory (no run.zarr); --overwrite only replaces run "
                              "directories")
        return "new"

    def run(self, args, *, progress: bool | None = None) -> int:
        from hel_warp.case.build import build as build_simulation
        from hel_warp.case.models import check_model, model_for, surrogate_domain
        from hel_warp.case.probes import ProbeRecorder
        from hel_warp.runs.run import Run as RunLoop, RunConfig, check_device, load_kernels

        t_setup = time.perf_counter()
        check_device(args.device)
        flow = self.build(args)
        if self.weights and hasattr(args, "particles_per_parcel"):
            _check_weights(args.particles_per_parcel, flow)
        settings = self.settings(args, flow)
        mode = self.prepare_out(args)
        say = (lambda text: print(text, file=sys.stderr)) if args.json else print
        model_meta = None
        if settings.collisions in ("surrogate", "surrogate-paper"):
            if settings.model is None:
                if settings.collisions == "surrogate-paper":
                    raise ConfigError("--collisions surrogate-paper needs --model MODEL_DIR (a paper-form model); "
                                      "only the contact form is built automatically")
                from dataclasses import replace

                settings = replace(settings, model=model_for(flow.species_list, announce=say))
            model_meta = check_model(settings.model, flow.species_list, force=args.force)
        observers = list(self.observers(args, flow) if self.observers else [])
        recorder = ProbeRecorder(list(flow.probes), settings.dt) if flow.probes else None
        if recorder is not None:
            observers.append(recorder)
        show = (progress if progress is not None else not args.no_progress) and not args.json
        pour = None
        if show and any(f.settles for f in flow.fills):
            from tqdm import tqdm

            pour = tqdm(unit="s", desc=f"{self.name}: pouring the bed", bar_format="{desc} {n:.2f} s of DEM",
                        file=sys.stderr)
        sim = build_simulation(flow, settings, observers=observers,
                             progress=(lambda t: pour.update(t - pour.n)) if pour is not None else None)
        if pour is not None:
            pour.close()
        for observer in observers:  # what an observer needs of the built simulation (and its record at t = 0)
            if hasattr(observer, "bind"):
                observer.bind(sim)
        kernel_load_s = load_kernels(settings.device)
        warm_steps = 0 if mode == "resume" else sim.warm_up()
        setup_s = time.perf_counter() - t_setup
        out = Path(args.out)
        if mode == "new" and out.exists():
            shutil.rmtree(out) if out.is_dir() else out.unlink()
        output_interval = args.output_interval or max(args.end_time / 10.0, settings.dt)
        run_config = RunConfig(out_dir=str(out), end_time=float(args.end_time), output_interval=float(output_interval),
                               checkpoint_interval=args.checkpoint_interval, vtk=not args.no_vtk,
                               gas_snapshots=self.gas_snapshots and flow.gas is not None and not args.no_gas_snapshots)
        case_config = {"case": self.name, **flow.attrs, "options": _case_options(args)}
        loop = RunLoop(sim.solver, run_config, case_config=case_config, restart=mode == "resume")
        events = None
        if args.collision_events:
            from hel_warp.case.events import EventRecorder

            events = EventRecorder(sim.solver)
        bar = None
        if show:
            from tqdm import tqdm

            bar = tqdm(total=loop.total_steps, initial=sim.solver.step_count, unit="step", file=sys.stderr,
                       desc=f"{self.name} {settings.collisions} dt={settings.dt:g}", mininterval=0.5)

        def callback(solver):
            if events is not None:
                events.add(solver)
            if bar is not None:
                bar.update(1)

        start = time.perf_counter()
        taken = loop.run(progress=callback)
        loop_s = time.perf_counter() - start
        if bar is not None:
            bar.close()
        if events is not None:
            events.save(args.collision_events)
        import zarr

        root = zarr.open_group(str(out / "run.zarr"), mode="r+")
        if recorder is not None:
            recorder.write(root)
        result = Run(sim=sim, runner=loop, probes=recorder, args=args, out=out, steps_this_call=taken, loop_s=loop_s)
        errors = list(self.check(result) if self.check else [])
        summary = self.standard_summary(result, settings, kernel_load_s, setup_s, warm_steps, model_meta)
        if self.summary is not None:
            summary.update(self.summary(result))
        summary["check_errors"] = errors
        from hel_warp.runs.io import _jsonable

        summary = _jsonable(summary)
        root.attrs["summary"] = summary
        if self.finish is not None and not getattr(args, "no_pictures", False):
            self.finish(result, summary)
        with open(out / SUMMARY, "w") as fh:
            json.dump(summary, fh, indent=1)
        if args.json:
            print(json.dumps(summary))
        else:
            line = self.report(result, summary) if self.report else _report_line(self.name, summary, out)
            print(line)
        for e in errors:
            print(f"{self.name}: check failed: {e}", file=sys.stderr)
        return 1 if errors else 0

    def standard_summary(self, run: Run, settings, kernel_load_s: float, setup_s: float, warm_steps: int,
                         model_meta) -> dict:
        """The figures every case reports (the case's ``summary`` adds its own)."""
        sim = run.sim
        solver = sim.solver
        step_wall = run.series("timing_step")
        wall = float(np.sum(step_wall)) if step_wall is not None else 0.0
        steps = int(solver.step_count)
        parcels = int(solver.pool.particles.alive.numpy().sum())
        weights = solver.pool.particles.weight.numpy()[solver.pool.particles.alive.numpy().astype(bool)]
        counts = {}
        import zarr

        series = zarr.open_group(str(run.out / "run.zarr"), mode="r")["series"]
        for name, arr in series.arrays():
            if name.startswith("collisions_"):
                total = np.sum(arr[...])
                counts[name[len("collisions_"):]] = float(total) if arr.dtype.kind == "f" else int(total)
        timed_steps = len(step_wall) if step_wall is not None else 0
        summary = {
            "case": self.name, "collision_model": settings.collisions, "dt": settings.dt, "seed": settings.seed,
            "device": settings.device, "end_time": float(run.args.end_time), "simulated_time": float(solver.time),
            "steps": steps, "status": "complete" if steps >= run.runner.total_steps else "running",
            "particles": float(np.sum(weights)), "parcels": parcels,
            "particles_per_parcel": sorted({float(s.weight) for s in sim.flow.species_list}),
            "fluid_cells": sim.fluid_cells, "wall_clock_s": wall,
            "parcel_steps_per_second": (parcels * timed_steps / wall) if wall > 0 else None,
            "wall_clock_with_output_s": run.loop_s, "setup_wall_clock_s": setup_s, "kernel_load_s": kernel_load_s,
            "warmup_steps": warm_steps, "collision_totals": counts, "notes": list(sim.notes),
            "model": settings.model,
        }
        if model_meta is not None:
            summary["model_metadata"] = {k: model_meta.get(k) for k in ("form", "dataset_hash", "defaults")}
        if getattr(solver, "injected", None) is not None and hasattr(solver, "config") and \
                hasattr(solver.config, "injectors"):
            summary["injected"] = int(sum(e["count"] for e in solver.injected()))
            summary["removed"] = int(solver.pool.removed_count())
        return summary


def _default(defaults: dict, key: str) -> str:
    return f" (default {defaults[key]})" if key in defaults and defaults[key] is not None else ""


def _case_options(args) -> dict:
    """The options a resume must repeat (everything but the run-loop ones it may change)."""
    skip = {"out", "overwrite", "resume", "end_time", "output_interval", "checkpoint_interval", "no_vtk", "json",
            "no_pictures", "no_progress", "collision_events", "no_gas_snapshots", "device"}
    # "_name": what a case keeps on args for itself (the rig's validated config), not an option
    return {k: v for k, v in sorted(vars(args).items()) if k not in skip and not k.startswith("_")}


def _check_weights(value, flow) -> None:
    from hel_warp.collisions.mixture import species_weights

    species_weights(value, max(len(flow.species_list), 1))


def weights_of(args, species: int = 1) -> tuple:
    """``--particles-per-parcel`` as one integer weight per species (``hel_warp.collisions.mixture.species_weights``)."""
    from hel_warp.collisions.mixture import species_weights

    return species_weights(getattr(args, "particles_per_parcel", "1"), species)


def _report_line(name: str, summary: dict, out: Path) -> str:
    return (f"{name}: {summary['collision_model']}, dt = {summary['dt']:g} s, {summary['steps']} steps, t = "
            f"{summary['simulated_time']:.4g} s, {summary['parcels']} parcels, step wall clock "
            f"{summary['wall_clock_s']:.2f} s -> {out}")

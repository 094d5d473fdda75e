"""The run loop of a HEL case: output directory, snapshots, per-step series, checkpoints, restart.

One run directory ``DIR``::

    DIR/run.zarr/                        zarr v3 group; attrs ``config`` (resolved: HEL config, run
                                         settings, case arguments), ``code_version``, ``created``,
                                         ``snapshot_count``, ``gas_snapshot_count``, ``kernel_load_s``
                                         (Warp compilation / module loading before the timed steps, s,
                                         summed over restarts; never part of ``series/timing_*``)
        snapshots/000000/{name}          live parcels at an output time: x, v (n, 3); radius, density,
                                         weight (n,); stream, particle_id (n,); attrs time, step, count
                                         (the layout of ``hel_warp.runs.io``, so ``io.read_snapshot`` reads it)
        time, step                       (n_snapshots,) float64 / int64
        gas/000000/{name}                cell fields at the same output time: cell_velocity (nx,ny,nz,3),
                                         cell_pressure, cell_eps_s, cell_eps_f (nx,ny,nz); attrs time, step
        series/step, series/time         one entry per step
        series/timing_{sub_step}         wall clock of each sub-step of ``HelSolver.step``, s
        series/timing_step               wall clock of the whole step, s
        series/collisions_{name}         the strategy's ``counts()`` per step (if it has one): int64, or
                                         float64 for a weight-aware count (``collisions`` of parcels)
        series/wall_hits                 parcel-wall reflections so far (at output steps; series/output_step)
    DIR/vtk/particles_0000.vtp, particles.pvd   parcels (``hel_warp.runs.io.write_vtp`` / ``write_pvd``)
    DIR/vtk/gas_0000.vti, gas.pvd               cell fields on the grid (pyvista ImageData, cell data)
    DIR/checkpoint.npz                   everything ``HelSolver.state()`` holds + the resolved config
    DIR/checkpoint.prev.npz              the checkpoint before it

Checkpoints are written atomically (a temporary file, flushed and fsynced, then renamed), so the
last good one survives a crash at any moment. ``Run(..., restart=True)`` loads the checkpoint,
cuts ``run.zarr`` back to its step (snapshots and series written after it are dropped) and
continues; the continued run is bitwise identical to an uninterrupted one (tested).

Failure handling: a ``HelWarpError`` inside a step (e.g. the gas pressure solve does not converge)
or NaN/inf found by the device check at an output step stops the run with a ``HelWarpError`` that
says what to change and where the last good checkpoint is; no snapshot or checkpoint of the bad
state is written. Per-step series are buffered on the host and flushed at output steps.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
import os
import time as _time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hel_warp.errors import ConfigError, HelWarpError, require_positive
from hel_warp.runs.io import _jsonable

CHECKPOINT = "checkpoint.npz"
CHECKPOINT_WALL_S = 60.0
"""Default least wall clock between two checkpoints when no ``--checkpoint-interval`` is given, s."""
CHECKPOINT_PREV = "checkpoint.prev.npz"
GAS_FIELDS = ("cell_velocity", "cell_pressure", "cell_eps_s", "cell_eps_f")
PARTICLE_FIELDS = ("x", "v", "radius", "density", "weight", "stream", "particle_id")


@dataclass(frozen=True, kw_only=True)
class RunConfig:
    """Settings of the run loop (outputs, checkpoints)."""

    out_dir: str
    """Run directory (created)."""
    end_time: float
    """Simulated time to reach, s."""
    output_interval: float
    """Time between snapshots (particles, gas, VTK) and NaN checks, s; rounded to whole steps."""
    checkpoint_interval: float | None = None
    """Time between checkpoints, s; rounded to a multiple of the output steps. None: at the output steps, but no
    sooner than ``checkpoint_wall_s`` of wall clock after the last one (the first and the last step always)."""
    checkpoint_wall_s: float = CHECKPOINT_WALL_S
    """With ``checkpoint_interval`` None: the least wall clock between two checkpoints, s (0: one at every
    output). A checkpoint (state, fsync) and the per-step series it flushes cost ~0.1 s each, as much as a rig
    step of 188 parcels at dt = 1e-3 s; a crash loses at most this much work."""
    vtk: bool = True
    """Also write VTK files (pyvista)."""
    gas_snapshots: bool = True
    """Write the cell fields at output times."""

    def __post_init__(self):
        require_positive("end_time", self.end_time, "s")
        require_positive("output_interval", self.output_interval, "s")
        if self.checkpoint_interval is not None:
            require_positive("checkpoint_interval", self.checkpoint_interval, "s")
        if not (math.isfinite(self.checkpoint_wall_s) and self.checkpoint_wall_s >= 0.0):
            raise ConfigError(f"checkpoint_wall_s must be >= 0 s (got {self.checkpoint_wall_s!r})")


def add_run_arguments(parser) -> None:
    """The run options every HEL case shares: --out, --end-time, --output-interval, --checkpoint-interval,
    --restart, --no-vtk, --device."""
    from hel_warp.errors import finite_float

    parser.add_argument("--out", required=True, help="run directory")
    parser.add_argument("--end-time", type=finite_float, required=True, help="simulated time, s")
    parser.add_argument("--output-interval", type=finite_float, required=True, help="time between snapshots, s")
    parser.add_argument("--checkpoint-interval", type=finite_float, default=None,
                        help=f"time between checkpoints, s (default: at the snapshots, at most one per "
                             f"{CHECKPOINT_WALL_S:g} s of wall clock; the first and last step always)")
    parser.add_argument("--restart", action="store_true", help="continue from OUT/checkpoint.npz")
    parser.add_argument("--no-vtk", action="store_true", help="write run.zarr only")
    parser.add_argument("--device", default="cpu", help="Warp device: cpu or cuda (default cpu)")


def check_device(name: str) -> str:
    """``name`` if Warp has that device here (``cpu``, ``cuda``, ``cuda:N``), else a ConfigError saying to use
    ``--device cpu`` (asked for ``cuda`` on a machine without a GPU, Warp raises a RuntimeError deep in the first
    allocation)."""
    from hel_warp._warp import init_warp, start_warp

    if not isinstance(name, str) or not (name == "cpu" or name == "cuda" or name.startswith("cuda:")):
        raise ConfigError(f"--device must be cpu, cuda or cuda:N (got {name!r})")
    import warp as wp

    start_warp(cuda=name != "cpu")  # Warp's missing-driver line only where a CUDA device is asked for
    if name != "cpu" and not wp.is_cuda_available():
        raise ConfigError(f"--device {name}: Warp finds no CUDA device on this machine (no GPU or no driver); "
                          "use --device cpu")
    init_warp(name)  # cuda:N beyond the GPUs present: ConfigError naming --device cpu
    return name


CPU_ONLY_MODULES = ("kernels.swept_queue",)
"""Warp modules only a CPU device launches (the swept detection's serial queue; a CUDA device resolves in rounds):
``load_kernels`` neither imports nor builds them for CUDA, where NVRTC took over ten minutes on the queue."""


def kernel_modules(device) -> list:
    """The Warp modules ``load_kernels`` builds for ``device`` (a ``wp.Device``): every imported one with Warp code,
    less ``CPU_ONLY_MODULES`` on CUDA."""
    import warp as wp

    registry = getattr(getattr(wp, "_src", None), "context", None)
    modules = getattr(registry, "user_modules", None)
    if modules is None:  # another Warp layout: every module (force_load's default)
        return None
    return [m for name, m in modules.items() if not (device.is_cuda and name in CPU_ONLY_MODULES)]


def import_kernel_modules(cpu: bool = True) -> None:
    """Import every module of ``kernels/`` (less ``CPU_ONLY_MODULES`` when ``cpu`` is False), so that Warp knows
    their modules (``load_kernels``; ``scripts/gpu_kernel_cache.py`` compiles them for a GPU)."""
    import importlib
    import pkgutil

    import kernels

    for info in pkgutil.iter_modules(kernels.__path__):
        name = f"kernels.{info.name}"
        if cpu or name not in CPU_ONLY_MODULES:
            importlib.import_module(name)


def plain_atomics_without_cuda() -> None:
    """On a machine without CUDA, compile the modules that ask for Warp's deterministic atomics
    (``DeterministicMode.RUN_TO_RUN``: ``kernels.gas``, ``kernels.deposit``, ``kernels.free_flight``) with plain ones.

    The CPU device runs a kernel's threads one after another, so its atomic sums are in index order either way and
    the results are the same to the bit (the reduced rig's and the cooling box's run.zarr arrays compared). What the
    mode costs on the CPU is start-up: Warp rebuilds such a module's code in every process that loads it from the
    kernel cache, ~7 s of a tiny run's ~10 s (``python -m cProfile cases/homogeneous_cooling.py ...``), which an
    ensemble of a thousand tiny members pays a thousand times. A machine with a GPU keeps the mode everywhere, so that
    a process that runs on both devices never launches a CUDA kernel without it."""
    import warp as wp

    if not hasattr(wp.config, "DeterministicMode"):
        return
    plain = wp.config.DeterministicMode.NOT_GUARANTEED
    registry = getattr(getattr(wp, "_src", None), "context", None)
    for name in list(getattr(registry, "user_modules", None) or {}):
        if wp.get_module_options(name).get("deterministic", plain) != plain:
            wp.set_module_options({"deterministic": plain}, module=name)


def load_kernels(device) -> float:
    """Compile (or load from Warp's kernel cache) every Warp module of ``kernels/`` and any other imported module
    with Warp code, on ``device`` (None: every device), less ``CPU_ONLY_MODULES`` on CUDA; returns the seconds it
    took.

    Warp compiles a module at its first launch, so without this the first steps of a run on a cold cache carry
    the compilation (on a fresh machine the first model run looked 3x slower than the next); ``Run.run`` calls it
    before it times any step and reports the time apart (``kernel_load_s``)."""
    import warp as wp

    start = _time.perf_counter()
    devices = wp.get_devices() if device is None else [wp.get_device(device)]
    import_kernel_modules(cpu=any(not d.is_cuda for d in devices))
    if wp.get_cuda_device_count() == 0:
        plain_atomics_without_cuda()
    for d in devices:
        wp.force_load(device=d, modules=kernel_modules(d))
    return _time.perf_counter() - start


def run_config_from_args(args) -> RunConfig:
    return RunConfig(out_dir=args.out, end_time=args.end_time, output_interval=args.output_interval,
                     checkpoint_interval=args.checkpoint_interval, vtk=not args.no_vtk)


def resolved_config(solver, run_config: RunConfig, case_config: dict | None = None) -> dict:
    """The configuration of a run as JSON-safe values (HEL config, strategy, grid, run settings, case)."""
    strategy = solver.collision
    strategy_config = getattr(strategy, "config", None)
    return _jsonable({"hel": solver.config, "collision": {"name": strategy.name, "config": strategy_config},
                      "grid": solver.grid, "gas": getattr(solver.gas_solver, "config", None),
                      "capacity": solver.pool.capacity, "run": run_config, "case": case_config or {}})


def _physics_fingerprint(config: dict) -> str:
    """The part of the resolved config a restart must match (everything but the run settings)."""
    return json.dumps({k: v for k, v in config.items() if k != "run"}, sort_keys=True)


# ---------------------------------------------------------------------- checkpoints

def write_checkpoint(out_dir, state: dict, config: dict) -> Path:
    """Atomically write ``state`` (+ config) to ``out_dir/checkpoint.npz``; the previous one becomes
    ``checkpoint.prev.npz``."""
    out_dir = Path(out_dir)
    path, prev, tmp = out_dir / CHECKPOINT, out_dir / CHECKPOINT_PREV, out_dir / (CHECKPOINT + ".tmp")
    payload = dict(state)
    payload["meta/config"] = np.array(json.dumps(config, sort_keys=True))
    with open(tmp, "wb") as fh:
        np.savez(fh, **payload)
        fh.flush()
        os.fsync(fh.fileno())
    if path.exists():
        os.replace(path, prev)
    os.replace(tmp, path)
    return path


def read_checkpoint(out_dir) -> tuple[dict, dict, Path]:
    """(state, config, path) of the newest readable checkpoint in ``out_dir``."""
    out_dir = Path(out_dir)
    errors = []
    for name in (CHECKPOINT, CHECKPOINT_PREV):
        path = out_dir / name
        if not path.exists():
            continue
        try:
            with np.load(path, allow_pickle=False) as data:
                state = {k: data[k] for k in data.files}
        except Exception as err:  # a torn or foreign file: fall back to the previous one
            errors.append(f"{path}: {err}")
            continue
        config = json.loads(str(state.pop("meta/config")))
        return state, config, path
    detail = f" ({'; '.join(errors)})" if errors else ""
    raise ConfigError(f"no readable checkpoint in {out_dir}{detail}; run without --restart to start afresh")


# ---------------------------------------------------------------------- VTK of the grid

def write_grid_vti(path, grid, fields: dict[str, np.ndarray]) -> None:
    """Cell fields on the uniform grid as VTK ImageData (.vti); (nx,ny,nz[,3]) arrays as cell data."""
    import pyvista as pv

    nx, ny, nz = grid.shape
    image = pv.ImageData(dimensions=(nx + 1, ny + 1, nz + 1), spacing=(grid.spacing,) * 3, origin=grid.origin)
    for name, arr in fields.items():
        arr = np.asarray(arr)
        if arr.ndim == 4:  # vector: x fastest (VTK order), one column per component
            image.cell_data[name] = np.stack([arr[..., c].reshape(-1, order="F") for c in range(arr.shape[-1])],
                                             axis=1)
        else:
            image.cell_data[name] = arr.reshape(-1, order="F")
    image.save(str(path))


def _write_empty_vtp(path) -> None:
    import pyvista as pv

    pv.PolyData().save(str(path))


# ---------------------------------------------------------------------- the run

class Run:
    """Drives ``solver`` (a ``hel_warp.hel.HelSolver``) to ``config.end_time`` writing ``config.out_dir``.

    ``case_config``: the case's own settings (stored in the attrs). ``restart``: continue from the
    checkpoint in ``out_dir`` (the solver must be built with the same configuration; checked).
    """

    def __init__(self, solver, config: RunConfig, *, case_config: dict | None = None, restart: bool = False):
        import zarr

        from hel_warp import __version__

        self.solver = solver
        self.config = config
        self.out_dir = Path(config.out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.vtk_dir = self.out_dir / "vtk"
        dt = solver.config.dt
        self.total_steps = int(round(config.end_time / dt))
        if config.end_time < dt * (1.0 - 1e-9):
            raise ConfigError(f"--end-time {config.end_time:g} s is shorter than one step (dt = {dt:g} s), so the "
                              "run would take no step; give an end time of at least one step")
        self.kernel_load_s = 0.0
        """Seconds this Run spent compiling / loading Warp modules before the timed steps (:func:`load_kernels`)."""
        self.output_every = max(1, int(round(config.output_interval / dt)))
        interval = config.checkpoint_interval if config.checkpoint_interval is not None else config.output_interval
        self.checkpoint_every = self.output_every * max(1, int(round(interval / (self.output_every * dt))))
        self.resolved = resolved_config(solver, config, case_config)
        self._series: dict[str, list] = {}
        self._counts_log = _DeviceCountsLog(self.output_every)
        self._output_rows: dict[str, list] = {"output_step": [], "wall_hits": []}
        """Per-output series rows not yet written (flushed with the per-step ones at each checkpoint)."""
        self._checkpoint_step = None
        self._checkpoint_wall = None
        """perf_counter() of this Run's last checkpoint (None: none yet)."""
        store = self.out_dir / "run.zarr"
        if restart:
            state, saved, path = read_checkpoint(self.out_dir)
            if _physics_fingerprint(saved) != _physics_fingerprint(self.resolved):
                raise ConfigError(f"the checkpoint {path} was written with another configuration; restart with "
                                  "the same case options (only --end-time and output settings may change)")
            solver.set_state(state)
            self._checkpoint_step = solver.step_count
            if not store.exists():
                raise ConfigError(f"{store} is missing; a restart needs the run directory it was written in")
            self.root = zarr.open_group(str(store), mode="r+")
            self.root.attrs["config"] = self.resolved
            self._truncate(solver.step_count)
        else:
            self.root = zarr.open_group(str(store), mode="w")
            self.root.attrs.update({"config": self.resolved, "code_version": __version__,
                                    "created": _dt.datetime.now(_dt.timezone.utc).isoformat(),
                                    "snapshot_count": 0, "gas_snapshot_count": 0})
            for group in ("snapshots", "gas", "series"):
                self.root.create_group(group)
            self.root.create_array("time", shape=(0,), chunks=(1024,), dtype="float64")
            self.root.create_array("step", shape=(0,), chunks=(1024,), dtype="int64")
        if config.vtk:
            self.vtk_dir.mkdir(exist_ok=True)

    # ------------------------------------------------------------------ restart bookkeeping
    def _truncate(self, step: int) -> None:
        """Drop snapshots and series entries written after ``step`` (the checkpoint's)."""
        steps = self.root["step"][...]
        keep = int(np.searchsorted(steps, step, side="right"))
        for name in ("time", "step"):
            self.root[name].resize((keep,))
        for group_name, count_attr in (("snapshots", "snapshot_count"), ("gas", "gas_snapshot_count")):
            group = self.root[group_name]
            for key in list(group.group_keys()):
                if int(group[key].attrs["step"]) > step:
                    del group[key]
            self.root.attrs[count_attr] = len(list(group.group_keys()))
        series = self.root["series"]
        if "step" in series:
            keep_rows = int(np.searchsorted(series["step"][...], step, side="right"))
            for name, arr in list(series.arrays()):
                if name in ("output_step", "wall_hits"):
                    continue
                arr.resize((keep_rows,))
        if "output_step" in series:
            keep_out = int(np.searchsorted(series["output_step"][...], step, side="right"))
            series["output_step"].resize((keep_out,))
            series["wall_hits"].resize((keep_out,))

    # ------------------------------------------------------------------ outputs
    def _record_step(self, wall: float) -> None:
        s = self.solver
        row = {"step": np.int64(s.step_count), "time": np.float64(s.time), "timing_step": np.float64(wall)}
        row.update({f"timing_{name}": np.float64(t) for name, t in s.timings.items()})
        staged = None
        if getattr(s, "read_back", "step") == "output" and hasattr(s, "collision_count_arrays"):
            staged = s.collision_count_arrays()
        if staged is not None and self._counts_log.stage(row, *staged):
            return  # the row waits for its counts, copied on the device, until the next read (_drain_counts)
        self._drain_counts()
        self._append_row(row, s.collision_counts())

    def _drain_counts(self) -> None:
        """The rows whose collision counts wait on the device: one read, then into the series in step order."""
        for row, host, extras in self._counts_log.drain():
            self._append_row(row, self.solver.collision_counts_from(host, extras))

    def _append_row(self, row: dict, counts: dict) -> None:
        # integer counts stay integers; a weight-aware count (real collisions of parcels, min(w_i, w_j) each) is float
        row.update({f"collisions_{name}": (np.int64(c) if isinstance(c, (int, np.integer)) else np.float64(c))
                    for name, c in counts.items()})
        done = len(self._series.get("step", []))
        for name in set(self._series) - set(row):  # a count not reported this step: 0
            self._series[name].append(np.zeros((), dtype=np.asarray(self._series[name][0]).dtype)[()])
        for name, value in row.items():
            buffer = self._series.setdefault(name, [])
            buffer.extend([type(value)(0)] * (done - len(buffer)))  # first reported now: 0 before
            buffer.append(value)

    def _flush_series(self) -> None:
        """Append the buffered per-step rows (and the per-output ones). A count that a strategy reports only on some
        steps reads 0 on the others, so every per-step series stays as long as ``series/step``."""
        self._drain_counts()
        for name, values in self._output_rows.items():
            if values:
                self._append_series(name, np.asarray(values, np.int64))
                values.clear()
        series = self.root["series"]
        rows = len(self._series.get("step", []))
        if not rows:
            return
        before = series["step"].shape[0] if "step" in series else 0
        names = set(self._series) | {name for name, _ in series.arrays()}
        for name in sorted(names - {"output_step", "wall_hits"}):
            values = self._series.get(name, [])
            if name not in series:
                dtype = np.asarray(values).dtype if values else np.int64
                series.create_array(name, shape=(0,), chunks=(4096,), dtype=dtype)
            arr = series[name]
            if arr.shape[0] < before:
                arr.append(np.zeros(before - arr.shape[0], dtype=arr.dtype))
            padded = np.zeros(rows, dtype=arr.dtype)
            if values:
                padded[rows - len(values):] = np.asarray(values, dtype=arr.dtype)
            arr.append(padded)
        self._series = {}

    def _append_series(self, name: str, values: np.ndarray) -> None:
        series = self.root["series"]
        if name not in series:
            series.create_array(name, shape=(0,), chunks=(4096,), dtype=values.dtype)
        series[name].append(values)

    def write_output(self) -> None:
        """Snapshot of the live parcels and the gas cells (zarr + VTK); a host read, output steps only."""
        from hel_warp.runs.io import write_pvd, write_vtp

        s = self.solver
        index = int(self.root.attrs["snapshot_count"])
        p = s.pool.particles
        alive = p.alive.numpy().astype(bool)
        arrays = {name: getattr(p, name).numpy()[alive] for name in PARTICLE_FIELDS}
        group = self.root["snapshots"].create_group(f"{index:06d}")
        for name, arr in arrays.items():
            z = group.create_array(name, shape=arr.shape, chunks=(max(min(len(arr), 65536), 1),) + arr.shape[1:],
                                   dtype=arr.dtype)
            z[...] = arr
        group.attrs.update({"time": float(s.time), "step": int(s.step_count), "count": int(alive.sum())})
        self.root["time"].append(np.array([s.time], np.float64))
        self.root["step"].append(np.array([s.step_count], np.int64))
        self.root.attrs["snapshot_count"] = index + 1
        self._output_rows["output_step"].append(s.step_count)
        self._output_rows["wall_hits"].append(s.wall_hit_count())
        if self.config.gas_snapshots:
            gas_group = self.root["gas"].create_group(f"{index:06d}")
            fields = {name: getattr(s.gas, name).numpy() for name in GAS_FIELDS if hasattr(s.gas, name)}
            for name, arr in fields.items():
                z = gas_group.create_array(name, shape=arr.shape, chunks=arr.shape, dtype=arr.dtype)
                z[...] = arr
            gas_group.attrs.update({"time": float(s.time), "step": int(s.step_count)})
            self.root.attrs["gas_snapshot_count"] = index + 1
        if self.config.vtk:
            times = self.root["time"][...]
            if len(arrays["x"]):
                write_vtp(self.vtk_dir / f"particles_{index:04d}.vtp", arrays)
            else:  # io.write_vtp refuses empty arrays; no parcels yet (before injection)
                _write_empty_vtp(self.vtk_dir / f"particles_{index:04d}.vtp")
            write_pvd(self.vtk_dir / "particles.pvd",
                      [(float(t), f"particles_{k:04d}.vtp") for k, t in enumerate(times)])
            if self.config.gas_snapshots:
                write_grid_vti(self.vtk_dir / f"gas_{index:04d}.vti", s.grid, fields)
                write_pvd(self.vtk_dir / "gas.pvd", [(float(t), f"gas_{k:04d}.vti") for k, t in enumerate(times)])

    def checkpoint(self) -> Path:
        """Write the solver's state (and first the buffered series, so the store holds every row up to it)."""
        self._flush_series()
        path = write_checkpoint(self.out_dir, self.solver.state(), self.resolved)
        self._checkpoint_step = self.solver.step_count
        self._checkpoint_wall = _time.perf_counter()
        return path

    def _checkpoint_due(self) -> bool:
        """At an output step: ``checkpoint_interval``'s steps, or (None) ``checkpoint_wall_s`` after the last one."""
        if self.config.checkpoint_interval is not None:
            return self.solver.step_count % self.checkpoint_every == 0
        return (self._checkpoint_wall is None
                or _time.perf_counter() - self._checkpoint_wall >= self.config.checkpoint_wall_s)

    def _failure(self, what: str, err: Exception) -> HelWarpError:
        s = self.solver
        if self._checkpoint_step is None:
            kept = "no checkpoint was written yet"
        else:
            kept = (f"the last good checkpoint (step {self._checkpoint_step}) is kept in "
                    f"{self.out_dir / CHECKPOINT}; fix the cause and rerun with --restart")
        return HelWarpError(f"{what} at step {s.step_count} (t = {s.time:.6g} s): {err}; {kept}")

    # ------------------------------------------------------------------ the loop
    def run(self, *, progress=None) -> int:
        """Step to ``end_time``; returns the number of steps taken by this call."""
        s = self.solver
        taken = 0
        if s.step_count < self.total_steps:  # compile before the first timed step, and say how long it took
            took = load_kernels(s.pool.particles.device)
            self.kernel_load_s += took
            self.root.attrs["kernel_load_s"] = float(self.root.attrs.get("kernel_load_s", 0.0)) + took
        if s.step_count == 0 and self._checkpoint_step is None:
            self._output_and_checkpoint(force_checkpoint=True)
        try:
            while s.step_count < self.total_steps:
                start = _time.perf_counter()
                try:
                    s.step()
                except HelWarpError as err:
                    raise self._failure("the step failed", err) from err
                self._record_step(_time.perf_counter() - start)
                taken += 1
                if progress is not None:
                    progress(s)
                if s.step_count % self.output_every == 0 or s.step_count == self.total_steps:
                    self._output_and_checkpoint(force_checkpoint=s.step_count == self.total_steps)
        finally:  # however the loop ends, the store keeps the rows of the steps taken (a restart drops those
            self._flush_series()  # after its checkpoint)
        return taken

    def _output_and_checkpoint(self, *, force_checkpoint: bool) -> None:
        s = self.solver
        self._drain_counts()
        try:
            s.check_finite()
        except HelWarpError as err:
            raise self._failure("NaN/inf found", err) from err
        self.write_output()
        if force_checkpoint or self._checkpoint_due():
            self.checkpoint()


class _DeviceCountsLog:
    """Per-step collision counts kept on the device between two reads (``HelConfig.read_back`` 'output'): each
    step copies the strategy's count arrays into the next row of a buffer per dtype (device-to-device copies, no
    sync), and :meth:`drain` reads each buffer once. A change of arrays (the detection switched) or a full buffer
    drains first. The counts are the same bits a per-step read gives."""

    def __init__(self, rows: int):
        self.rows = max(1, int(rows))
        self.layout = None  # ((name, dtype, shape), ...) of the staged arrays
        self.buffers = {}  # dtype -> (flat device buffer, row width)
        self.offsets = {}  # name -> (dtype, offset in the row)
        self.pending = []  # (row dict, extras)
        self.device = None

    def stage(self, row: dict, arrays: dict, extras: dict) -> bool:
        """Copy ``arrays`` into the next row; False (nothing staged) for arrays off the device or not contiguous."""
        import warp as wp

        layout = tuple((name, a.dtype, tuple(a.shape)) for name, a in arrays.items())
        if any(not a.is_contiguous for a in arrays.values()):
            return False
        if layout != self.layout or len(self.pending) >= self.rows:
            if self.pending:
                return False  # the caller drains, then stages the next step afresh
            if layout != self.layout:
                self._allocate(arrays, layout)
        k = len(self.pending)
        for name, a in arrays.items():
            dtype, offset = self.offsets[name]
            buffer, width = self.buffers[dtype]
            wp.copy(buffer, a.flatten() if a.ndim > 1 else a, dest_offset=k * width + offset, count=a.size)
        self.pending.append((row, dict(extras)))
        return True

    def _allocate(self, arrays: dict, layout) -> None:
        import warp as wp

        widths, self.offsets = {}, {}
        for name, a in arrays.items():
            self.offsets[name] = (a.dtype, widths.get(a.dtype, 0))
            widths[a.dtype] = widths.get(a.dtype, 0) + a.size
        device = next(iter(arrays.values())).device
        self.buffers = {dtype: (wp.zeros(self.rows * width, dtype=dtype, device=device), width)
                        for dtype, width in widths.items()}
        self.layout = layout

    def drain(self) -> list:
        """[(row, {name: host array}, extras)] of the staged steps, in order (one read per dtype), emptied."""
        if not self.pending:
            return []
        host = {dtype: buffer.numpy().copy() for dtype, (buffer, _) in self.buffers.items()}
        shapes = {name: shape for name, _, shape in self.layout}
        out = []
        for k, (row, extras) in enumerate(self.pending):
            values = {}
            for name, (dtype, offset) in self.offsets.items():
                width = self.buffers[dtype][1]
                size = int(np.prod(shapes[name])) if shapes[name] else 1
                values[name] = host[dtype][k * width + offset:k * width + offset + size].reshape(shapes[name])
            out.append((row, values, extras))
        self.pending = []
        return out

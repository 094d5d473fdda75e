"""The collision data set: configurations (``surrogate.configurations``) run through the batched
binary DEM (``hel_warp.collisions.impact.simulate_pairs``) and stored in a zarr group, paper section 4.1.

Layout (``docs/file-formats.md`` "The collision data set"): arrays ``inputs`` (N, 14) float64,
``outputs`` (N, 15) float64, ``config_id`` (N,) int64, ``family`` (N,) int8, ``chunk_done``
(n_chunks,) bool, and the group attrs listed there.

Writing is chunk by chunk (``chunk_size`` rows, the zarr chunk of every row array, so a chunk
is whole files): compute, check (finite rows, ids in order), write the four row arrays, then
set ``chunk_done[k]`` (a file of its own; zarr's local store writes files atomically). A killed
run leaves at most one chunk written but not marked; the rerun recomputes every unmarked
chunk. Rows depend on ``(seed, k)`` only and every pair runs on its own thread of the DEM
kernel, so a resumed set is byte-identical to an uninterrupted one. ``dataset_hash`` (sha256
of the bytes of ``inputs`` then ``outputs``, little-endian float64, C order) is set when the
last chunk is done; ``load_dataset`` recomputes it and refuses a set that is incomplete or
whose bytes changed.

With a Dask scheduler address the chunks are computed by ``compute_chunk`` on the cluster's
workers (which need hel_warp installed) and written by the client, in completion order.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from hel_warp.errors import ConfigError, HelWarpError
from hel_warp.material import Material
from surrogate.configurations import (FAMILIES, GRAZING_MAX_OFFSET, Configurations, ConfigurationSpec, generate,
                                      paper_diameter_std)

INPUT_COLUMNS = ("v1x", "v1y", "v1z", "v2x", "v2y", "v2z", "d1", "d2", "rho1", "rho2", "nx", "ny", "nz", "offset")
SPIN_INPUT_COLUMNS = ("o1x", "o1y", "o1z", "o2x", "o2y", "o2z")
"""The spins before the impact (rad/s), after INPUT_COLUMNS in a set made with ``spin_fraction`` > 0."""
OUTPUT_COLUMNS = ("u1x", "u1y", "u1z", "u2x", "u2y", "u2z", "w1x", "w1y", "w1z", "w2x", "w2y", "w2z",
                  "contact_duration", "max_overlap", "max_normal_force")
CONTACT_MODELS = ("hertz", "linear")
DEFAULT_CHUNK_SIZE = 4096
FORMAT_VERSION = 1
ROW_ARRAYS = ("inputs", "outputs", "config_id", "family")
FINGERPRINT_MODULES = ("surrogate.configurations", "surrogate.dataset", "hel_warp.material", "hel_warp.collisions.impact",
                       "hel_warp.collisions.contact_law", "kernels.hertz")
"""Modules whose source decides the bytes of a data set (``code_fingerprint``)."""


@functools.lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """sha256 over the source files of ``FINGERPRINT_MODULES`` (first 16 hex digits).

    Stored in the attrs: a resume with changed configuration or DEM code would mix two versions
    of the physics in one set, so it is refused. Also returned by every chunk computed on a Dask
    worker, so a worker running other code is caught.
    """
    import importlib.util

    digest = hashlib.sha256()
    for name in FINGERPRINT_MODULES:
        spec = importlib.util.find_spec(name)
        if spec is None or spec.origin is None:
            digest.update(f"{name}:missing".encode())
            continue
        digest.update(name.encode() + b"\0" + Path(spec.origin).read_bytes())
    return digest.hexdigest()[:16]

PairRunner = Callable[[Configurations, "DatasetSpec"], np.ndarray]
"""``runner(configs, spec) -> outputs`` (n, 15) float64 in ``OUTPUT_COLUMNS`` order."""


class DatasetError(HelWarpError):
    """A data set that cannot be written, resumed or loaded; the message says what to do."""


@dataclass(frozen=True, kw_only=True)
class DatasetSpec:
    """Everything that determines the bytes of a data set (stored in the group attrs)."""

    samples: int
    """Number of configurations N."""
    seed: int
    """Seed of the configuration generator (non-negative integer)."""
    configurations: ConfigurationSpec
    """How configurations are drawn."""
    material: Material = field(default_factory=Material)
    """Particle material (elastic constants, restitution, friction)."""
    contact_model: str = "hertz"
    """DEM normal contact law: "hertz" or "linear"."""
    chunk_size: int = DEFAULT_CHUNK_SIZE
    """Rows per chunk (one DEM launch batch, one zarr chunk, one resume unit)."""
    dt_factor: float = 0.5
    """DEM time step as a fraction of the eq. (12) stable step of the pair's smaller sphere, in (0, 1].
    The runner's restitution error is O((dt/t_c)^2); measured on 4096 central Hertz impacts of
    315 um spheres (approach speeds up to 40 m/s): largest |e_out/e - 1| = 1.0 % at factor 1,
    0.29 % at 0.5 (linear model: 0.23 %, 0.07 %), for ~10-20 % more run time."""

    def __post_init__(self) -> None:
        if not isinstance(self.samples, (int, np.integer)) or self.samples < 1:
            raise ConfigError(f"samples must be a positive integer (got {self.samples!r})")
        if not isinstance(self.seed, (int, np.integer)) or not 0 <= self.seed < 2**63:
            raise ConfigError(f"seed must be a non-negative integer (got {self.seed!r})")
        if not isinstance(self.chunk_size, (int, np.integer)) or self.chunk_size < 1:
            raise ConfigError(f"chunk size must be a positive integer (got {self.chunk_size!r})")
        if not (isinstance(self.dt_factor, (int, float)) and 0.0 < self.dt_factor <= 1.0):
            raise ConfigError(f"DEM time-step factor must lie in (0, 1] (got {self.dt_factor!r})")
        if self.contact_model not in CONTACT_MODELS:
            raise ConfigError(f"contact model must be one of {', '.join(CONTACT_MODELS)} (got {self.contact_model!r})")

    @property
    def input_columns(self) -> tuple:
        """INPUT_COLUMNS, then SPIN_INPUT_COLUMNS for a spinning set."""
        return INPUT_COLUMNS + (SPIN_INPUT_COLUMNS if self.configurations.spin_fraction > 0 else ())

    @property
    def n_chunks(self) -> int:
        return math.ceil(self.samples / self.chunk_size)

    def rows(self, k: int) -> tuple[int, int]:
        """Row range ``[start, stop)`` of chunk ``k``."""
        start = k * self.chunk_size
        return start, min(self.samples, start + self.chunk_size)

    def attrs(self) -> dict:
        """The group attrs that identify the set (all but ``dataset_hash``), JSON-normalised."""
        from hel_warp import __version__

        cfg = self.configurations
        attrs = {
            "format_version": FORMAT_VERSION,
            "material": self.material.as_dict(),
            "contact_model": self.contact_model,
            "seed": int(self.seed),
            "samples": int(self.samples),
            "chunk_size": int(self.chunk_size),
            "dt_factor": float(self.dt_factor),
            "n_chunks": int(self.n_chunks),
            "diameter_mean": cfg.diameter_mean,
            "diameter_std": cfg.diameter_std,
            "density": cfg.density_mean,
            "density_std": cfg.density_std,
            "configuration": cfg.as_dict(),
            "families": list(FAMILIES),
            "code_version": __version__,
            "code_fingerprint": code_fingerprint(),
            "input_columns": list(self.input_columns),
            "output_columns": list(OUTPUT_COLUMNS),
        }
        return json.loads(json.dumps(attrs))


DEFAULT_GRAZING_FRACTION = 0.3
"""Share of grazing rows when the caller sets none and the central share leaves room for it."""


def make_spec(*, samples: int, seed: int, diameter: float, diameter_std: float | None = None,
              density_std: float = 0.0, material: Material | None = None, contact_model: str = "hertz",
              chunk_size: int = DEFAULT_CHUNK_SIZE, central_fraction: float = 0.1,
              grazing_fraction: float | None = None, grazing_angle: float = 60.0, max_offset: float = GRAZING_MAX_OFFSET,
              slow_fraction: float = 0.3, min_relative_speed: float = 0.01, min_normal_speed: float = 1e-3,
              speed_max: float = 20.0, touch_steps: float = 2.0, dt_factor: float = 0.5,
              mixture_diameters: tuple = (), mixture_diameter_stds: tuple | None = None,
              mixture_mass_fractions: tuple = (), spin_fraction: float = 0.0, spin_ratio: float = 1.5) -> DatasetSpec:
    """A ``DatasetSpec`` from user options.

    Defaults cover every impact the engine meets (``surrogate.configurations``: grazing rows up to
    89.8 deg, relative speeds down to 0.01 m/s, normal approach >= 1e-3 m/s); ``**surrogate.configurations.paper_spec_options()``
    gives the earlier paper-like set.

    ``diameter_std`` defaults to the paper's size table (315 um: 8.2 um, 475 um: 22 um) and must
    be given for another diameter. The pair starts ``touch_time = touch_steps x dt_factor x`` the
    eq. (12) step of the smallest likely particle (mean - 4 std) at 40 m/s before first touch:
    about ``touch_steps`` DEM steps of a pair (measured on 4096 pairs: 1.7-2.0 steps with the defaults).

    ``grazing_fraction`` left unset (None) is ``min(0.3, 1 - central_fraction)``: the default 0.3 gives way to a
    central fraction the caller chose (``central_fraction=1``: every row central, none grazing). The rows
    neither central nor grazing, ``1 - central - grazing``, are uniform in b^2.
    """
    if grazing_fraction is None:
        grazing_fraction = min(DEFAULT_GRAZING_FRACTION, max(0.0, 1.0 - float(central_fraction)))
    material = material if material is not None else Material()
    if not (isinstance(diameter, (int, float)) and math.isfinite(diameter) and diameter > 0):
        raise ConfigError(f"--diameter must be a positive number of metres (got {diameter!r}); e.g. 315e-6")
    if diameter_std is None:
        diameter_std = paper_diameter_std(diameter)
        if diameter_std is None:
            raise ConfigError(f"no size distribution known for diameter {diameter:g} m (the paper gives 315e-6 and "
                              "475e-6); give --diameter-std (0 for monodisperse)")
    if not touch_steps > 0:
        raise ConfigError(f"touch steps must be > 0 (got {touch_steps})")
    if mixture_diameter_stds is not None:
        if len(mixture_diameter_stds) != len(mixture_diameters):
            raise ConfigError(f"--diameter-stds has {len(mixture_diameter_stds)} values for {len(mixture_diameters)} "
                              "diameters; give one standard deviation per diameter")
        mixture_stds = [float(sd) for sd in mixture_diameter_stds]
    else:
        mixture_stds = []
        for d in mixture_diameters:
            sd = paper_diameter_std(float(d))
            if sd is None:
                raise ConfigError(f"no size distribution known for mixture diameter {d:g} m (the paper gives 315e-6 "
                                  "and 475e-6); give --diameter-stds")
            mixture_stds.append(sd)
    smallest = min([diameter - 4.0 * diameter_std] + [d - 4.0 * sd for d, sd in zip(mixture_diameters, mixture_stds)])
    small_radius = 0.5 * max(smallest, 0.25 * min([diameter, *mixture_diameters]))
    dt = material.time_step(small_radius, max_speed=2.0 * speed_max).chosen  # the runner's step at 40 m/s
    cfg = ConfigurationSpec(diameter_mean=float(diameter), diameter_std=float(diameter_std),
                            mixture_diameters=tuple(float(d) for d in mixture_diameters),
                            mixture_diameter_stds=tuple(float(sd) for sd in mixture_stds),
                            mixture_mass_fractions=tuple(float(w) for w in mixture_mass_fractions),
                            density_mean=material.density, density_std=float(density_std),
                            speed_max=float(speed_max), central_fraction=float(central_fraction),
                            grazing_fraction=float(grazing_fraction), grazing_angle=float(grazing_angle),
                            max_offset=float(max_offset), slow_fraction=float(slow_fraction),
                            min_relative_speed=float(min_relative_speed), min_normal_speed=float(min_normal_speed),
                            touch_time=float(touch_steps * dt_factor * dt), spin_fraction=float(spin_fraction),
                            spin_ratio=float(spin_ratio))
    return DatasetSpec(samples=int(samples), seed=int(seed), configurations=cfg, material=material,
                       contact_model=contact_model, chunk_size=int(chunk_size), dt_factor=float(dt_factor))


# ---------------------------------------------------------------- computing one chunk

GRAZING_CONTACT_STEPS = 10
"""Fewest DEM steps over the geometric contact time of a grazing impact (``grazing_contact_time``)."""


def grazing_contact_time(configs: Configurations) -> np.ndarray:
    """Time the undeflected relative path spends inside the contact sphere, ``2 (r1 + r2) g_n / |g|^2``, s.

    A chord of the sphere of radius ``r1 + r2`` at impact parameter ``b``: length ``2 (r1 + r2) cos chi``.
    At grazing incidence and speed the soft contact ends by this geometry (the spheres slide past)
    long before the Hertz duration at the normal speed: at 89.9 deg and 20 m/s it is 5.5e-8 s, half the
    eq. (12) step; the data set's DEM step is capped at 1/GRAZING_CONTACT_STEPS of it.
    """
    g = configs.v1 - configs.v2
    g_n = np.maximum(np.einsum("ij,ij->i", g, configs.normal), 0.0)
    return (configs.d1 + configs.d2) * g_n / np.maximum(np.einsum("ij,ij->i", g, g), 1e-300)


def dem_runner(configs: Configurations, spec: DatasetSpec) -> np.ndarray:
    """Outputs (n, 15) of the batched binary DEM ``hel_warp.collisions.impact.simulate_pairs`` for ``configs``.

    One call (one Warp thread per pair) for the whole chunk, in each pair's centre-of-mass frame (the
    lab velocity added back to the outputs); the time step is ``spec.dt_factor``
    times the runner's default (eq. 12 for the smaller sphere of the pair, V_max = max(20 m/s,
    approach speed), ``hel_warp.collisions.impact.stable_time_step``), capped at 1/GRAZING_CONTACT_STEPS of the
    grazing contact time (``grazing_contact_time``); the step limit covers 4x the longer of the Hertz
    and the geometric contact times. Pairs that never touched or did not
    separate within the runner's step limit are refused (DatasetError), never stored.
    """
    from hel_warp.collisions.impact import TIME_STEP_MAX_SPEED, simulate_pairs, stable_time_step  # lazy: imports warp

    material = spec.material
    # run in the centre-of-mass frame (Galilean invariance: no gravity, no walls) so float32 keeps the
    # relative motion: a slow pair (|g| ~ 0.01 m/s) riding at 20 m/s in the lab drifts by ~its own size
    # during the contact, and the float32 positions then resolve its ~1e-9 m overlap to a few % only
    # (measured: up to 1.7 % of |g| energy gain and spurious tangential impulses in the lab frame)
    m1 = configs.rho1 * configs.d1**3
    m2 = configs.rho2 * configs.d2**3
    v_com = (m1[:, None] * configs.v1 + m2[:, None] * configs.v2) / (m1 + m2)[:, None]
    v1, v2 = configs.v1 - v_com, configs.v2 - v_com
    vmax = np.maximum(TIME_STEP_MAX_SPEED, np.linalg.norm(configs.v1 - configs.v2, axis=1))
    stable = np.minimum(
        stable_time_step(0.5 * configs.d1, configs.rho1, material.youngs_modulus, material.poisson_ratio, vmax),
        stable_time_step(0.5 * configs.d2, configs.rho2, material.youngs_modulus, material.poisson_ratio, vmax))
    t_graze = grazing_contact_time(configs)
    dt = np.minimum(spec.dt_factor * stable, t_graze / GRAZING_CONTACT_STEPS)
    # start at most half a step before first touch (contact point at the origin): the runner's first step
    # then jumps to the touch instant. Stepping a slow grazing pair through a longer float32 approach
    # drifts it systematically (each step rounds v dt ~ 25 ulps the same way) and it can miss a contact
    # whose depth is R (1 - b) ~ 1e-9 m (measured: 89.8 deg, 0.013 m/s)
    t_start = np.minimum(configs.touch_time, 0.5 * dt)[:, None]
    r1, r2 = 0.5 * configs.d1[:, None], 0.5 * configs.d2[:, None]
    x1 = -r1 * configs.normal - t_start * v1
    x2 = r2 * configs.normal - t_start * v2
    # step limit: the runner's own estimate uses the Hertz duration at the normal speed; a slow grazing
    # contact lasts up to the geometric time instead (the spheres slide past before the normal rebound)
    from hel_warp.collisions.contact_law import hertz_contact_duration

    inv_e = 2.0 * (1.0 - material.poisson_ratio**2) / material.youngs_modulus
    r_eff = 0.5 * configs.d1 * configs.d2 / (configs.d1 + configs.d2)
    m_eff = np.pi / 6.0 * m1 * m2 / (m1 + m2)
    g_n = np.maximum(np.einsum("ij,ij->i", configs.v1 - configs.v2, configs.normal), 1e-12)
    t_hertz = hertz_contact_duration(1.0 / inv_e, r_eff, m_eff, g_n)
    max_steps = int(np.max(4.0 * (configs.touch_time + np.maximum(t_hertz, t_graze)) / dt + 100.0))
    spins = {} if configs.omega1 is None else {"omega1": configs.omega1, "omega2": configs.omega2}
    result = simulate_pairs(
        x1=x1, x2=x2, v1=v1, v2=v2, **spins,
        radius1=0.5 * configs.d1, radius2=0.5 * configs.d2, density1=configs.rho1, density2=configs.rho2,
        youngs1=material.youngs_modulus, poisson1=material.poisson_ratio,
        restitution=material.restitution, friction=material.friction,
        rolling_friction=material.rolling_friction, model=spec.contact_model, dt=dt, max_steps=max_steps)
    failed = ~(result.touched & result.separated)
    if failed.any():
        ids = configs.config_id[failed]
        raise DatasetError(f"{int(failed.sum())} pairs did not complete a collision in the DEM (config ids "
                           f"{', '.join(map(str, ids[:5]))}{'...' if ids.size > 5 else ''}); nothing of this chunk "
                           "was written")
    return np.column_stack([result.velocity1 + v_com, result.velocity2 + v_com, result.omega1, result.omega2,
                            result.contact_duration, result.max_overlap, result.max_normal_force]
                           ).astype(np.float64)


@dataclass(frozen=True)
class ChunkResult:
    """The four row arrays of one chunk."""

    k: int
    inputs: np.ndarray
    outputs: np.ndarray
    config_id: np.ndarray
    family: np.ndarray
    fingerprint: str = ""


def compute_chunk(spec: DatasetSpec, k: int, runner: PairRunner | None = None) -> ChunkResult:
    """Configurations and DEM outcomes of chunk ``k`` (pure: runs the same on any worker).

    Raises DatasetError when any row is not finite (the count and first ids are in the message).
    """
    start, stop = spec.rows(k)
    configs = generate(spec.configurations, spec.seed, start, stop)
    outputs = np.asarray((runner or dem_runner)(configs, spec), dtype=np.float64)
    inputs = configs.inputs()
    if outputs.shape != (stop - start, len(OUTPUT_COLUMNS)):
        raise DatasetError(f"pair runner returned shape {outputs.shape}, expected {(stop - start, len(OUTPUT_COLUMNS))}")
    bad = ~(np.all(np.isfinite(inputs), axis=1) & np.all(np.isfinite(outputs), axis=1))
    if bad.any():
        ids = configs.config_id[bad]
        raise DatasetError(f"chunk {k}: {int(bad.sum())} of {stop - start} rows are NaN/inf (config ids "
                           f"{', '.join(map(str, ids[:5]))}{'...' if ids.size > 5 else ''}); nothing of this chunk "
                           "was written; check the material and time step")
    return ChunkResult(k=k, inputs=inputs, outputs=outputs, config_id=configs.config_id, family=configs.family,
                       fingerprint=code_fingerprint())


# ---------------------------------------------------------------- the store

def _is_our_store(path: Path) -> bool:
    """True when ``path`` holds a zarr group whose attrs name our input columns."""
    try:
        attrs = json.loads((path / "zarr.json").read_text()).get("attributes", {})
    except (OSError, ValueError, AttributeError):
        return False
    return attrs.get("input_columns") in (list(INPUT_COLUMNS), list(INPUT_COLUMNS + SPIN_INPUT_COLUMNS))


def _open_store(path: Path, spec: DatasetSpec, overwrite: bool):
    import zarr

    expected = spec.attrs()
    if overwrite and path.exists():
        if not _is_our_store(path) and (path.is_file() or any(path.iterdir())):
            raise DatasetError(f"{path} exists and is not a hel-warp data set; --overwrite only replaces a data set "
                               "(choose another --out)")
        shutil.rmtree(path)
    if path.exists() and not (path / "zarr.json").exists():
        if any(path.iterdir()):
            raise DatasetError(f"{path} exists and is not a data set; choose a new --out or remove it")
    if (path / "zarr.json").exists():
        try:
            group = zarr.open_group(str(path), mode="r+")
        except Exception as exc:  # noqa: BLE001 - any read failure means: not our store
            raise DatasetError(f"{path} is not a readable zarr group ({exc}); use a new --out or --overwrite") from None
        stored = dict(group.attrs)
        diff = [key for key in expected if stored.get(key) != expected[key]]
        if diff == ["code_fingerprint"]:
            raise DatasetError(f"{path} was started with other configuration/DEM code (fingerprint "
                               f"{stored.get('code_fingerprint')}, now {expected['code_fingerprint']}); finishing it "
                               "would mix two versions in one set: finish it with the old code, or use a new --out "
                               "or --overwrite")
        if diff:
            details = "; ".join(f"{key}: stored {stored.get(key)!r}, requested {expected[key]!r}" for key in diff[:4])
            raise DatasetError(f"{path} holds a data set made with other parameters ({details}); "
                               "rerun with the same parameters to resume, or use a new --out or --overwrite")
    else:
        group = zarr.open_group(str(path), mode="w", attributes=expected)
    n, cs = spec.samples, spec.chunk_size
    layout = {
        "inputs": ((n, len(spec.input_columns)), "float64", (cs, len(spec.input_columns)), 0.0),
        "outputs": ((n, len(OUTPUT_COLUMNS)), "float64", (cs, len(OUTPUT_COLUMNS)), 0.0),
        "config_id": ((n,), "int64", (cs,), -1),
        "family": ((n,), "int8", (cs,), -1),
        "chunk_done": ((spec.n_chunks,), "bool", (1,), False),
    }
    for name, (shape, dtype, chunks, fill) in layout.items():
        if name in group:
            arr = group[name]
            if arr.shape != shape or arr.dtype != np.dtype(dtype) or arr.chunks != chunks:
                raise DatasetError(f"{path}/{name} has shape {arr.shape}, dtype {arr.dtype}, chunks {arr.chunks}; "
                                   f"expected {shape}, {dtype}, {chunks}: the store is corrupted, use --overwrite")
        else:
            group.create_array(name, shape=shape, dtype=dtype, chunks=chunks, fill_value=fill)
    return group


def _write_chunk(group, spec: DatasetSpec, result: ChunkResult) -> None:
    start, stop = spec.rows(result.k)
    if result.fingerprint != code_fingerprint():
        raise DatasetError(f"chunk {result.k} was computed with other code (fingerprint {result.fingerprint}, "
                           f"this client {code_fingerprint()}); install the same hel_warp on every Dask worker")
    if not np.array_equal(result.config_id, np.arange(start, stop)):
        raise DatasetError(f"chunk {result.k}: config ids do not match rows {start}..{stop - 1} (input/output mix-up)")
    group["inputs"][start:stop] = result.inputs
    group["outputs"][start:stop] = result.outputs
    group["config_id"][start:stop] = result.config_id
    group["family"][start:stop] = result.family
    group["chunk_done"][result.k] = True


def _done_flags(group, n_chunks: int) -> np.ndarray:
    """``chunk_done`` read flag by flag; an unreadable flag counts as not done."""
    flags = np.zeros(n_chunks, dtype=bool)
    try:
        flags[:] = group["chunk_done"][:]
    except Exception:  # noqa: BLE001 - a damaged flag file: read one by one
        for k in range(n_chunks):
            try:
                flags[k] = bool(group["chunk_done"][k])
            except Exception:  # noqa: BLE001
                flags[k] = False
    return flags


def _content_hash(group, spec: DatasetSpec) -> str:
    """sha256 of ``inputs`` then ``outputs`` (little-endian float64, C order), read chunk by chunk."""
    digest = hashlib.sha256()
    for name in ("inputs", "outputs"):
        for k in range(spec.n_chunks):
            start, stop = spec.rows(k)
            digest.update(np.ascontiguousarray(group[name][start:stop], dtype="<f8").tobytes())
    return digest.hexdigest()


def build_dataset(out: str | Path, spec: DatasetSpec, *, scheduler: str | None = None, overwrite: bool = False,
                  progress: bool = True, runner: PairRunner | None = None,
                  after_chunk: Callable[[int], None] | None = None, scheduler_timeout: float = 30.0) -> dict:
    """Write (or resume) the data set of ``spec`` at ``out``; return a summary dict.

    ``scheduler``: a Dask distributed scheduler address (chunks computed on its workers);
    None computes locally (``scheduler_timeout``: seconds to wait for it). ``runner`` replaces the DEM (tests); ``after_chunk(k)`` is called
    after chunk ``k`` is marked done (a test hook).
    """
    from tqdm import tqdm

    path = Path(out)
    t0 = time.perf_counter()
    group = _open_store(path, spec, overwrite)
    done = _done_flags(group, spec.n_chunks)
    pending = [k for k in range(spec.n_chunks) if not done[k]]
    resumed = len(pending) < spec.n_chunks
    bar = tqdm(total=spec.samples, initial=spec.samples - sum(stop - start for start, stop in map(spec.rows, pending)),
               unit="pair", desc="dataset", disable=not progress, smoothing=0.1)
    try:
        def write(result: ChunkResult) -> None:
            _write_chunk(group, spec, result)
            bar.update(result.config_id.shape[0])
            if after_chunk is not None:
                after_chunk(result.k)

        if scheduler:
            _compute_on_dask(scheduler, spec, pending, runner, write, scheduler_timeout)
        else:
            for k in pending:
                write(compute_chunk(spec, k, runner))
    finally:
        bar.close()
    if not _done_flags(group, spec.n_chunks).all():
        raise DatasetError(f"{path}: some chunks are still missing; rerun the same command to resume")
    digest = _content_hash(group, spec)
    stored = group.attrs.get("dataset_hash")
    if stored is not None and stored != digest:
        raise DatasetError(f"{path}: stored dataset_hash {stored[:12]}... does not match the arrays "
                           f"({digest[:12]}...): the set is corrupted; rebuild with --overwrite")
    if stored is None:
        group.attrs["dataset_hash"] = digest
    return {"out": str(path), "samples": spec.samples, "chunks": spec.n_chunks, "computed_chunks": len(pending),
            "resumed": resumed, "dataset_hash": digest, "seconds": time.perf_counter() - t0}


def _compute_on_dask(address: str, spec: DatasetSpec, pending: list[int], runner, write, timeout: float) -> None:
    try:
        from dask.distributed import Client, as_completed
    except ImportError:
        raise ConfigError("--scheduler needs dask distributed: pip install 'hel_warp[dask]' "
                          "(or 'dask[distributed]'), or leave --scheduler out to compute locally") from None
    try:
        client = Client(address, timeout=timeout)
    except Exception as exc:  # noqa: BLE001 - connection errors come in many types
        raise ConfigError(f"cannot reach the Dask scheduler at {address!r} ({exc}); check the address") from None
    with client:
        futures = [client.submit(compute_chunk, spec, k, runner, pure=False) for k in pending]
        for future in as_completed(futures):
            write(future.result())


# ---------------------------------------------------------------- reading

@dataclass(frozen=True)
class Dataset:
    """A complete, verified data set in memory."""

    inputs: np.ndarray
    """(N, 14) float64 (a spinning set: (N, 20)), columns ``attrs["input_columns"]``."""
    outputs: np.ndarray
    """(N, 15) float64, columns ``attrs["output_columns"]``."""
    config_id: np.ndarray
    """(N,) int64, equal to the row index."""
    family: np.ndarray
    """(N,) int8: 0 converging, 1 parallel, 2 head-on."""
    attrs: dict
    """The group attrs (material, seed, samples, contact model, dataset_hash, ...)."""


def load_dataset(path: str | Path) -> Dataset:
    """Read the data set at ``path``; refuse it (DatasetError) when incomplete or corrupted."""
    import zarr

    path = Path(path)
    if not (path / "zarr.json").exists():
        raise DatasetError(f"{path} is not a data set (no zarr.json); make one with hel-warp dataset --out {path}")
    try:
        group = zarr.open_group(str(path), mode="r")
        attrs = dict(group.attrs)
        arrays = {name: group[name][:] for name in ROW_ARRAYS}
        flags = group["chunk_done"][:]
    except Exception as exc:  # noqa: BLE001 - a missing or damaged array file
        raise DatasetError(f"{path} cannot be read ({type(exc).__name__}: {exc}); the set is corrupted, "
                           "rebuild it with hel-warp dataset --overwrite") from None
    missing = [key for key in ("samples", "input_columns", "output_columns") if key not in attrs]
    if missing:
        raise DatasetError(f"{path} lacks the attrs {missing}: not a hel-warp collision data set")
    if not flags.all():
        raise DatasetError(f"{path} is incomplete ({int(flags.sum())} of {flags.size} chunks done); "
                           "rerun the same hel-warp dataset command to finish it")
    if "dataset_hash" not in attrs:
        raise DatasetError(f"{path} has no dataset_hash (the run stopped before the end); rerun the same command")
    n = int(attrs["samples"])
    inputs, outputs = arrays["inputs"], arrays["outputs"]
    if inputs.shape != (n, len(attrs["input_columns"])) or outputs.shape != (n, len(attrs["output_columns"])):
        raise DatasetError(f"{path}: array shapes {inputs.shape}, {outputs.shape} do not match {n} samples")
    if not np.array_equal(arrays["config_id"], np.arange(n)):
        raise DatasetError(f"{path}: config_id is not 0..{n - 1} in order (rows mixed up); rebuild with --overwrite")
    digest = hashlib.sha256(np.ascontiguousarray(inputs, dtype="<f8").tobytes()
                            + np.ascontiguousarray(outputs, dtype="<f8").tobytes()).hexdigest()
    if digest != attrs["dataset_hash"]:
        raise DatasetError(f"{path}: content does not match dataset_hash (corrupted); rebuild with --overwrite")
    if not (np.isfinite(inputs).all() and np.isfinite(outputs).all()):
        raise DatasetError(f"{path}: holds NaN/inf values; rebuild with --overwrite")
    return Dataset(inputs=inputs, outputs=outputs, config_id=arrays["config_id"], family=arrays["family"], attrs=attrs)

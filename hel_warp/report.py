"""Post-processing of colliding-streams runs: velocity profiles, dispersion pictures, wall clock, collision rates.

What the paper compares (sections 6 and 8; Figs. 11-23):

- time-averaged particle velocity profiles at the ten measurement sections, each section split
  across the channel width into 20, 88 or 126 sub-boxes (Figs. 14-16, 19). The mean axial
  velocity of a sub-box is the parcel-weight-weighted mean over every (snapshot, parcel) sample
  whose centre lies in it: ``u_b = sum_s w_s u_s / sum_s w_s`` (a parcel of weight w stands for w
  particles). ``downstream_only`` keeps samples with ``u > 0`` only, as the experimental tracking
  did (it "tracks only particles that move in the downstream direction", section 8);
- the RMS difference of two runs' profiles, over the ten sections and the sub-boxes where both
  have at least ``min_samples`` (default 10) samples: ``sqrt(mean_b (u_b - u_b^dem)^2)`` (m/s), taken
  against a ``dem`` run of the same report (same diameter and dt preferred);
- particle dispersion coloured by stream and the solid volume fraction on a log scale (Figs. 11,
  17, 20): eps_s of the last snapshot, particle volume binned on the grid spacing in the x-y plane
  and divided by the bin volume (bin area x channel depth);
- wall clock per model and time step (Figs. 12, 22) and collision rates, detected collisions per
  simulated second (Fig. 23).

A run directory is what ``cases/colliding_streams.py`` writes: ``run.zarr`` with snapshots
(``x``, ``v``, ``weight``, ``stream`` per parcel), series ``collisions`` and attrs ``config`` holding
``collisions``, ``dt``, ``diameter``, ``end_time``, ``wall_clock_s`` and ``rig`` (``axial_axis``,
``transverse_axis``, ``downstream``, ``sections``: ten boxes ``{name, lo, hi}`` in m).
Figures are rendered with pyvista off-screen, or with matplotlib when pyvista cannot render.

``report.json``::

    {"runs": [{"run", "label", "collisions", "dt" (s), "diameter" (m), "end_time" (simulated s),
               "particles_per_parcel", "wall_clock_s" (sum of the per-step wall clock), "collision_rate" (1/s
               or null), "total_collisions", "snapshots",
               "profiles": {"20": [{"section", "centres" (m), "mean_axial_velocity" (m/s, null where empty),
                                    "samples"}, ... ten sections], "88": [...], "126": [...]},
               "dem_reference" and "profile_rms_vs_dem": {"20": m/s, ...} (null for the reference itself),
               "paper_experimental_uncertainty" (m/s: 0.63 at 315 um, 0.71 at 475 um, else null), only when a
               dem run is in the report}, ...],
     "boxes", "downstream_only", "from_time", "min_samples", "figures", "renderer"}
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hel_warp.errors import ConfigError

DEFAULT_BOXES = (20, 88, 126)
"""Sub-boxes per section used in the paper (section 8)."""
STREAM_COLOURS = {0: "#d62728", 1: "#1f77b4"}
"""Left stream red, right stream blue (as Fig. 11)."""


COLLISION_SERIES = "collisions_detected_pairs"
"""The per-step count a collision rate is made of (``counts()['detected_pairs']`` of hel_warp.collision_models)."""
_RUN_KEYS = ("hel", "collision", "grid", "gas", "capacity", "run", "case")


@dataclass
class RunData:
    """One run directory read from disk (host arrays)."""

    path: str
    label: str
    config: dict
    times: np.ndarray
    """(n_snapshots,) s."""
    snapshots: list
    """Per snapshot: dict of arrays (x, v, weight, stream, radius, ...)."""
    series: dict = field(default_factory=dict)
    """name -> 1-d array (per step)."""

    @property
    def rig(self) -> dict:
        return self.config["rig"]


def _require(config: dict, key: str, path: str):
    if key not in config:
        raise ConfigError(f"{path}: run.zarr attrs config lacks {key!r}; not a colliding-streams run directory "
                          "(written by cases/colliding_streams.py)")
    return config[key]


def load_run(run_dir: str) -> RunData:
    """Read ``run_dir/run.zarr``; ConfigError with what is wrong for a missing or corrupt run directory."""
    import zarr

    path = Path(run_dir)
    if not path.is_dir():
        raise ConfigError(f"run directory {run_dir} not found")
    store = path / "run.zarr"
    if not store.is_dir():
        raise ConfigError(f"{run_dir} has no run.zarr; is it a run directory written by cases/colliding_streams.py?")
    try:
        root = zarr.open_group(str(store), mode="r")
        attrs = dict(root.attrs)
    except Exception as exc:  # noqa: BLE001 - zarr raises many types for a damaged store
        raise ConfigError(f"{store} cannot be opened ({type(exc).__name__}: {exc}); the store is corrupt") from None
    raw = attrs.get("config")
    if not isinstance(raw, dict):
        raise ConfigError(f"{store} has no config attrs; the store is corrupt or was not written by a run")
    # hel_warp.run.Run layout: config = {hel, collision, grid, gas, capacity, run, case}, plus the case's
    # ``summary`` attrs at the end; a flat config (hand-made runs) is read as it is
    config = {k: v for k, v in raw.items() if k not in _RUN_KEYS}
    if isinstance(raw.get("case"), dict):
        config.update(raw["case"])
    if isinstance(attrs.get("summary"), dict):
        config.update(attrs["summary"])
    for key in ("collisions", "dt", "diameter", "end_time", "rig"):
        _require(config, key, run_dir)
    if config.get("status") not in (None, "complete"):
        raise ConfigError(f"{run_dir}: the run did not finish (status {config.get('status')!r}); "
                          "rerun it before reporting")
    rig = config["rig"]
    sections = rig.get("sections") if isinstance(rig, dict) else None
    if not isinstance(sections, list) or not sections:
        raise ConfigError(f"{run_dir}: config.rig has no sections")
    snapshots, times = [], []
    try:
        count = int(attrs.get("snapshot_count", 0))
        for index in range(count):
            group = root["snapshots"][f"{index:06d}"]
            arrays = {name: np.asarray(arr[...]) for name, arr in group.arrays()}
            for need in ("x", "v"):
                if need not in arrays:
                    raise ConfigError(f"{run_dir}: snapshot {index} lacks {need!r}")
            n = arrays["x"].shape[0]
            arrays.setdefault("weight", np.ones(n, np.float32))
            arrays.setdefault("stream", np.zeros(n, np.int32))
            snapshots.append(arrays)
            times.append(float(group.attrs["time"]))
        series = {}
        if "series" in root:
            for name, arr in root["series"].arrays():
                series[name] = np.asarray(arr[...])
    except ConfigError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise ConfigError(f"{store} cannot be read ({type(exc).__name__}: {exc}); the store is corrupt") from None
    if not snapshots:
        raise ConfigError(f"{run_dir}: run.zarr holds no particle snapshot")
    return RunData(path=str(path), label=path.name, config=config, times=np.asarray(times), snapshots=snapshots,
                   series=series)


# ------------------------------------------------------------------------------------------ profiles
def section_profile(run: RunData, section: dict, boxes: int, *, downstream_only: bool = False,
                    from_time: float = 0.0) -> dict:
    """Sub-box centres (m, along the transverse axis), mean axial velocity (m/s; None where empty), sample counts."""
    rig = run.rig
    axial, transverse = int(rig["axial_axis"]), int(rig["transverse_axis"])
    sign = 1.0 if float(rig.get("downstream", [1.0, 0.0, 0.0])[axial]) >= 0 else -1.0
    lo, hi = np.asarray(section["lo"], float), np.asarray(section["hi"], float)
    edges = np.linspace(lo[transverse], hi[transverse], boxes + 1)
    weighted = np.zeros(boxes)
    weight_sum = np.zeros(boxes)
    samples = np.zeros(boxes, dtype=np.int64)
    for t, snap in zip(run.times, run.snapshots):
        if t < from_time:
            continue
        x = np.asarray(snap["x"], np.float64)
        if x.shape[0] == 0:
            continue
        inside = np.all((x >= lo) & (x < hi), axis=1)
        u = sign * np.asarray(snap["v"], np.float64)[inside, axial]
        w = np.asarray(snap["weight"], np.float64)[inside]
        pos = x[inside, transverse]
        if downstream_only:
            keep = u > 0.0
            u, w, pos = u[keep], w[keep], pos[keep]
        index = np.clip(np.searchsorted(edges, pos, side="right") - 1, 0, boxes - 1)
        np.add.at(weighted, index, w * u)
        np.add.at(weight_sum, index, w)
        np.add.at(samples, index, 1)
    mean = [float(weighted[b] / weight_sum[b]) if weight_sum[b] > 0 else None for b in range(boxes)]
    return {"section": section.get("name", ""), "centres": (0.5 * (edges[:-1] + edges[1:])).tolist(),
            "mean_axial_velocity": mean, "samples": samples.tolist()}


def profiles(run: RunData, boxes: int, *, downstream_only: bool = False, from_time: float = 0.0) -> list:
    """The profiles of all sections of ``run`` with ``boxes`` sub-boxes each."""
    return [section_profile(run, s, boxes, downstream_only=downstream_only, from_time=from_time)
            for s in run.rig["sections"]]


DEFAULT_MIN_SAMPLES = 10
"""Sub-boxes with fewer (snapshot, parcel) samples than this in either run are left out of the RMS: the mean
of n samples of a velocity spread sigma has a standard error sigma / sqrt(n), ~0.3 sigma at 10 (at the front
of the cloud a box may hold one or two parcels, whose noise would swamp the comparison)."""


def profile_rms(a: list, b: list, *, min_samples: int = 1) -> float | None:
    """RMS of the differences of two runs' profiles over all sections and the sub-boxes where both runs have at
    least ``min_samples`` samples."""
    if len(a) != len(b):
        raise ConfigError(f"the runs have {len(a)} and {len(b)} sections; compare runs of the same rig")
    diffs = []
    for pa, pb in zip(a, b):
        if len(pa["mean_axial_velocity"]) != len(pb["mean_axial_velocity"]):
            raise ConfigError("profiles with different sub-box counts cannot be compared")
        na = pa.get("samples") or [min_samples] * len(pa["mean_axial_velocity"])
        nb = pb.get("samples") or [min_samples] * len(pb["mean_axial_velocity"])
        for ua, ub, ka, kb in zip(pa["mean_axial_velocity"], pb["mean_axial_velocity"], na, nb):
            if ua is not None and ub is not None and ka >= min_samples and kb >= min_samples:
                diffs.append(ua - ub)
    return float(np.sqrt(np.mean(np.square(diffs)))) if diffs else None


PAPER_UNCERTAINTY = {315e-6: 0.63, 475e-6: 0.71}
"""The paper's experimental uncertainty of the measured velocity profiles, m/s, per particle size (section 8):
the bar an RMS against dem is read against."""


def paper_uncertainty(diameter: float) -> float | None:
    """The paper's experimental uncertainty (m/s) for a run of this diameter (within 1e-3), else None."""
    for d, value in PAPER_UNCERTAINTY.items():
        if abs(float(diameter) - d) <= 1e-3 * d:
            return value
    return None


def collision_rate(run: RunData) -> float | None:
    """Detected collisions per simulated second: the sum of series ``collisions`` (hand-made runs) or
    ``collisions_detected_pairs`` (the strategies' ``counts()``: pairs found overlapping in a step) over the
    simulated time; None when the model does not count collisions (none, ktgf)."""
    if run.config.get("collision_counts_available") is False:
        return None
    counts = run.series.get("collisions", run.series.get(COLLISION_SERIES))
    if counts is None:
        return None
    simulated = float(run.config.get("simulated_time", run.config["end_time"]))
    return float(np.sum(counts)) / simulated if simulated > 0 else None


def _dem_reference(run: RunData, runs: list) -> RunData | None:
    """The ``dem`` run to compare ``run`` with: same particle diameter (required), same dt preferred."""
    dems = [r for r in runs if r.config["collisions"] == "dem"
            and abs(float(r.config["diameter"]) - float(run.config["diameter"])) <= 1e-9]
    if not dems:
        return None
    return sorted(dems, key=lambda r: abs(float(r.config["dt"]) - float(run.config["dt"])) > 1e-12)[0]


# ------------------------------------------------------------------------------------------ the report
def build_report(run_dirs: list, *, boxes=DEFAULT_BOXES, downstream_only: bool = False,
                 from_time: float = 0.0, min_samples: int = DEFAULT_MIN_SAMPLES) -> tuple:
    """(the report.json document, the loaded ``RunData``s) for ``run_dirs``; no files written."""
    if not run_dirs:
        raise ConfigError("give at least one run directory")
    boxes = [int(b) for b in boxes]
    if int(min_samples) < 1:
        raise ConfigError(f"--min-samples must be >= 1 (got {min_samples})")
    if any(b < 1 for b in boxes):
        raise ConfigError(f"--boxes must be positive integers (got {boxes})")
    runs = [load_run(d) for d in run_dirs]
    labels = [r.label for r in runs]
    for i, r in enumerate(runs):  # unique labels for the figures
        if labels.count(r.label) > 1:
            r.label = f"{r.label}_{i}"
    all_profiles = {r.path: {str(b): profiles(r, b, downstream_only=downstream_only, from_time=from_time)
                             for b in boxes} for r in runs}
    entries = []
    for r in runs:
        c = r.config
        entry = {"run": r.path, "label": r.label, "collisions": c["collisions"], "dt": float(c["dt"]),
                 "diameter": float(c["diameter"]), "end_time": float(c["end_time"]),
                 "particles_per_parcel": c.get("particles_per_parcel"),
                 "wall_clock_s": (float(c["wall_clock_s"]) if c.get("wall_clock_s") is not None else None),
                 "collision_rate": collision_rate(r),
                 "total_collisions": c.get("total_collisions"),
                 "snapshots": len(r.snapshots), "profiles": all_profiles[r.path]}
        ref = _dem_reference(r, runs)
        if ref is not None:
            entry["dem_reference"] = ref.label
            entry["paper_experimental_uncertainty"] = paper_uncertainty(c["diameter"])
            entry["profile_rms_vs_dem"] = (None if ref is r else
                                           {str(b): profile_rms(all_profiles[r.path][str(b)],
                                                                all_profiles[ref.path][str(b)],
                                                                min_samples=int(min_samples)) for b in boxes})
        entries.append(entry)
    return {"runs": entries, "boxes": boxes, "downstream_only": bool(downstream_only), "from_time": from_time,
            "min_samples": int(min_samples),
            "velocity": "mean axial (downstream) particle velocity, m/s, weighted by parcel weight",
            "profile_rms_vs_dem": "m/s, RMS over the ten sections and the sub-boxes where both runs have at least "
                                  "min_samples samples"}, runs


def write_report(run_dirs: list, out_dir: str, *, boxes=DEFAULT_BOXES, downstream_only: bool = False,
                 from_time: float = 0.0, figures: bool = True, min_samples: int = DEFAULT_MIN_SAMPLES) -> dict:
    """Write ``out_dir/report.json`` and the PNG figures; returns the report document."""
    report, runs = build_report(run_dirs, boxes=boxes, downstream_only=downstream_only, from_time=from_time,
                                min_samples=min_samples)
    os.makedirs(out_dir, exist_ok=True)
    written = []
    if figures:
        renderer = _Renderer()
        for r in runs:
            written.append(renderer.dispersion(r, os.path.join(out_dir, f"dispersion_{r.label}.png")))
            written.append(renderer.volume_fraction(r, os.path.join(out_dir, f"eps_s_{r.label}.png")))
        for b in report["boxes"]:
            written.append(_plot_profiles(report, b, os.path.join(out_dir, f"profiles_{b}.png")))
        written.append(_plot_bars(report, "wall_clock_s", "wall clock, s", os.path.join(out_dir, "wall_clock.png")))
        written.append(_plot_bars(report, "collision_rate", "collision rate, 1/s",
                                  os.path.join(out_dir, "collision_rate.png")))
        report["renderer"] = renderer.used
    report["figures"] = [os.path.basename(p) for p in written if p]
    tmp = os.path.join(out_dir, "report.json.tmp")
    with open(tmp, "w") as fh:
        json.dump(report, fh, indent=1)
    os.replace(tmp, os.path.join(out_dir, "report.json"))
    return report


# ------------------------------------------------------------------------------------------ figures
def _volume_fraction_image(run: RunData) -> tuple:
    """log10 eps_s of the last snapshot binned in the axial-transverse plane: (image, extent)."""
    rig, c = run.rig, run.config
    axial, transverse = int(rig["axial_axis"]), int(rig["transverse_axis"])
    lo, hi = np.asarray(rig.get("domain_lo", [0, 0, 0]), float), np.asarray(rig.get("domain_hi", [1, 1, 1]), float)
    h = float(c.get("spacing", (hi[axial] - lo[axial]) / 100.0))
    depth = float(rig.get("main_depth", h))
    snap = run.snapshots[-1]
    nx = max(1, int(round((hi[axial] - lo[axial]) / h)))
    ny = max(1, int(round((hi[transverse] - lo[transverse]) / h)))
    volume = np.zeros((nx, ny))
    x = np.asarray(snap["x"], float)
    if x.shape[0]:
        radius = np.asarray(snap.get("radius", np.full(x.shape[0], 0.5 * float(c["diameter"]))), float)
        vol = np.asarray(snap["weight"], float) * 4.0 / 3.0 * math.pi * radius**3
        i = np.clip(((x[:, axial] - lo[axial]) / h).astype(int), 0, nx - 1)
        j = np.clip(((x[:, transverse] - lo[transverse]) / h).astype(int), 0, ny - 1)
        np.add.at(volume, (i, j), vol)
    eps = volume / (h * h * depth)
    with np.errstate(divide="ignore"):
        image = np.where(eps > 0, np.log10(np.maximum(eps, 1e-30)), np.nan)
    return image, (lo[axial], hi[axial], lo[transverse], hi[transverse])


def _plane_bounds(run: RunData) -> tuple:
    lo, hi = run.rig.get("domain_lo", [0.0, 0.0, 0.0]), run.rig.get("domain_hi", [1.0, 1.0, 1.0])
    return (lo[0], hi[0], lo[1], hi[1], 0.0, 0.0)


class _Renderer:
    """pyvista off-screen first; after one failure, matplotlib for the rest of the report."""

    def __init__(self):
        self.used = "pyvista"
        self._pyvista_ok = True

    def dispersion(self, run: RunData, path: str) -> str:
        if self._pyvista_ok:
            try:
                return self._pv_dispersion(run, path)
            except Exception:  # noqa: BLE001 - no OpenGL context etc.: fall back
                self._pyvista_ok, self.used = False, "matplotlib"
        return _mpl_dispersion(run, path)

    def volume_fraction(self, run: RunData, path: str) -> str:
        if self._pyvista_ok:
            try:
                return self._pv_volume_fraction(run, path)
            except Exception:  # noqa: BLE001
                self._pyvista_ok, self.used = False, "matplotlib"
        return _mpl_volume_fraction(run, path)

    @staticmethod
    def _pv_dispersion(run: RunData, path: str) -> str:
        import pyvista as pv

        pv.OFF_SCREEN = True
        snap = run.snapshots[-1]
        plotter = pv.Plotter(off_screen=True, window_size=(1400, 600))
        for stream, colour in STREAM_COLOURS.items():
            keep = np.asarray(snap["stream"]) == stream
            if keep.any():
                plotter.add_points(np.asarray(snap["x"], float)[keep], color=colour, point_size=3,
                                   render_points_as_spheres=True)
        for s in run.rig["sections"]:
            lo, hi = s["lo"], s["hi"]
            plotter.add_mesh(pv.Box(bounds=(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])), style="wireframe",
                             color="black")
        lo, hi = run.rig.get("domain_lo"), run.rig.get("domain_hi")
        if lo and hi:
            plotter.add_mesh(pv.Box(bounds=(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])), style="wireframe",
                             color="grey")
        plotter.add_text(f"{run.label}: t = {run.times[-1]:.4g} s (red: left, blue: right)", font_size=10)
        return _screenshot_plane(plotter, run, path)

    @staticmethod
    def _pv_volume_fraction(run: RunData, path: str) -> str:
        import pyvista as pv

        pv.OFF_SCREEN = True
        image, (x0, x1, y0, y1) = _volume_fraction_image(run)
        nx, ny = image.shape
        grid = pv.ImageData(dimensions=(nx + 1, ny + 1, 1), spacing=((x1 - x0) / nx, (y1 - y0) / ny, 1.0),
                            origin=(x0, y0, 0.0))
        grid.cell_data["log10_eps_s"] = image.ravel(order="F")
        plotter = pv.Plotter(off_screen=True, window_size=(1400, 600))
        finite = image[np.isfinite(image)]
        clim = (float(finite.min()), float(finite.max())) if finite.size else (-6.0, 0.0)
        if clim[0] == clim[1]:
            clim = (clim[0] - 1.0, clim[1])
        plotter.add_mesh(grid, scalars="log10_eps_s", clim=clim, nan_color="white", cmap="viridis",
                         scalar_bar_args={"title": "log10 eps_s"})
        plotter.add_text(f"{run.label}: solid volume fraction, t = {run.times[-1]:.4g} s", font_size=10)
        return _screenshot_plane(plotter, run, path)


def _screenshot_plane(plotter, run: RunData, path: str) -> str:
    """Top view (x-y) of the rig plane, parallel projection, written to ``path``; closes the plotter."""
    plotter.view_xy()
    plotter.enable_parallel_projection()
    plotter.reset_camera(bounds=_plane_bounds(run))
    plotter.camera.zoom(1.4)
    plotter.screenshot(path)
    plotter.close()
    return path


def _mpl():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _mpl_dispersion(run: RunData, path: str) -> str:
    plt = _mpl()
    rig = run.rig
    a, t = int(rig["axial_axis"]), int(rig["transverse_axis"])
    snap = run.snapshots[-1]
    fig, ax = plt.subplots(figsize=(12, 5))
    x = np.asarray(snap["x"], float)
    for stream, colour in STREAM_COLOURS.items():
        keep = np.asarray(snap["stream"]) == stream
        ax.scatter(x[keep, a], x[keep, t], s=1, c=colour, label={0: "left", 1: "right"}[stream])
    for s in rig["sections"]:
        ax.add_patch(plt.Rectangle((s["lo"][a], s["lo"][t]), s["hi"][a] - s["lo"][a], s["hi"][t] - s["lo"][t],
                                   fill=False, lw=0.8))
    ax.set_aspect("equal")
    ax.set_xlabel("x, m")
    ax.set_ylabel("y, m")
    ax.set_title(f"{run.label}: particles at t = {run.times[-1]:.4g} s")
    ax.legend(loc="upper right", markerscale=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _mpl_volume_fraction(run: RunData, path: str) -> str:
    plt = _mpl()
    image, extent = _volume_fraction_image(run)
    fig, ax = plt.subplots(figsize=(12, 5))
    im = ax.imshow(image.T, origin="lower", extent=extent, cmap="viridis")
    fig.colorbar(im, ax=ax, label="log10 eps_s")
    ax.set_title(f"{run.label}: solid volume fraction, t = {run.times[-1]:.4g} s")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _plot_profiles(report: dict, boxes: int, path: str) -> str:
    plt = _mpl()
    fig, axes = plt.subplots(2, 5, figsize=(18, 7), sharey=True)
    for entry in report["runs"]:
        for k, prof in enumerate(entry["profiles"][str(boxes)][:10]):
            u = np.array([np.nan if v is None else v for v in prof["mean_axial_velocity"]])
            axes.flat[k].plot(np.asarray(prof["centres"]) * 1e3, u, ".-", ms=3,
                              label=f"{entry['collisions']} d={entry['diameter'] * 1e6:.0f}um dt={entry['dt']:g}")
            axes.flat[k].set_title(prof["section"])
    for ax in axes[-1]:
        ax.set_xlabel("y, mm")
    for ax in axes[:, 0]:
        ax.set_ylabel("mean axial velocity, m/s")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(f"time-averaged particle velocity profiles, {boxes} sub-boxes"
                 + (" (downstream-moving only)" if report["downstream_only"] else ""))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _plot_bars(report: dict, key: str, ylabel: str, path: str) -> str:
    """Bars grouped by (diameter, dt), one bar per collision model (Figs. 12, 22, 23)."""
    plt = _mpl()
    groups = sorted({(e["diameter"], e["dt"]) for e in report["runs"]}, key=lambda g: (g[0], -g[1]))
    models = sorted({e["collisions"] for e in report["runs"]})
    fig, ax = plt.subplots(figsize=(max(6, 1.6 * len(groups) * max(1, len(models)) / 2), 4.5))
    width = 0.8 / max(1, len(models))
    for m, model in enumerate(models):
        values = []
        for g in groups:
            vals = [e[key] for e in report["runs"] if (e["diameter"], e["dt"]) == g and e["collisions"] == model
                    and e[key] is not None]
            values.append(float(np.mean(vals)) if vals else np.nan)
        bars = ax.bar(np.arange(len(groups)) + (m - (len(models) - 1) / 2) * width, values, width, label=model)
        ax.bar_label(bars, labels=["" if np.isnan(v) else f"{v:.3g}" for v in values], fontsize=7)
    ax.set_xticks(np.arange(len(groups)))
    ax.set_xticklabels([f"{d * 1e6:.0f} um\ndt={dt:g} s" for d, dt in groups])
    ax.set_ylabel(ylabel)
    if key == "wall_clock_s":
        ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path

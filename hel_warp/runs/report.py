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
- wall clock per model and time step (Figs. 12, 22), Warp kernel loading apart (``kernel_load_s``);
- what tells collision models apart, from the particles in each section over the snapshots of a
  window (default: the second half of each run), weighted by parcel weight: the stream composition per sub-box,
  the **stream crossing** (the fraction of a stream found on the far side of the channel axis from its own arm:
  0 = both streams stay on their side, 1 = they pass through each other, 1/2 = mixed), the transverse spread
  (std of y per stream) and the transverse velocity (v_y profiles per sub-box, rms over the section), each
  against the ``dem`` run (``*_vs_dem``);
- real collision rates (Fig. 23): binary collisions per simulated second, series ``collisions_collisions``
  (``dem``: contact onsets between spheres; ``surrogate``: resolved collisions, min(w_i, w_j) each), per stream
  pair (left-left, left-right, right-right); the pairs overlapping at step ends (``collisions_detected_pairs``,
  which depend on dt and on how long contacts last) stay as ``overlap_pair_rate``;
- like with like: what still differs between ``dem`` and the HEL runs besides the particle collisions
  (:data:`MODEL_DIFFERENCES`, and each run's config differences), and the gap the walls alone make, measured
  as ``none`` against ``dem`` with the particle contacts off (``model`` ``dem-no-contacts``).

A run directory is what ``cases/colliding_streams.py`` writes: ``run.zarr`` with snapshots
(``x``, ``v``, ``weight``, ``stream`` per parcel), per-step series and attrs ``config`` (``hel``, ``collision``,
``case`` ...) and ``summary`` holding ``collisions``, ``dt``, ``diameter``, ``end_time``, ``wall_clock_s`` and
``rig`` (``axial_axis``, ``transverse_axis``, ``downstream``, ``sections``: ten boxes ``{name, lo, hi}`` in m;
``streams`` {tag: name}, ``stream_sides`` {tag: +1/-1}, ``axis_transverse`` m).
Figures are rendered with pyvista off-screen, or with matplotlib when pyvista cannot render.

``report.json``::

    {"runs": [{"run", "label", "collisions", "model" (collisions, or dem-no-contacts), "particle_contacts",
               "dt" (s), "diameter" (m), "end_time" (simulated s), "particles_per_parcel",
               "wall_clock_s" (sum of the per-step wall clock), "kernel_load_s" (Warp compilation, not in it),
               "collision_rate" (1/s or null), "collision_rate_per_stream_pair" {"left-right": 1/s, ...},
               "collision_rate_note" (why 0 or null), "overlap_pair_rate", "overlap_pair_rate_per_stream_pair",
               "total_collisions", "snapshots",
               "profiles": {"20": [{"section", "centres" (m), "mean_axial_velocity" (m/s, null where empty),
                                    "samples"}, ... ten sections], "88": [...], "126": [...]},
               "stream_metrics": {"window_s", "snapshots", "streams", "stream_sides", "axis_transverse",
                                  "sections": [{"section", "samples", "samples_per_stream", "crossing" {stream: f},
                                                "stream_crossing", "transverse_spread_mm" {stream: mm},
                                                "transverse_velocity_rms" (m/s),
                                                "transverse_velocity_rms_per_stream"}, ...],
                                  "stream_crossing", "transverse_velocity_rms", "transverse_spread_mm" (means over
                                  the sections), "composition" {"20": [{"section", "centres", "fractions"
                                  {stream: [...]}, "samples"}]}, "transverse_velocity_profiles" {"20": [{"section",
                                  "centres", "mean_transverse_velocity", "samples"}]}},
               only when a dem run is in the report: "dem_reference", "paper_experimental_uncertainty" (m/s: 0.63
               at 315 um, 0.71 at 475 um, else null) and, null or absent for the reference itself,
               "profile_rms_vs_dem" {"20": m/s, ...}, "stream_crossing_vs_dem" {"difference", "per_section",
               "sections_compared"}, "transverse_velocity_rms_vs_dem" {"relative_difference", "difference",
               "per_section", "sections_compared"}, "transverse_spread_vs_dem" {"difference_mm"},
               "stream_composition_vs_dem" {"20": RMS of fractions}, "transverse_velocity_profile_rms_vs_dem"
               {"20": m/s}, "collision_rate_vs_dem" (relative), "config_differences_vs_dem" [{"key", "dem",
               "run"}]}, ...],
     "summary_table": [{"label", "model", "diameter", "dt", "stream_crossing", "stream_crossing_vs_dem",
                        "transverse_velocity_rms", "transverse_velocity_rms_vs_dem", "collision_rate",
                        "collision_rate_vs_dem", "profile_rms_vs_dem" (first box count), "wall_clock_s"}, ...],
     "like_with_like": {"model_differences": [{"what", "dem", "hel", "intended", "measured" (optional)}], "wall_effect": [{"diameter",
                        "dt", "none", "dem_no_contacts", "stream_crossing_difference",
                        "transverse_velocity_rms_relative_difference", "transverse_spread_difference_mm",
                        "profile_rms"}], "wall_effect_note"},
     "boxes", "downstream_only", "from_time", "min_samples", "stream_window", "composition_section", "figures",
     "renderer"}
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
    raw_config: dict = field(default_factory=dict)
    """The ``config`` attrs as stored (``hel``, ``collision``, ``grid``, ``gas``, ``run``, ``case``): what the
    like-with-like comparison diffs."""
    kernel_load_s: float | None = None
    """Warp compilation / module loading before the timed steps, s (attrs ``kernel_load_s``; None: not recorded)."""

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
    # hel_warp.runs.run.Run layout: config = {hel, collision, grid, gas, capacity, run, case}, plus the case's
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
    kernel_load = attrs.get("kernel_load_s", config.get("kernel_load_s"))
    return RunData(path=str(path), label=path.name, config=config, times=np.asarray(times), snapshots=snapshots,
                   series=series, raw_config=raw,
                   kernel_load_s=float(kernel_load) if kernel_load is not None else None)


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


def profile_rms(a: list, b: list, *, min_samples: int = 1, key: str = "mean_axial_velocity") -> float | None:
    """RMS of the differences of two runs' profiles (of ``key``) over all sections and the sub-boxes where both runs
    have at least ``min_samples`` samples."""
    if len(a) != len(b):
        raise ConfigError(f"the runs have {len(a)} and {len(b)} sections; compare runs of the same rig")
    diffs = []
    for pa, pb in zip(a, b):
        if len(pa[key]) != len(pb[key]):
            raise ConfigError("profiles with different sub-box counts cannot be compared")
        na = pa.get("samples") or [min_samples] * len(pa[key])
        nb = pb.get("samples") or [min_samples] * len(pb[key])
        for ua, ub, ka, kb in zip(pa[key], pb[key], na, nb):
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


# ------------------------------------------------------------------------------------------ stream metrics
DEFAULT_STREAM_WINDOW = (0.5, 1.0)
"""The stream metrics average the snapshots from this fraction of each run's simulated time to that one: the
second half by default, when the streams have reached the sections and the release is under way."""
DEFAULT_COMPOSITION_SECTION = "S5"
"""The section whose stream composition the stacked-bar picture shows (the middle one of the ten)."""


def stream_layout(rig: dict) -> tuple:
    """({tag: name}, {tag: side}, axis) of the rig: side = the sign of (transverse position - axis) on the stream's
    own arm (left = +1), axis the transverse position of the main-channel axis (m; None: each section's centre).

    Runs written before the rig stored ``stream_sides`` read stream 0 = left = +1, stream 1 = right = -1, as
    ``cases/colliding_streams.py`` lays them out."""
    names = {int(k): str(v) for k, v in (rig.get("streams") or {"0": "left", "1": "right"}).items()}
    sides = {int(k): float(np.sign(v)) for k, v in (rig.get("stream_sides") or {"0": 1.0, "1": -1.0}).items()}
    axis = rig.get("axis_transverse")
    return names, sides, (None if axis is None else float(axis))


def _run_time(run: RunData) -> float:
    return float(run.config.get("simulated_time", run.config["end_time"]))


def stream_window(run: RunData, window=DEFAULT_STREAM_WINDOW) -> tuple:
    """(t_from, t_to) in s: the fractions ``window`` of the run's simulated time."""
    total = _run_time(run)
    return float(window[0]) * total, float(window[1]) * total


def _section_samples(run: RunData, section: dict, window_s: tuple) -> dict:
    """Every (snapshot, parcel) sample inside ``section`` from the snapshots in ``window_s``: transverse position
    ``y`` (m), transverse velocity ``v_y`` (m/s), ``weight``, ``stream``; ``snapshots`` = how many were used."""
    rig = run.rig
    transverse = int(rig["transverse_axis"])
    lo, hi = np.asarray(section["lo"], float), np.asarray(section["hi"], float)
    tol = 1e-9 * max(1.0, abs(window_s[1]))
    parts, used = [], 0
    for t, snap in zip(run.times, run.snapshots):
        if t < window_s[0] - tol or t > window_s[1] + tol:
            continue
        used += 1
        x = np.asarray(snap["x"], np.float64)
        if x.shape[0] == 0:
            continue
        inside = np.all((x >= lo) & (x < hi), axis=1)
        parts.append((x[inside, transverse], np.asarray(snap["v"], np.float64)[inside, transverse],
                      np.asarray(snap["weight"], np.float64)[inside], np.asarray(snap["stream"])[inside]))
    if parts:
        y, vy, w, tag = (np.concatenate(column) for column in zip(*parts))
    else:
        y, vy, w, tag = np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0, np.int32)
    return {"y": y, "v_y": vy, "weight": w, "stream": tag.astype(np.int64), "snapshots": used}


def _mean_or_none(values) -> float | None:
    kept = [v for v in values if v is not None]
    return float(np.mean(kept)) if kept else None


def section_stream_metrics(samples: dict, section: dict, transverse: int, names: dict, sides: dict,
                           axis: float | None, *, min_samples: int = 1) -> dict:
    """Stream metrics of one section from its samples (weights = real particles per parcel):

    - ``crossing[name]``: the weight fraction of the stream's samples on the far side of the channel axis from
      its own arm, ``sum_{side (y - axis) < 0} w / sum w``; ``stream_crossing`` the mean over the streams
      (0: both stay on their side, 1: they pass through each other, 1/2: mixed);
    - ``transverse_spread_mm[name]``: the weighted standard deviation of y, mm;
    - ``transverse_velocity_rms``: ``sqrt(sum w v_y^2 / sum w)`` over all samples, m/s (and per stream).
    A stream (a section) with fewer than ``min_samples`` samples gets None."""
    lo, hi = float(section["lo"][transverse]), float(section["hi"][transverse])
    centre = 0.5 * (lo + hi) if axis is None else axis
    y, vy, w, tag = samples["y"], samples["v_y"], samples["weight"], samples["stream"]
    crossing, spread, rms_stream, counts = {}, {}, {}, {}
    for s in sorted(set(names) | set(np.unique(tag).tolist())):
        name = names.get(s, str(s))
        keep = tag == s
        n, ws = int(keep.sum()), w[keep]
        counts[name] = n
        if n < min_samples or ws.sum() <= 0:
            crossing[name] = spread[name] = rms_stream[name] = None
            continue
        ys = y[keep]
        mean_y = float(np.sum(ws * ys) / ws.sum())
        spread[name] = 1e3 * float(np.sqrt(np.sum(ws * (ys - mean_y) ** 2) / ws.sum()))
        rms_stream[name] = float(np.sqrt(np.sum(ws * vy[keep] ** 2) / ws.sum()))
        side = sides.get(s)
        crossing[name] = (float(np.sum(ws[side * (ys - centre) < 0.0]) / ws.sum()) if side else None)
    total_ok = len(w) >= min_samples and w.sum() > 0
    return {"section": section.get("name", ""), "samples": int(len(w)), "samples_per_stream": counts,
            "crossing": crossing, "stream_crossing": _mean_or_none(crossing.values()),
            "transverse_spread_mm": spread,
            "transverse_velocity_rms": float(np.sqrt(np.sum(w * vy**2) / w.sum())) if total_ok else None,
            "transverse_velocity_rms_per_stream": rms_stream}


def section_box_profiles(samples: dict, section: dict, transverse: int, boxes: int, names: dict) -> tuple:
    """(stream composition, transverse velocity profile) of one section over ``boxes`` sub-boxes across the
    channel: per sub-box the weight fraction of each stream, ``W_bs / sum_s W_bs``, and the weighted mean v_y
    (None where empty), with the sample counts."""
    lo, hi = float(section["lo"][transverse]), float(section["hi"][transverse])
    edges = np.linspace(lo, hi, boxes + 1)
    y, vy, w, tag = samples["y"], samples["v_y"], samples["weight"], samples["stream"]
    index = np.clip(np.searchsorted(edges, y, side="right") - 1, 0, boxes - 1)
    weight = np.zeros(boxes)
    np.add.at(weight, index, w)
    momentum = np.zeros(boxes)
    np.add.at(momentum, index, w * vy)
    count = np.bincount(index, minlength=boxes) if len(index) else np.zeros(boxes, np.int64)
    fractions = {}
    for s in sorted(set(names) | set(np.unique(tag).tolist())):
        ws = np.zeros(boxes)
        np.add.at(ws, index[tag == s], w[tag == s])
        fractions[names.get(s, str(s))] = [float(ws[b] / weight[b]) if weight[b] > 0 else None for b in range(boxes)]
    centres = (0.5 * (edges[:-1] + edges[1:])).tolist()
    composition = {"section": section.get("name", ""), "centres": centres, "fractions": fractions,
                   "samples": count.tolist()}
    velocity = {"section": section.get("name", ""), "centres": centres, "samples": count.tolist(),
                "mean_transverse_velocity": [float(momentum[b] / weight[b]) if weight[b] > 0 else None
                                             for b in range(boxes)]}
    return composition, velocity


def stream_metrics(run: RunData, boxes, *, window=DEFAULT_STREAM_WINDOW, min_samples: int = 1) -> dict:
    """The stream metrics of ``run`` per section (see :func:`section_stream_metrics`, :func:`section_box_profiles`)
    over the snapshots of ``window``, and their means over the sections that have a value."""
    rig = run.rig
    transverse = int(rig["transverse_axis"])
    names, sides, axis = stream_layout(rig)
    window_s = stream_window(run, window)
    sections, composition, velocity = [], {str(b): [] for b in boxes}, {str(b): [] for b in boxes}
    used = 0
    for section in rig["sections"]:
        samples = _section_samples(run, section, window_s)
        used = samples["snapshots"]
        sections.append(section_stream_metrics(samples, section, transverse, names, sides, axis,
                                               min_samples=min_samples))
        for b in boxes:
            comp, vel = section_box_profiles(samples, section, transverse, int(b), names)
            composition[str(b)].append(comp)
            velocity[str(b)].append(vel)
    stream_names = list(sections[0]["crossing"]) if sections else []
    return {"window_s": list(window_s), "snapshots": used, "streams": {str(k): v for k, v in names.items()},
            "stream_sides": {names.get(k, str(k)): v for k, v in sides.items()}, "axis_transverse": axis,
            "sections": sections,
            "stream_crossing": _mean_or_none(s["stream_crossing"] for s in sections),
            "transverse_velocity_rms": _mean_or_none(s["transverse_velocity_rms"] for s in sections),
            "transverse_spread_mm": {n: _mean_or_none(s["transverse_spread_mm"].get(n) for s in sections)
                                     for n in stream_names},
            "composition": composition, "transverse_velocity_profiles": velocity}


def composition_rms(a: list, b: list, *, min_samples: int = 1) -> float | None:
    """RMS of the differences of two runs' stream fractions over the sections, the sub-boxes where both have at
    least ``min_samples`` samples and every stream either names."""
    diffs = []
    for ca, cb in zip(a, b):
        for name in set(ca["fractions"]) | set(cb["fractions"]):
            fa = ca["fractions"].get(name) or [0.0] * len(ca["samples"])
            fb = cb["fractions"].get(name) or [0.0] * len(cb["samples"])
            for va, vb, na, nb in zip(fa, fb, ca["samples"], cb["samples"]):
                if va is not None and vb is not None and na >= min_samples and nb >= min_samples:
                    diffs.append(va - vb)
    return float(np.sqrt(np.mean(np.square(diffs)))) if diffs else None


def _relative(value, reference):
    return None if value is None or reference is None or reference == 0 else (value - reference) / reference


def stream_metrics_vs(metrics: dict, ref: dict, boxes, *, min_samples: int = 1) -> dict:
    """``*_vs_dem`` of a run's stream metrics against a reference's, over the sections where both have a value:
    crossing as a difference (model - reference; target 0.05), transverse rms velocity as a relative difference
    (target 5 %), spread per stream as a difference (mm), composition and v_y profiles as RMS over sub-boxes."""
    out = {}
    pairs = list(zip(metrics["sections"], ref["sections"]))
    diffs = [None if a["stream_crossing"] is None or b["stream_crossing"] is None
             else a["stream_crossing"] - b["stream_crossing"] for a, b in pairs]
    out["stream_crossing_vs_dem"] = {"difference": _mean_or_none(diffs), "per_section": diffs,
                                     "sections_compared": sum(d is not None for d in diffs)}
    both = [(a["transverse_velocity_rms"], b["transverse_velocity_rms"]) for a, b in pairs
            if a["transverse_velocity_rms"] is not None and b["transverse_velocity_rms"] is not None]
    mean_a = float(np.mean([p[0] for p in both])) if both else None
    mean_b = float(np.mean([p[1] for p in both])) if both else None
    out["transverse_velocity_rms_vs_dem"] = {
        "relative_difference": _relative(mean_a, mean_b),
        "difference": None if mean_a is None else mean_a - mean_b,
        "per_section": [_relative(a["transverse_velocity_rms"], b["transverse_velocity_rms"]) for a, b in pairs],
        "sections_compared": len(both)}
    spread = {}
    for name in metrics["transverse_spread_mm"]:
        d = [a["transverse_spread_mm"].get(name) - b["transverse_spread_mm"].get(name) for a, b in pairs
             if a["transverse_spread_mm"].get(name) is not None and b["transverse_spread_mm"].get(name) is not None]
        spread[name] = float(np.mean(d)) if d else None
    out["transverse_spread_vs_dem"] = {"difference_mm": spread}
    out["stream_composition_vs_dem"] = {str(b): composition_rms(metrics["composition"][str(b)],
                                                                ref["composition"][str(b)], min_samples=min_samples)
                                        for b in boxes}
    out["transverse_velocity_profile_rms_vs_dem"] = {
        str(b): profile_rms(metrics["transverse_velocity_profiles"][str(b)], ref["transverse_velocity_profiles"][str(b)],
                            min_samples=min_samples, key="mean_transverse_velocity") for b in boxes}
    return out


# ------------------------------------------------------------------------------------------ collision rates
REAL_COLLISIONS = "collisions_collisions"
"""Series of real binary collisions per step (``counts()['collisions']``: ``dem`` contact onsets between spheres
during the sub-steps; ``surrogate`` resolved collisions, each min(w_i, w_j) real ones); per stream pair
``collisions_collisions_<a>_<b>``."""
OVERLAP_PAIRS = "collisions_detected_pairs"
"""Series of parcel pairs overlapping at the end of a step (``counts()['detected_pairs']``); per stream pair
``collisions_detected_pairs_<a>_<b>``. Not a collision rate: it depends on dt and on how long contacts last."""
COLLISION_SERIES = OVERLAP_PAIRS  # the series name that older run directories carry


def _pair_rates(run: RunData, prefix: str, total_time: float) -> dict:
    """{"left-right": 1/s, ...} from the series ``<prefix>_<a>_<b>``: every pair of named streams, and any other
    pair that counted something."""
    import re

    names = stream_layout(run.rig)[0]
    pattern = re.compile(rf"^{re.escape(prefix)}_(\d+)_(\d+)$")
    rates = {}
    for series_name, values in sorted(run.series.items()):
        match = pattern.match(series_name)
        if not match:
            continue
        a, b = int(match.group(1)), int(match.group(2))
        total = float(np.sum(values))
        if (a in names and b in names) or total:
            rates[f"{names.get(a, str(a))}-{names.get(b, str(b))}"] = total / total_time
    return rates


def collision_rates(run: RunData) -> dict:
    """Real collision rate (1/s of simulated time) and the per-stream-pair rates, beside the rate of pairs
    overlapping at step ends; ``collision_rate_note`` says why a rate is 0 or null."""
    model = run.config["collisions"]
    total_time = _run_time(run)
    out = {"collision_rate": None, "collision_rate_per_stream_pair": None, "collision_rate_note": None,
           "overlap_pair_rate": None, "overlap_pair_rate_per_stream_pair": None}
    if total_time <= 0:
        out["collision_rate_note"] = "the run simulated no time"
        return out
    if OVERLAP_PAIRS in run.series:
        out["overlap_pair_rate"] = float(np.sum(run.series[OVERLAP_PAIRS])) / total_time
        out["overlap_pair_rate_per_stream_pair"] = _pair_rates(run, OVERLAP_PAIRS, total_time)
    if REAL_COLLISIONS in run.series:
        out["collision_rate"] = float(np.sum(run.series[REAL_COLLISIONS])) / total_time
        out["collision_rate_per_stream_pair"] = _pair_rates(run, REAL_COLLISIONS, total_time)
        if run.config.get("particle_contacts") is False:
            out["collision_rate_note"] = "dem with particle-particle contacts off: no collision can happen"
    elif model == "none":
        out["collision_rate"] = 0.0
        out["collision_rate_note"] = "none resolves no particle-particle collision (rate 0 by construction)"
    elif model == "ktgf":
        out["collision_rate_note"] = ("ktgf acts through a continuum solids pressure and counts no collision; "
                                      "its rate is undefined (null)")
    else:
        out["collision_rate_note"] = (f"the run has no series {REAL_COLLISIONS} (real collisions, written by "
                                      "engines whose strategy counts() reports 'collisions'); rerun it with such an "
                                      "engine. overlap_pair_rate holds the pairs overlapping at step ends")
    return out


def collision_rate(run: RunData) -> float | None:
    """Real binary collisions per simulated second (:func:`collision_rates`)."""
    return collision_rates(run)["collision_rate"]


# ------------------------------------------------------------------------------------------ like with like
MODEL_DIFFERENCES = (
    {"what": "particle-particle collisions", "intended": True,
     "dem": "Hertz-Mindlin contacts between the spheres, resolved at the DEM step (eq. 12)",
     "hel": "the collision model under test (none, ktgf, surrogate, ...)"},
    {"what": "walls", "intended": False,
     "dem": "Hertz-Mindlin sphere-wall contact against the SDF at every DEM sub-step: the sphere meets the wall with "
            "its surface (radius), normal restitution from the wall dashpot (Material.wall_restitution_normal), "
            "Coulomb friction of the material, rolling carried by the spin",
     "hel": "reflection of the parcel (kernels/reflect.py) where its surface meets the wall (HelConfig.wall_contact "
            "'surface', the rig's default; 'point': where its centre does): at its crossing within the step, in time "
            "order with the collisions (the surrogate's swept detection with wall events, its default), else once "
            "per step at the step's end; e_n, e_t "
            "(Material.wall_restitution_*), tangential loss capped by Coulomb friction (HelConfig.wall_friction); no "
            "spin",
     "measured": "single impacts on a plane wall (hel-warp impact --target wall, 315 and 475 um, 1-5 m/s): the dem "
                 "wall keeps 0.60-0.70 of the tangential speed at 20-60 deg incidence (the sphere leaves rolling), "
                 "the HEL reflection 0.8 (Table 1) until the Coulomb cap; HEL walls at e_t = 5/7 on the mixture rig "
                 "(16 seeds, 1e-3 s) gave the 475 um class's transverse rms +14.9 +- 7.5 % of the dem's against "
                 "+17.2 +- 7.0 % at 0.8 (python -m hel_warp.studies.rig_ensemble)"},
    {"what": "parcel integration", "intended": False,
     "dem": "velocity-Verlet sub-steps at the DEM step with the fluid acceleration of the push held over the fluid "
            "step (same fluid impulse per step)",
     "hel": "one implicit drag-exchange push per fluid step"},
    {"what": "parcel weight", "intended": False,
     "dem": "every parcel one real sphere (weight 1)",
     "hel": "parcels of any weight (--particles-per-parcel)"},
)
"""What still differs between the ``dem`` reference and an HEL run besides the particle-particle collisions
(injection, drag law and exchange, gas solver, wall restitution and friction values are shared)."""
_NOT_A_DIFFERENCE = ("collision", "run", "case.collisions", "case.model", "case.force", "case.particle_contacts",
                     "case.model_metadata", "case.collision_counts_available", "case.options.collisions",
                     "case.options.model", "case.options.force", "case.options.no_particle_contacts")
"""Config keys that name the collision model or follow from it, or are run/output settings: never listed."""


def _flatten(value, prefix: str = "") -> dict:
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: value}


def config_differences(run: RunData, ref: RunData) -> list:
    """Settings in which ``run`` and ``ref`` differ, other than the collision model and the run/output settings:
    [{"key": "hel.material.friction", "dem": ..., "run": ...}, ...]."""
    a, b = _flatten(run.raw_config), _flatten(ref.raw_config)
    out = []
    for key in sorted(set(a) | set(b)):
        if any(key == skip or key.startswith(skip + ".") for skip in _NOT_A_DIFFERENCE):
            continue
        if a.get(key) != b.get(key):
            out.append({"key": key, "dem": b.get(key), "run": a.get(key)})
    return out


def model_name(config: dict) -> str:
    """The model a run stands for in tables and pictures: ``collisions``, ``dem-no-contacts`` for a dem run with
    the particle-particle contacts off, and the surrogate's ``detection`` where the run records one."""
    name = str(config["collisions"])
    if name == "dem" and config.get("particle_contacts") is False:
        return "dem-no-contacts"
    if name == "surrogate" and config.get("detection"):  # surrogate-paper keeps the paper's overlap test
        return f"{name}/{config['detection']}"
    return name


def _sizes(config: dict) -> tuple:
    """(diameter, diameter2, mass fraction 2) of a run, m; (d, None, None) for one size."""
    d2 = config.get("diameter2")
    return (round(float(config["diameter"]), 12), None if d2 is None else round(float(d2), 12),
            None if d2 is None else round(float(config.get("mass_fraction2") or 0.0), 9))


def sizes_label(config: dict) -> str:
    """``315 um``, or ``315/475 um (mass fraction 0.5 of 475 um)`` for a mixture."""
    d, d2, f2 = _sizes(config)
    if d2 is None:
        return f"{d * 1e6:.0f} um"
    return f"{d * 1e6:.0f}/{d2 * 1e6:.0f} um (mass fraction {f2:g} of {d2 * 1e6:.0f} um)"


def _same_size_and_step(a: RunData, b: RunData) -> bool:
    return _sizes(a.config) == _sizes(b.config) and abs(float(a.config["dt"]) - float(b.config["dt"])) <= 1e-12


# ------------------------------------------------------------------------------------------ size classes
def size_classes(run: RunData) -> list | None:
    """The species of a mixture run (``rig.size_classes``: diameter, diameter_std, parcels, particles_per_parcel),
    or None."""
    classes = run.rig.get("size_classes") if isinstance(run.rig, dict) else None
    return classes or None


def size_class_view(run: RunData, k: int) -> RunData:
    """``run`` with only the parcels of size class ``k`` in its snapshots (each parcel put in the class of the
    nearest mean diameter in units of its standard deviation, ``hel_warp.collisions.mixture.species_of``)."""
    from hel_warp.collisions.mixture import species_of

    classes = size_classes(run)
    means = [float(c["diameter"]) for c in classes]
    stds = [float(c.get("diameter_std") or 0.0) for c in classes]
    snaps = []
    for snap in run.snapshots:
        if "radius" not in snap:
            raise ConfigError(f"{run.path}: snapshots lack 'radius'; the size classes of a mixture need it")
        keep = species_of(2.0 * np.asarray(snap["radius"], np.float64), means, stds) == k
        snaps.append({name: np.asarray(arr)[keep] for name, arr in snap.items()})
    return RunData(path=run.path, label=f"{run.label}[{means[k] * 1e6:.0f}um]", config=run.config, times=run.times,
                   snapshots=snaps, series=run.series, raw_config=run.raw_config, kernel_load_s=run.kernel_load_s)


def size_class_entries(run: RunData, ref: RunData | None, boxes, *, downstream_only: bool, from_time: float,
                       window, min_samples: int) -> list:
    """Per size class of a mixture run: its profiles and stream metrics, and against the same class of the dem
    reference (a mixture run of the same sizes) the axial RMS, crossing and v_y rms differences."""
    out = []
    for k, c in enumerate(size_classes(run)):
        view = size_class_view(run, k)
        prof = {str(b): profiles(view, b, downstream_only=downstream_only, from_time=from_time) for b in boxes}
        metrics = stream_metrics(view, boxes, window=window, min_samples=min_samples)
        entry = {"diameter": float(c["diameter"]), "label": f"{float(c['diameter']) * 1e6:.0f} um",
                 "particles_per_parcel": c.get("particles_per_parcel"),  # None: a run directory written without per-species weights
                 "paper_experimental_uncertainty": paper_uncertainty(float(c["diameter"])),
                 "profiles": prof, "stream_metrics": metrics}
        if ref is not None and ref is not run and size_classes(ref) is not None:
            ref_view = size_class_view(ref, k)
            ref_prof = {str(b): profiles(ref_view, b, downstream_only=downstream_only, from_time=from_time)
                        for b in boxes}
            ref_metrics = stream_metrics(ref_view, boxes, window=window, min_samples=min_samples)
            entry["profile_rms_vs_dem"] = {str(b): profile_rms(prof[str(b)], ref_prof[str(b)],
                                                               min_samples=min_samples) for b in boxes}
            entry.update(stream_metrics_vs(metrics, ref_metrics, boxes, min_samples=min_samples))
        out.append(entry)
    return out


def wall_effect(runs: list, metrics: dict, all_profiles: dict, boxes, *, min_samples: int) -> list:
    """Per (diameter, dt) with a ``none`` run and a ``dem-no-contacts`` run: the gap the walls (and the parcel
    integration) alone make, in the stream metrics and the axial profiles (dem-no-contacts - none)."""
    out = []
    for free in [r for r in runs if model_name(r.config) == "none"]:
        for walls in [r for r in runs if model_name(r.config) == "dem-no-contacts" and _same_size_and_step(r, free)]:
            vs = stream_metrics_vs(metrics[free.path], metrics[walls.path], boxes, min_samples=min_samples)
            out.append({"diameter": float(free.config["diameter"]), "dt": float(free.config["dt"]),
                        "none": free.label, "dem_no_contacts": walls.label,
                        "stream_crossing_difference": vs["stream_crossing_vs_dem"]["difference"],
                        "transverse_velocity_rms_relative_difference":
                            vs["transverse_velocity_rms_vs_dem"]["relative_difference"],
                        "transverse_spread_difference_mm": vs["transverse_spread_vs_dem"]["difference_mm"],
                        "profile_rms": {str(b): profile_rms(all_profiles[free.path][str(b)],
                                                            all_profiles[walls.path][str(b)],
                                                            min_samples=min_samples) for b in boxes},
                        "sign": "none minus dem-no-contacts, as a model minus the dem reference"})
    return out


def _dem_reference(run: RunData, runs: list) -> RunData | None:
    """The ``dem`` run (contacts on) to compare ``run`` with: same particle diameter (required; a mixture: the same
    sizes and mass fraction), same dt preferred."""
    dems = [r for r in runs if model_name(r.config) == "dem" and _sizes(r.config) == _sizes(run.config)]
    if not dems:
        return None
    return sorted(dems, key=lambda r: abs(float(r.config["dt"]) - float(run.config["dt"])) > 1e-12)[0]


# ------------------------------------------------------------------------------------------ the summary table
MODEL_ORDER = ("none", "ktgf", "surrogate", "surrogate-paper", "dem-no-contacts", "dem")
SUMMARY_COLUMNS = (("model", "model", "{}"), ("stream_crossing", "crossing", "{:.3f}"),
                   ("stream_crossing_vs_dem", "d crossing", "{:+.3f}"),
                   ("transverse_velocity_rms", "v_y rms m/s", "{:.3f}"),
                   ("transverse_velocity_rms_vs_dem", "v_y rms vs dem", "{:+.1%}"),
                   ("collision_rate", "collisions 1/s", "{:.4g}"), ("collision_rate_vs_dem", "vs dem", "{:+.1%}"),
                   ("profile_rms_vs_dem", "axial RMS m/s", "{:.3f}"), ("wall_clock_s", "wall s", "{:.1f}"))
"""(row key, heading, format) of the summary table: per (diameter, dt) the numbers a collision model is judged by."""


def _model_rank(name: str) -> tuple:
    base = name.split("/")[0].split(" [")[0]
    return (MODEL_ORDER.index(base) if base in MODEL_ORDER else len(MODEL_ORDER), name)


def summary_rows(report: dict) -> list:
    """One row per run, sorted by diameter, dt (largest first) and model: the columns of :data:`SUMMARY_COLUMNS`."""
    boxes = str(report["boxes"][0])
    rows = []
    for e in report["runs"]:
        sm = e["stream_metrics"]
        rms = e.get("profile_rms_vs_dem")
        sizes = e.get("sizes") or f"{e['diameter'] * 1e6:.0f} um"
        rows.append({"label": e["label"], "model": e["model"], "diameter": e["diameter"], "dt": e["dt"],
                     "sizes": sizes,
                     "stream_crossing": sm["stream_crossing"],
                     "stream_crossing_vs_dem": (e.get("stream_crossing_vs_dem") or {}).get("difference"),
                     "transverse_velocity_rms": sm["transverse_velocity_rms"],
                     "transverse_velocity_rms_vs_dem":
                         (e.get("transverse_velocity_rms_vs_dem") or {}).get("relative_difference"),
                     "collision_rate": e["collision_rate"], "collision_rate_vs_dem": e.get("collision_rate_vs_dem"),
                     "profile_rms_vs_dem": rms.get(boxes) if rms else None, "wall_clock_s": e["wall_clock_s"]})
        for c in e.get("size_classes") or []:  # a mixture: one row per size class beside the run's own
            csm, crms = c["stream_metrics"], c.get("profile_rms_vs_dem")
            rows.append({"label": f"{e['label']}[{c['label']}]", "model": f"{e['model']} [{c['label']}]",
                         "diameter": e["diameter"], "dt": e["dt"], "sizes": sizes,
                         "stream_crossing": csm["stream_crossing"],
                         "stream_crossing_vs_dem": (c.get("stream_crossing_vs_dem") or {}).get("difference"),
                         "transverse_velocity_rms": csm["transverse_velocity_rms"],
                         "transverse_velocity_rms_vs_dem":
                             (c.get("transverse_velocity_rms_vs_dem") or {}).get("relative_difference"),
                         "collision_rate": None, "collision_rate_vs_dem": None,
                         "profile_rms_vs_dem": crms.get(boxes) if crms else None, "wall_clock_s": None})
    return sorted(rows, key=lambda r: (r["diameter"], r["sizes"], -r["dt"], _model_rank(r["model"])))


def format_summary_table(rows: list, *, boxes=None) -> str:
    """The summary rows as Markdown tables, one per (diameter, dt); '-' where a value is null."""
    lines = []
    groups = []
    for r in rows:
        key = (r.get("sizes") or f"{r['diameter'] * 1e6:.0f} um", r["dt"])
        if key not in groups:
            groups.append(key)
    for sizes, dt in groups:
        lines.append(f"d = {sizes}, dt = {dt:g} s"
                     + (f" (axial RMS over {boxes} sub-boxes)" if boxes else ""))
        lines.append("| " + " | ".join(h for _, h, _ in SUMMARY_COLUMNS) + " |")
        lines.append("|" + "|".join("---" for _ in SUMMARY_COLUMNS) + "|")
        for r in rows:
            if (r.get("sizes") or f"{r['diameter'] * 1e6:.0f} um", r["dt"]) != (sizes, dt):
                continue
            cells = ["-" if r[key] is None else fmt.format(r[key]) for key, _, fmt in SUMMARY_COLUMNS]
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------ the report
def _check_window(window) -> tuple:
    try:
        lo, hi = (float(v) for v in window)
    except (TypeError, ValueError):
        raise ConfigError(f"--stream-window needs two fractions FROM TO of the run time (got {window!r})") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo <= hi <= 1.0):
        raise ConfigError(f"--stream-window must satisfy 0 <= FROM <= TO <= 1 (fractions of each run's simulated "
                          f"time; got {lo:g} {hi:g}); e.g. 0.5 1 for the second half")
    return lo, hi


def build_report(run_dirs: list, *, boxes=DEFAULT_BOXES, downstream_only: bool = False,
                 from_time: float = 0.0, min_samples: int = DEFAULT_MIN_SAMPLES,
                 stream_window=DEFAULT_STREAM_WINDOW, composition_section: str = DEFAULT_COMPOSITION_SECTION) -> tuple:
    """(the report.json document, the loaded ``RunData``s) for ``run_dirs``; no files written."""
    if not run_dirs:
        raise ConfigError("give at least one run directory")
    boxes = [int(b) for b in boxes]
    if int(min_samples) < 1:
        raise ConfigError(f"--min-samples must be >= 1 (got {min_samples})")
    if any(b < 1 for b in boxes):
        raise ConfigError(f"--boxes must be positive integers (got {boxes})")
    window = _check_window(stream_window)
    runs = [load_run(d) for d in run_dirs]
    section_names = [s.get("name", "") for s in runs[0].rig["sections"]]
    if composition_section not in section_names:
        raise ConfigError(f"--composition-section {composition_section!r} is not a section of the rig; choose one "
                          f"of {', '.join(section_names)}")
    labels = [r.label for r in runs]
    for i, r in enumerate(runs):  # unique labels for the figures
        if labels.count(r.label) > 1:
            r.label = f"{r.label}_{i}"
    all_profiles = {r.path: {str(b): profiles(r, b, downstream_only=downstream_only, from_time=from_time)
                             for b in boxes} for r in runs}
    metrics = {r.path: stream_metrics(r, boxes, window=window, min_samples=int(min_samples)) for r in runs}
    entries = []
    for r in runs:
        c = r.config
        entry = {"run": r.path, "label": r.label, "collisions": c["collisions"], "model": model_name(c),
                 "particle_contacts": c.get("particle_contacts"), "dt": float(c["dt"]),
                 "diameter": float(c["diameter"]), "end_time": float(c["end_time"]),
                 "particles_per_parcel": c.get("particles_per_parcel"),
                 "wall_clock_s": (float(c["wall_clock_s"]) if c.get("wall_clock_s") is not None else None),
                 "kernel_load_s": r.kernel_load_s,
                 **collision_rates(r),
                 "total_collisions": c.get("total_collisions"),
                 "snapshots": len(r.snapshots), "profiles": all_profiles[r.path], "stream_metrics": metrics[r.path]}
        ref = _dem_reference(r, runs)
        if ref is not None:
            entry["dem_reference"] = ref.label
            entry["paper_experimental_uncertainty"] = paper_uncertainty(c["diameter"])
            if ref is r:
                entry["profile_rms_vs_dem"] = None
            else:
                entry["profile_rms_vs_dem"] = {str(b): profile_rms(all_profiles[r.path][str(b)],
                                                                   all_profiles[ref.path][str(b)],
                                                                   min_samples=int(min_samples)) for b in boxes}
                entry.update(stream_metrics_vs(metrics[r.path], metrics[ref.path], boxes,
                                               min_samples=int(min_samples)))
                entry["collision_rate_vs_dem"] = _relative(entry["collision_rate"], collision_rate(ref))
                entry["config_differences_vs_dem"] = config_differences(r, ref)
        if size_classes(r) is not None:
            entry["sizes"] = sizes_label(c)
            entry["size_classes"] = size_class_entries(r, ref, boxes, downstream_only=downstream_only,
                                                       from_time=from_time, window=window,
                                                       min_samples=int(min_samples))
        entries.append(entry)
    effect = wall_effect(runs, metrics, all_profiles, boxes, min_samples=int(min_samples))
    report = {
        "runs": entries, "boxes": boxes, "downstream_only": bool(downstream_only), "from_time": from_time,
        "min_samples": int(min_samples), "stream_window": list(window), "composition_section": composition_section,
        "velocity": "mean axial (downstream) particle velocity, m/s, weighted by parcel weight",
        "profile_rms_vs_dem": "m/s, RMS over the ten sections and the sub-boxes where both runs have at least "
                              "min_samples samples",
        "stream_metrics": "per section, over the snapshots of stream_window (fractions of each run's simulated "
                          "time), weighted by parcel weight: crossing = fraction of a stream on the far side of the "
                          "channel axis from its own arm (0 stay, 1 pass through each other, 0.5 mixed), "
                          "stream_crossing its mean over the streams; transverse_spread_mm = std of y per stream; "
                          "transverse_velocity_rms = sqrt(mean v_y^2), m/s; composition = stream fractions per "
                          "sub-box; run values are means over the sections with at least min_samples samples",
        "vs_dem": "stream_crossing_vs_dem: difference (target |d| <= 0.05); transverse_velocity_rms_vs_dem and "
                  "collision_rate_vs_dem: relative differences (targets 5 %, 15 %); composition and v_y profiles: "
                  "RMS over sub-boxes",
        "collision_rate": "real binary collisions per simulated second (dem: contact onsets between spheres; "
                          "surrogate: resolved collisions, min(w_i, w_j) each); overlap_pair_rate: pairs found "
                          "overlapping at step ends per simulated second (depends on dt)",
        "like_with_like": {
            "model_differences": list(MODEL_DIFFERENCES),
            "wall_effect": effect,
            "wall_effect_note": None if effect else (
                "to measure how much of a gap the walls make, add a `none` run and a dem run with "
                "--no-particle-contacts of the same size and step to the report")}}
    report["summary_table"] = summary_rows(report)
    return report, runs


def write_report(run_dirs: list, out_dir: str, *, boxes=DEFAULT_BOXES, downstream_only: bool = False,
                 from_time: float = 0.0, figures: bool = True, min_samples: int = DEFAULT_MIN_SAMPLES,
                 stream_window=DEFAULT_STREAM_WINDOW, composition_section: str = DEFAULT_COMPOSITION_SECTION) -> dict:
    """Write ``out_dir/report.json``, ``out_dir/summary.md`` and the PNG figures; returns the report document."""
    report, runs = build_report(run_dirs, boxes=boxes, downstream_only=downstream_only, from_time=from_time,
                                min_samples=min_samples, stream_window=stream_window,
                                composition_section=composition_section)
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
        written.append(_plot_bars(report, "collision_rate", "real collisions, 1/s",
                                  os.path.join(out_dir, "collision_rate.png")))
        written.append(_plot_bars(report, "overlap_pair_rate", "pairs overlapping at step ends, 1/s",
                                  os.path.join(out_dir, "overlap_pair_rate.png")))
        written.append(_plot_per_section(report, "stream_crossing", "stream crossing (0 stay, 1 cross, 0.5 mixed)",
                                         os.path.join(out_dir, "stream_crossing.png")))
        written.append(_plot_per_section(report, "transverse_velocity_rms", "transverse velocity rms, m/s",
                                         os.path.join(out_dir, "transverse_velocity_rms.png")))
        written.append(_plot_composition(report, os.path.join(
            out_dir, f"stream_composition_{report['composition_section']}.png")))
        written.append(_plot_summary_table(report, os.path.join(out_dir, "summary_table.png")))
        report["renderer"] = renderer.used
    report["figures"] = [os.path.basename(p) for p in written if p]
    with open(os.path.join(out_dir, "summary.md"), "w") as fh:
        fh.write(format_summary_table(report["summary_table"], boxes=report["boxes"][0]))
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


def _save(plt, fig, path: str, dpi: int = 100) -> str:
    """Lay out, write and close one figure; its path."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


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
    return _save(plt, fig, path, dpi=110)


def _mpl_volume_fraction(run: RunData, path: str) -> str:
    plt = _mpl()
    image, extent = _volume_fraction_image(run)
    fig, ax = plt.subplots(figsize=(12, 5))
    im = ax.imshow(image.T, origin="lower", extent=extent, cmap="viridis")
    fig.colorbar(im, ax=ax, label="log10 eps_s")
    ax.set_title(f"{run.label}: solid volume fraction, t = {run.times[-1]:.4g} s")
    return _save(plt, fig, path, dpi=110)


def _plot_profiles(report: dict, boxes: int, path: str) -> str:
    plt = _mpl()
    fig, axes = plt.subplots(2, 5, figsize=(18, 7), sharey=True)
    for entry in report["runs"]:
        for k, prof in enumerate(entry["profiles"][str(boxes)][:10]):
            u = np.array([np.nan if v is None else v for v in prof["mean_axial_velocity"]])
            axes.flat[k].plot(np.asarray(prof["centres"]) * 1e3, u, ".-", ms=3,
                              label=f"{entry['model']} d={entry['diameter'] * 1e6:.0f}um dt={entry['dt']:g}")
            axes.flat[k].set_title(prof["section"])
    for ax in axes[-1]:
        ax.set_xlabel("y, mm")
    for ax in axes[:, 0]:
        ax.set_ylabel("mean axial velocity, m/s")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(f"time-averaged particle velocity profiles, {boxes} sub-boxes"
                 + (" (downstream-moving only)" if report["downstream_only"] else ""))
    return _save(plt, fig, path)


def _plot_bars(report: dict, key: str, ylabel: str, path: str) -> str:
    """Bars grouped by (diameter, dt), one bar per collision model (Figs. 12, 22, 23)."""
    plt = _mpl()
    groups = sorted({(e["diameter"], e["dt"]) for e in report["runs"]}, key=lambda g: (g[0], -g[1]))
    models = sorted({e["model"] for e in report["runs"]}, key=_model_rank)
    fig, ax = plt.subplots(figsize=(max(6, 1.6 * len(groups) * max(1, len(models)) / 2), 4.5))
    width = 0.8 / max(1, len(models))
    for m, model in enumerate(models):
        values = []
        for g in groups:
            vals = [e[key] for e in report["runs"] if (e["diameter"], e["dt"]) == g and e["model"] == model
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
    return _save(plt, fig, path)


def _run_label(entry: dict) -> str:
    return f"{entry['model']} d={entry['diameter'] * 1e6:.0f}um dt={entry['dt']:g}"


def _plot_per_section(report: dict, key: str, ylabel: str, path: str) -> str:
    """One line per run over the ten sections (stream crossing, transverse rms velocity); empty sections are gaps."""
    plt = _mpl()
    fig, ax = plt.subplots(figsize=(9, 4.5))
    for entry in sorted(report["runs"], key=lambda e: _model_rank(e["model"])):
        sections = entry["stream_metrics"]["sections"]
        values = [np.nan if s[key] is None else s[key] for s in sections]
        style = "k-" if entry["model"] == "dem" else ".-"
        ax.plot(np.arange(1, len(sections) + 1), values, style, ms=5, label=_run_label(entry))
    if key == "stream_crossing":
        ax.axhline(0.5, color="grey", lw=0.8, ls="--")
        ax.set_ylim(-0.02, 1.02)
    ax.set_xticks(np.arange(1, 11))
    ax.set_xticklabels([f"S{k}" for k in range(1, 11)])
    ax.set_xlabel("section")
    ax.set_ylabel(ylabel)
    window = report["stream_window"]
    ax.set_title(f"{ylabel} per section, snapshots from {window[0]:g} to {window[1]:g} of each run's time")
    ax.legend(fontsize=7)
    return _save(plt, fig, path)


def _plot_composition(report: dict, path: str) -> str:
    """Stacked bars of the stream fractions per sub-box of the chosen section, one panel per run."""
    plt = _mpl()
    name, boxes = report["composition_section"], str(report["boxes"][0])
    entries = sorted(report["runs"], key=lambda e: (e["diameter"], -e["dt"], _model_rank(e["model"])))
    fig, axes = plt.subplots(len(entries), 1, figsize=(9, 1.8 + 1.6 * len(entries)), sharex=True, squeeze=False)
    for ax, entry in zip(axes[:, 0], entries):
        comp = next(c for c in entry["stream_metrics"]["composition"][boxes] if c["section"] == name)
        centres = np.asarray(comp["centres"]) * 1e3
        width = (centres[1] - centres[0]) * 0.9 if len(centres) > 1 else 1.0
        bottom = np.zeros(len(centres))
        streams = entry["stream_metrics"]["streams"]
        for k, (stream, fractions) in enumerate(comp["fractions"].items()):
            tag = next((int(t) for t, n in streams.items() if n == stream), k)
            values = np.array([0.0 if f is None else f for f in fractions])
            ax.bar(centres, values, width, bottom=bottom, color=STREAM_COLOURS.get(tag), label=stream)
            bottom += values
        ax.set_ylim(0, 1)
        ax.set_ylabel("fraction")
        ax.set_title(_run_label(entry), fontsize=8)
    axes[0, 0].legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("y, mm (left arm at +y)")
    fig.suptitle(f"stream composition of section {name}, {boxes} sub-boxes (empty: no parcel)")
    return _save(plt, fig, path)


def _plot_summary_table(report: dict, path: str) -> str:
    """The summary table (crossing, transverse rms, collision rate, axial RMS per model and step) as a picture."""
    plt = _mpl()
    rows = report["summary_table"]
    cells = [[f"{r['diameter'] * 1e6:.0f}", f"{r['dt']:g}"]
             + ["-" if r[key] is None else fmt.format(r[key]) for key, _, fmt in SUMMARY_COLUMNS] for r in rows]
    headings = ["d um", "dt s"] + [h for _, h, _ in SUMMARY_COLUMNS]
    fig, ax = plt.subplots(figsize=(13, 0.9 + 0.32 * max(1, len(rows))))
    ax.axis("off")
    table = ax.table(cellText=cells or [["-"] * len(headings)], colLabels=headings, loc="center")
    table.auto_set_font_size(False)
    table.set_fontsize(8)
    table.scale(1.0, 1.3)
    ax.set_title(f"collision models against dem (axial RMS over {report['boxes'][0]} sub-boxes)", fontsize=9)
    return _save(plt, fig, path, dpi=110)

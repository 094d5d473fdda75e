"""Run output: particle snapshots in ``run.zarr`` and VTK ``.vtp`` files with a ``.pvd`` series.

Layout of one run directory ``DIR`` (written by :class:`RunWriter`)::

    DIR/run.zarr/                      zarr v3 group; attrs: ``config`` (resolved), ``code_version``,
                                       ``created``, ``snapshot_count``
        snapshots/000000/{name}        one group per snapshot; any named per-particle arrays
                                       (x, v, omega (n, 3); radius, ... (n,)), chunked by rows;
                                       group attrs ``time`` (s), ``step``, ``count``
        time, step                     (n_snapshots,) float64 / int64, appended per snapshot
        series/{name}                  per-step series appended by :meth:`RunWriter.append_series`
    DIR/vtk/particles_0000.vtp         PolyData: points = x, point data = every other array
    DIR/vtk/particles.pvd              ParaView collection of the .vtp files with their times

Snapshots are written one at a time (chunk by chunk), so a run that stops keeps every snapshot
written so far; the particle count may change between snapshots (injection, outlets).
pyvista and zarr are imported lazily.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import os
from pathlib import Path

import numpy as np

ROW_CHUNK = 65536
"""Rows per zarr chunk of a snapshot array."""


def _jsonable(value):
    """Config values as JSON-safe types (zarr attrs, summary.json): dataclasses as dicts with their type's name,
    non-finite floats as text, other objects as text without memory addresses (a restart compares configs)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {"type": type(value).__name__,
                **{f.name: _jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}}
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    text = str(value)
    return type(value).__name__ if " at 0x" in text else text


class RunWriter:
    """Writes particle snapshots of one run to ``out_dir/run.zarr`` and ``out_dir/vtk``.

    Args:
        out_dir: run directory (created).
        config: resolved configuration, stored as the ``config`` attribute of the root group.
        vtk: also write ``.vtp`` files and the ``.pvd`` series.
        vtk_name: base name of the VTK files (``{vtk_name}_0000.vtp``).
        overwrite: replace an existing ``run.zarr`` (otherwise an existing store is an error).
    """

    def __init__(self, out_dir, *, config: dict | None = None, vtk: bool = True, vtk_name: str = "particles",
                 overwrite: bool = True):
        import zarr

        from hel_warp import __version__
        from hel_warp.errors import ConfigError

        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        store = self.out_dir / "run.zarr"
        if store.exists() and not overwrite:
            raise ConfigError(f"{store} exists; choose another --out or allow overwrite")
        self.root = zarr.open_group(str(store), mode="w" if overwrite else "w-")
        self.root.attrs.update({"config": _jsonable(config or {}), "code_version": __version__,
                                "created": _dt.datetime.now(_dt.timezone.utc).isoformat(), "snapshot_count": 0})
        self.root.create_group("snapshots")
        self.root.create_group("series")
        self._time = self.root.create_array("time", shape=(0,), chunks=(1024,), dtype="float64")
        self._step = self.root.create_array("step", shape=(0,), chunks=(1024,), dtype="int64")
        self.count = 0
        self.vtk = vtk
        self.vtk_name = vtk_name
        self.vtk_dir = self.out_dir / "vtk"
        self._pvd_entries: list[tuple[float, str]] = []
        if vtk:
            self.vtk_dir.mkdir(exist_ok=True)

    def write_snapshot(self, arrays: dict[str, np.ndarray], *, time: float, step: int, positions: str = "x") -> int:
        """Store one snapshot of named per-particle arrays (same leading length); returns its index."""
        n = None
        for name, arr in arrays.items():
            if n is None:
                n = len(arr)
            elif len(arr) != n:
                raise ValueError(f"snapshot array {name!r} has {len(arr)} rows, expected {n}")
        index = self.count
        group = self.root["snapshots"].create_group(f"{index:06d}")
        for name, arr in arrays.items():
            arr = np.ascontiguousarray(arr)
            chunks = (min(max(len(arr), 1), ROW_CHUNK),) + arr.shape[1:]
            z = group.create_array(name, shape=arr.shape, chunks=chunks, dtype=arr.dtype)
            z[...] = arr
        group.attrs.update({"time": float(time), "step": int(step), "count": int(n or 0)})
        self._time.append(np.array([time], dtype=np.float64))
        self._step.append(np.array([step], dtype=np.int64))
        self.count += 1
        self.root.attrs["snapshot_count"] = self.count
        if self.vtk:
            path = self.vtk_dir / f"{self.vtk_name}_{index:04d}.vtp"
            write_vtp(path, arrays, positions=positions)
            self._pvd_entries.append((float(time), path.name))
            write_pvd(self.vtk_dir / f"{self.vtk_name}.pvd", self._pvd_entries)
        return index

    def append_series(self, name: str, values) -> None:
        """Append values to the 1-d series ``series/name`` (e.g. per-step contact counts, timings)."""
        values = np.atleast_1d(np.asarray(values))
        series = self.root["series"]
        if name not in series:
            series.create_array(name, shape=(0,), chunks=(4096,), dtype=values.dtype)
        series[name].append(values)


def write_vtp(path, arrays: dict[str, np.ndarray], *, positions: str = "x") -> None:
    """One VTK PolyData file: points from ``arrays[positions]`` (n, 3), every other array as point data."""
    import pyvista as pv

    points = np.asarray(arrays[positions], dtype=np.float64)
    cloud = pv.PolyData(points)
    for name, arr in arrays.items():
        if name == positions:
            continue
        arr = np.asarray(arr)
        if arr.dtype == np.bool_:
            arr = arr.astype(np.uint8)
        cloud.point_data[name] = arr
    cloud.save(str(path))


def write_pvd(path, entries: list[tuple[float, str]]) -> None:
    """ParaView collection file listing (time, file name relative to the .pvd) pairs."""
    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
             "  <Collection>"]
    lines += [f'    <DataSet timestep="{t:.9g}" group="" part="0" file="{name}"/>' for t, name in entries]
    lines += ["  </Collection>", "</VTKFile>", ""]
    tmp = f"{path}.tmp"
    with open(tmp, "w") as fh:
        fh.write("\n".join(lines))
    os.replace(tmp, path)


def read_snapshot(run_dir, index: int = -1) -> tuple[dict[str, np.ndarray], dict]:
    """Arrays and attrs (time, step, count) of snapshot ``index`` of ``run_dir/run.zarr``."""
    import zarr

    root = zarr.open_group(str(Path(run_dir) / "run.zarr"), mode="r")
    count = int(root.attrs["snapshot_count"])
    if index < 0:
        index += count
    group = root["snapshots"][f"{index:06d}"]
    return {name: arr[...] for name, arr in group.arrays()}, dict(group.attrs)

"""Probes: what a flow records while it runs, sampled every ``every`` seconds of simulated time.

- :class:`Pressure`: the gas pressure at a point (the cell holding it), or the mean over the fluid cells of a
  plane's cell layer (``axis`` and ``position``);
- :class:`PressureDrop`: the plane-mean pressure at ``low`` minus that at ``high`` along ``axis``: a bed's
  pressure drop;
- :class:`Plane`: on the cell layer at ``position`` along ``axis``, the solids fraction, the solids velocity and
  the gas velocity per cell along ``along``, averaged over the third axis;
- :class:`BedHeight`: the height of the bed above ``floor`` along the axis against gravity: where the layer-mean
  solids fraction last exceeds ``threshold`` (the bed's surface), and twice the real-particle-mean height above
  the floor (the height of a uniform bed of the same centre of mass).

Pressures are the solver's modified pressure p' = p - rho_f g . x (``hel_warp.gas.solver``): differences of p' are the
pressure differences less the gas's hydrostatic head, i.e. what the particles' weight and drag make. The records
live in memory and in the checkpoints (a resumed run keeps them) and go to ``run.zarr``'s ``probes`` group and
the summary at the end. Sampling reads the device at the probe times only.
"""

from __future__ import annotations

import abc

import math
from dataclasses import dataclass, field

import numpy as np

from hel_warp.errors import ConfigError

AXES = "xyz"


def _axis(name: str, axis) -> int:
    if isinstance(axis, str):
        if axis not in AXES:
            raise ConfigError(f"probe {name!r}: axis must be x, y or z (got {axis!r})")
        return AXES.index(axis)
    if axis not in (0, 1, 2):
        raise ConfigError(f"probe {name!r}: axis must be 0, 1 or 2 (got {axis!r})")
    return int(axis)


def _layer(grid_origin, spacing, shape, axis: int, position: float, name: str) -> int:
    index = int(math.floor((position - grid_origin[axis]) / spacing))
    if not 0 <= index < shape[axis]:
        raise ConfigError(f"probe {name!r}: position {position} m lies outside the domain along {AXES[axis]}")
    return index


def _plane(grid_origin, spacing, shape, axis: int, position: float, name: str) -> tuple[int, float]:
    """(i, w): the pressure at ``position`` along ``axis`` is p_i + w (p_(i+1) - p_i) from the cell centres i and
    i + 1 around it; between a boundary and the first (last) centre, 0 <= position - boundary < h / 2, the line
    through the two nearest centres is extended (w < 0 or w > 1): the pressure on a distributor or an outlet face.
    The boundaries themselves are accepted."""
    extent = spacing * shape[axis]
    offset = position - grid_origin[axis]
    if not (-1e-12 * extent <= offset <= extent * (1.0 + 1e-12)):
        raise ConfigError(f"probe {name!r}: position {position} m lies outside the domain along {AXES[axis]}")
    if shape[axis] == 1:
        return 0, 0.0
    s = offset / spacing - 0.5
    i = min(max(int(math.floor(s)), 0), shape[axis] - 2)
    return i, s - i


@dataclass
class Probe(abc.ABC):
    """A measurement sampled after steps (``ProbeRecorder``); each kind says what it samples in ``sample``."""

    name: str
    every: float | None = None
    """Sampling interval, s (None: every step)."""

    def check(self, flow) -> None:
        if self.every is not None and not (math.isfinite(self.every) and self.every > 0):
            raise ConfigError(f"probe {self.name!r}: every must be > 0 s (got {self.every})")

    def bind(self, sim) -> None:
        """Precompute what the samples need (indices, masks) once the simulation is built."""

    @abc.abstractmethod
    def sample(self, sim) -> dict:
        """{key: value} of this probe now (a number or an array per key)."""


def _fluid(sim) -> np.ndarray:
    return sim.solver.cell_fluid.numpy().astype(bool)


@dataclass
class Pressure(Probe):
    """Gas pressure p' at ``point`` (its cell's) or the plane mean on (``axis``, ``position``), Pa: linear between
    the cell centres on either side of the plane, extended to a boundary face (``_plane``), so that a drop between
    the distributor (``position`` 0) and the outlet counts the whole bed."""

    point: tuple | None = None
    axis: object = None
    position: float | None = None

    def check(self, flow) -> None:
        super().check(flow)
        if (self.point is None) == (self.axis is None):
            raise ConfigError(f"probe {self.name!r}: give a point or an axis and position")
        if self.point is not None:
            p = np.asarray(self.point, float)
            if p.shape != (3,) or np.any(p < np.asarray(flow.lo)) or np.any(p > np.asarray(flow.hi)):
                raise ConfigError(f"probe {self.name!r}: point {self.point} lies outside the domain")
        else:
            self.axis = _axis(self.name, self.axis)
            _plane(flow.lo, flow.spacing, flow.grid_shape, self.axis, float(self.position), self.name)

    def bind(self, sim) -> None:
        grid = sim.grid
        fluid = _fluid(sim)
        if self.point is not None:
            ijk = tuple(min(max(int((self.point[a] - grid.origin[a]) / grid.spacing), 0), grid.shape[a] - 1)
                        for a in range(3))
            if not fluid[ijk]:
                raise ConfigError(f"probe {self.name!r}: point {self.point} lies in a solid cell; move it into the gas")
            self._index = ijk
        else:
            index, self._weight = _plane(grid.origin, grid.spacing, grid.shape, self.axis, float(self.position),
                                         self.name)
            self._slices = []
            for layer in (index, min(index + 1, grid.shape[self.axis] - 1)):
                sl = [slice(None)] * 3
                sl[self.axis] = layer
                self._slices.append(tuple(sl))
            self._mask = fluid[self._slices[0]] & fluid[self._slices[1]]
            if not self._mask.any():
                raise ConfigError(f"probe {self.name!r}: the plane at {self.position} m has no fluid cell on both "
                                  "sides")

    def sample(self, sim) -> dict:
        p = sim.solver.gas.cell_pressure.numpy()
        if self.point is not None:
            return {"pressure": float(p[self._index])}
        p0, p1 = (p[sl][self._mask].astype(np.float64) for sl in self._slices)
        return {"pressure": float(np.mean(p0 + self._weight * (p1 - p0)))}


@dataclass
class PressureDrop(Probe):
    """Plane-mean p' at ``low`` minus at ``high`` along ``axis`` (m), Pa."""

    axis: object = 1
    low: float = 0.0
    high: float = 0.0

    def check(self, flow) -> None:
        super().check(flow)
        self.axis = _axis(self.name, self.axis)
        if not self.high > self.low:
            raise ConfigError(f"probe {self.name!r}: high {self.high} must exceed low {self.low}")
        self._planes = [Pressure(name=self.name, axis=self.axis, position=pos) for pos in (self.low, self.high)]
        for plane in self._planes:
            plane.check(flow)

    def bind(self, sim) -> None:
        for plane in self._planes:
            plane.bind(sim)

    def sample(self, sim) -> dict:
        low, high = (plane.sample(sim)["pressure"] for plane in self._planes)
        return {"pressure_drop": low - high}


def solids_by_cell(sim) -> tuple[np.ndarray, np.ndarray]:
    """(real-particle mass per cell, its momentum per cell (.., 3)) from the live parcels' centres (host read)."""
    grid = sim.grid
    p = sim.solver.pool.particles
    alive = p.alive.numpy().astype(bool)
    x = p.x.numpy()[alive].astype(np.float64)
    v = p.v.numpy()[alive].astype(np.float64)
    m = (p.weight.numpy()[alive] * p.density.numpy()[alive] * (4.0 / 3.0) * math.pi
         * p.radius.numpy()[alive].astype(np.float64) ** 3)
    ijk = np.floor((x - np.asarray(grid.origin)) / grid.spacing).astype(np.int64)
    ijk = np.clip(ijk, 0, np.asarray(grid.shape) - 1)
    flat = np.ravel_multi_index(ijk.T, grid.shape)
    cells = int(np.prod(grid.shape))
    mass = np.bincount(flat, weights=m, minlength=cells).reshape(grid.shape)
    momentum = np.stack([np.bincount(flat, weights=m * v[:, a], minlength=cells) for a in range(3)],
                        axis=-1).reshape(tuple(grid.shape) + (3,))
    return mass, momentum


@dataclass
class Plane(Probe):
    """On the cell layer at ``position`` (m) along ``axis``: per cell along ``along``, averaged over the third axis,
    ``solids_fraction`` (the coupling's deposit), ``solids_velocity`` (mass-weighted, m/s; NaN where no solids)
    and ``gas_velocity`` (m/s); ``coordinates`` the cell centres along ``along``, m."""

    axis: object = 1
    position: float = 0.0
    along: object = 0

    def check(self, flow) -> None:
        super().check(flow)
        self.axis = _axis(self.name, self.axis)
        self.along = _axis(self.name, self.along)
        if self.along == self.axis:
            raise ConfigError(f"probe {self.name!r}: along must differ from axis")
        _layer(flow.lo, flow.spacing, flow.grid_shape, self.axis, float(self.position), self.name)

    def bind(self, sim) -> None:
        grid = sim.grid
        self._index = _layer(grid.origin, grid.spacing, grid.shape, self.axis, float(self.position), self.name)
        self._other = ({0, 1, 2} - {self.axis, self.along}).pop()
        self.coordinates = grid.origin[self.along] + (np.arange(grid.shape[self.along]) + 0.5) * grid.spacing

    def _cut(self, field: np.ndarray) -> np.ndarray:
        sl = [slice(None)] * 3
        sl[self.axis] = self._index
        layer = field[tuple(sl)]  # the two remaining axes in order
        remaining = [a for a in range(3) if a != self.axis]
        return layer if remaining[0] == self.along else np.swapaxes(layer, 0, 1)

    def sample(self, sim) -> dict:
        eps = self._cut(sim.solver.fields.cell_eps_s.numpy().astype(np.float64)).mean(axis=1)
        gas = self._cut(sim.solver.gas.cell_velocity.numpy().astype(np.float64)).mean(axis=1)
        mass, momentum = solids_by_cell(sim)
        m = self._cut(mass).sum(axis=1)
        mv = self._cut(momentum).sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            solids = np.where(m[:, None] > 0, mv / m[:, None], np.nan)
        return {"solids_fraction": eps, "solids_velocity": solids, "gas_velocity": gas}


@dataclass
class BedHeight(Probe):
    """Bed height above ``floor`` (m) along the axis against gravity: ``bed_height`` where the layer-mean solids
    fraction last exceeds ``threshold``, ``mean_height_x2`` twice the real-particle-mean height above the floor, m;
    ``layer_solids_fraction`` the layer-mean deposited solids fraction per cell layer, in grid order (the voidage
    the drag sees)."""

    floor: float = 0.0
    threshold: float = 0.1

    def check(self, flow) -> None:
        super().check(flow)
        g = np.asarray(flow.gravity)
        if not np.any(g):
            raise ConfigError(f"probe {self.name!r}: a bed height needs gravity")
        self._axis = int(np.argmax(np.abs(g)))
        self._up = -float(np.sign(g[self._axis]))
        if not 0 < self.threshold < 1:
            raise ConfigError(f"probe {self.name!r}: threshold must lie in (0, 1) (got {self.threshold})")

    def bind(self, sim) -> None:
        grid = sim.grid
        self._fluid = _fluid(sim)
        centres = grid.origin[self._axis] + (np.arange(grid.shape[self._axis]) + 0.5) * grid.spacing
        self._height = self._up * (centres - self.floor)

    def sample(self, sim) -> dict:
        eps = sim.solver.fields.cell_eps_s.numpy().astype(np.float64)
        axes = tuple(a for a in range(3) if a != self._axis)
        weight = self._fluid.sum(axis=axes)
        layer = np.where(weight > 0, (eps * self._fluid).sum(axis=axes) / np.maximum(weight, 1), 0.0)
        above = np.nonzero(layer > self.threshold)[0]
        surface = float(np.max(self._height[above]) + 0.5 * sim.grid.spacing) if above.size else 0.0
        p = sim.solver.pool.particles
        alive = p.alive.numpy().astype(bool)
        w = (p.weight.numpy()[alive] * p.radius.numpy()[alive].astype(np.float64) ** 3)
        h = self._up * (p.x.numpy()[alive, self._axis].astype(np.float64) - self.floor)
        mean = float(np.sum(w * h) / np.sum(w)) if w.size else 0.0
        return {"bed_height": surface, "mean_height_x2": 2.0 * mean, "layer_solids_fraction": layer}


@dataclass
class ProbeRecorder:
    """Samples every probe at its interval after each step (an observer of the solver) and keeps the records."""

    probes: list
    dt: float
    records: dict = field(default_factory=dict)
    """probe name -> {"time": [...], key: [...]}."""

    def bind(self, sim) -> None:
        for probe in self.probes:
            probe.bind(sim)
        self._every = [max(1, int(round(p.every / self.dt))) if p.every else 1 for p in self.probes]
        self._sim = sim

    def after_step(self, solver) -> None:
        step = solver.step_count
        for probe, every in zip(self.probes, self._every):
            if step % every == 0:
                values = probe.sample(self._sim)
                rec = self.records.setdefault(probe.name, {"time": []})
                rec["time"].append(float(solver.time))
                for key, value in values.items():
                    rec.setdefault(key, []).append(np.asarray(value, np.float64))

    def arrays(self) -> dict:
        """probe name -> {key: array (samples, ...)}."""
        return {name: {k: np.asarray(v, np.float64) for k, v in rec.items()} for name, rec in self.records.items()}

    def state(self) -> dict:
        out = {}
        for name, rec in self.arrays().items():
            for key, value in rec.items():
                out[f"{name}:{key}"] = value
        return out

    def set_state(self, state: dict) -> None:
        self.records = {}
        for flat, value in state.items():
            name, key = flat.split(":", 1)
            self.records.setdefault(name, {})[key] = [v for v in np.asarray(value, np.float64)]
        for rec in self.records.values():
            rec["time"] = [float(t) for t in rec.get("time", [])]

    def write(self, root) -> None:
        """The records into ``root['probes']`` (a zarr group), replacing earlier ones."""
        if "probes" in root:
            del root["probes"]
        group = root.create_group("probes")
        for name, rec in self.arrays().items():
            sub = group.create_group(name)
            for key, value in rec.items():
                arr = sub.create_array(key, shape=value.shape, dtype=value.dtype,
                                       chunks=value.shape if value.size else (1,) * max(value.ndim, 1))
                if value.size:
                    arr[...] = value

    def time_average(self, name: str, key: str, start: float, end: float):
        """Mean of a record over samples with start <= t <= end (NaN-aware for profiles)."""
        rec = self.arrays().get(name)
        if rec is None or key not in rec:
            return None
        t = rec["time"]
        sel = (t >= start - 1e-12) & (t <= end + 1e-12)
        if not sel.any():
            return None
        with np.errstate(invalid="ignore"):
            return np.nanmean(rec[key][sel], axis=0)

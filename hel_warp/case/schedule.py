"""Time schedules and spatial profiles of inlet velocities.

An inlet's normal speed at face centre ``x`` and time ``t`` is ``profile(x) * schedule(t)``:

- a number is a constant schedule (m/s);
- :class:`Ramp` goes linearly from ``start_value`` to ``value`` over ``duration`` seconds from ``start``;
- :class:`Levels` holds each of several speeds for ``hold`` seconds, ramping ``ramp`` seconds into each
  (a fluidization curve: the bed settles at every level before the next);
- :class:`Profile` shapes the speed over the patch with a function of the face-centre positions.

Every schedule is a pure function of time, so a resumed run sets its inlets from the checkpoint's time alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hel_warp.errors import ConfigError, require_finite


@dataclass(frozen=True)
class Constant:
    """A fixed speed, m/s."""

    value: float

    def __post_init__(self):
        _check_speed("inlet velocity", self.value)

    def __call__(self, t: float) -> float:
        return float(self.value)

    @property
    def duration(self) -> float:
        """Time the schedule needs to play out, s (0: none)."""
        return 0.0

    def values(self) -> list:
        return [float(self.value)]


@dataclass(frozen=True, kw_only=True)
class Ramp:
    """Linear ramp from ``start_value`` (default 0) to ``value`` over ``duration`` s, starting at ``start`` s."""

    value: float
    duration: float
    start: float = 0.0
    start_value: float = 0.0

    def __post_init__(self):
        _check_speed("ramp value", self.value)
        _check_speed("ramp start_value", self.start_value)
        require_finite("ramp duration", self.duration)
        require_finite("ramp start", self.start)
        if self.duration < 0 or self.start < 0:
            raise ConfigError(f"ramp start and duration must be >= 0 s (got {self.start}, {self.duration})")

    def __call__(self, t: float) -> float:
        if self.duration <= 0.0:
            return float(self.value) if t >= self.start else float(self.start_value)
        f = min(max((t - self.start) / self.duration, 0.0), 1.0)
        return float(self.start_value + f * (self.value - self.start_value))

    @property
    def duration_total(self) -> float:
        return self.start + self.duration

    def values(self) -> list:
        return [float(self.value)]


@dataclass(frozen=True, kw_only=True)
class Levels:
    """A schedule of speeds: level k starts at ``k * (ramp + hold)``, ramps linearly from level k-1 (0 before the
    first) over ``ramp`` s, then holds ``values[k]`` for ``hold`` s; after the last level its value stays.

    :meth:`windows` gives each level's (start, end) of the hold, for averaging a measurement over it."""

    values_: tuple
    hold: float
    ramp: float = 0.0

    def __init__(self, values, *, hold: float, ramp: float = 0.0):
        vals = tuple(float(v) for v in np.atleast_1d(np.asarray(values, dtype=np.float64)))
        if not vals:
            raise ConfigError("a schedule of levels needs at least one velocity")
        for v in vals:
            _check_speed("velocity level", v)
        require_finite("hold", hold)
        require_finite("ramp", ramp)
        if not hold > 0:
            raise ConfigError(f"each velocity level must be held > 0 s (got --hold {hold})")
        if ramp < 0:
            raise ConfigError(f"the ramp between levels must be >= 0 s (got --ramp {ramp})")
        object.__setattr__(self, "values_", vals)
        object.__setattr__(self, "hold", float(hold))
        object.__setattr__(self, "ramp", float(ramp))

    @property
    def period(self) -> float:
        return self.ramp + self.hold

    @property
    def duration(self) -> float:
        """End of the last hold, s."""
        return len(self.values_) * self.period

    def values(self) -> list:
        return list(self.values_)

    def windows(self) -> list:
        """(start, end) of each level's hold, s."""
        return [(k * self.period + self.ramp, (k + 1) * self.period) for k in range(len(self.values_))]

    def level_at(self, t: float) -> int:
        return min(max(int(math.floor(t / self.period + 1e-12)), 0), len(self.values_) - 1)

    def __call__(self, t: float) -> float:
        k = self.level_at(t)
        before = self.values_[k - 1] if k > 0 else 0.0
        into = t - k * self.period
        if self.ramp > 0.0 and into < self.ramp:
            return float(before + (self.values_[k] - before) * max(into, 0.0) / self.ramp)
        return float(self.values_[k])


@dataclass(frozen=True)
class Profile:
    """A spatial shape of the inlet speed: ``function(points)`` takes the face centres of the patch (n, 3), m, and
    returns the speed factor at each (n,); the schedule multiplies it. E.g. a parabola across a channel of width W
    centred at y = 0: ``Profile(lambda p: 1.5 * (1 - (2 * p[:, 1] / W) ** 2))`` (mean 1)."""

    function: object

    def __call__(self, points: np.ndarray) -> np.ndarray:
        values = np.asarray(self.function(np.asarray(points, np.float64)), np.float64)
        if values.shape not in ((len(points),), ()):
            raise ConfigError(f"inlet profile returned shape {values.shape} for {len(points)} face centres; return "
                              "one factor per face centre")
        values = np.broadcast_to(values, (len(points),))
        if not np.all(np.isfinite(values)):
            raise ConfigError("inlet profile returned NaN or infinity; give a finite factor at every face centre")
        if np.any(values < 0):
            raise ConfigError("inlet profile returned a negative factor: an inlet blows into the domain; use an outlet "
                              "where the gas leaves")
        return values


def as_schedule(value):
    """A schedule from a number (constant speed) or a schedule object."""
    if isinstance(value, (Constant, Ramp, Levels)):
        return value
    if callable(value) and not isinstance(value, Profile):
        return value
    try:
        speed = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"inlet velocity must be a number (m/s), a Ramp or Levels (got {value!r})") from None
    return Constant(speed)


def _check_speed(name: str, value: float) -> None:
    if not (isinstance(value, (int, float, np.floating, np.integer)) and math.isfinite(float(value))):
        raise ConfigError(f"{name} must be a finite speed in m/s (got {value!r})")
    if value < 0:
        raise ConfigError(f"{name} must be >= 0 m/s into the domain (got {value!r}); a negative inlet speed blows "
                          "out of the domain: use an outlet there")

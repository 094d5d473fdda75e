"""``--collision-events PATH``: every collision of every step, for ``scripts/collision_events.py``.

``dem`` contact onsets (``DemCollision.onset_events``) or the ``surrogate``'s resolved collisions with swept or
overlap detection (``SurrogateCollision.collision_events``, switched on here), saved as one ``.npz`` of
equal-length arrays: ``step``, ``particle_a`` < ``particle_b`` (ids), ``speed`` (normal approach speed, m/s),
``time`` (s of the run), ``stream_a`` <= ``stream_b``, ``radius_a``, ``radius_b`` (m), and ``truncated_steps``
(steps whose list overflowed; their counts in the run's series stay exact).
"""

from __future__ import annotations

import numpy as np

from hel_warp.errors import ConfigError


class EventRecorder:
    """Collects the collision events of each step of a HEL solver (see the module docstring)."""

    def __init__(self, solver):
        collision = solver.collision
        if hasattr(collision, "record_events"):
            collision.record_events = True
            self._read = collision.collision_events
        elif hasattr(collision, "onset_events"):
            self._read = collision.onset_events
        else:
            raise ConfigError(f"--collision-events records the dem and surrogate collisions (got --collisions "
                              f"{collision.name}, which resolves none)")
        self.rows = {k: [] for k in ("step", "particle_a", "particle_b", "speed", "time", "stream_a", "stream_b",
                                     "radius_a", "radius_b")}
        self.truncated = []

    def add(self, solver) -> None:
        ev = self._read()
        n = len(ev["speed"])
        p = solver.pool.particles
        radius = np.full(max(int(p.particle_id.numpy().max(initial=0)) + 1, 1), np.nan, np.float32)
        alive = p.alive.numpy() != 0
        radius[p.particle_id.numpy()[alive]] = p.radius.numpy()[alive]
        step = solver.step_count - 1
        r = self.rows
        r["step"].append(np.full(n, step, np.int32))
        for key in ("particle_a", "particle_b", "speed", "stream_a", "stream_b"):
            r[key].append(np.asarray(ev[key]))
        r["time"].append(np.asarray(ev["time"], np.float64) + (solver.time - solver.config.dt))
        r["radius_a"].append(radius[np.asarray(ev["particle_a"], np.int64)])
        r["radius_b"].append(radius[np.asarray(ev["particle_b"], np.int64)])
        if ev.get("truncated"):
            self.truncated.append(step)

    def save(self, path: str) -> None:
        out = {k: (np.concatenate(v) if v else np.zeros(0)) for k, v in self.rows.items()}
        np.savez_compressed(path, **out, truncated_steps=np.asarray(self.truncated, np.int32))

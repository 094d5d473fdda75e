"""Three-particle streams (reference paper sec. 7, Fig. 13): do two streams rebound or pass through?

Two streams (tags 0, red, and 1, blue) of three 315 um polyethylene spheres (``Material()``:
rho = 1000 kg/m^3) move at 5 m/s in the x-y plane, 20 degrees apart (+-10 deg about +x), in a small
closed box of still air (10 x 4 x 4 mm, 1 mm cells, the engine's gas solver). One particle of each
stream enters at the start of each of the first three steps (dt = 1e-4 s) from a fixed nozzle
point; the nozzles are placed so that pair k (the k-th particle of each stream) overlaps at the end
of step k + 5: lateral gap 0.63 d then (0.2 mm), 1.19 d one step earlier. So every pair is first
seen overlapping "after the fifth step" and the centres are still apart (a defined normal).

``--collisions``: ``none``; ``ktgf`` (the paper's HEL: eps_s < 0.06 in every cell, the granular
pressure sees no collision and the streams pass through); ``surrogate`` (HELSCM pairwise; a contact-form
``--model``, or without one a model built for these particles on first use and cached); ``surrogate-paper``
(paper-form ``--model``); ``dem`` (Hertz-Mindlin sub-steps). The streams are a flow of the case API
(``hel_warp.case``): the nozzles are explicit releases, one particle per stream at the start of each of the
first three steps. ``check()`` reads the sign of each particle's lateral velocity v_y after its pair met:
reversed for every particle of a stream = "rebound", for none = "pass-through".

    python cases/three_streams.py --collisions dem --out runs/three_streams_dem
    python cases/three_streams.py --collisions surrogate --model runs/model_contact --out runs/three_streams_sm

Writes the run directory of every case (``run.zarr``, VTK) with ``OUT/before.png``, ``OUT/at.png``,
``OUT/after.png`` (pyvista off-screen; matplotlib if pyvista cannot render) and ``OUT/summary.json`` (outcome,
lateral velocities, max eps_s, counts).
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path

import numpy as np

if str(Path(__file__).resolve().parents[1]) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hel_warp import case as hc  # noqa: E402

DIAMETER = 315e-6
"""Particle diameter, m (the paper's small size)."""
SPEED = 5.0
"""Stream speed, m/s."""
HALF_ANGLE_DEG = 10.0
"""Each stream's angle to +x: the streams are 20 degrees apart."""
DT = 1e-4
"""HEL time step, s."""
PER_STREAM = 3
"""Particles per stream, one injected per step."""
MEET_STEPS = 5
"""Steps from injection to the step at whose end a pair first overlaps."""
GAP_AT_MEETING = 0.2e-3
"""Lateral centre distance of a pair at the end of its meeting step, m (0.63 d: overlapping)."""
BOX_LO = (0.0, -2e-3, 0.0)
BOX_HI = (10e-3, 2e-3, 4e-3)
SPACING = 1e-3
NOZZLE_X = 1.5e-3
NOZZLE_Z = 2e-3
COLLISIONS = ("none", "ktgf", "surrogate", "surrogate-paper", "dem")



def options(groups) -> None:
    groups.case.add_argument("--steps", type=int, default=12, help="HEL steps of 1e-4 s (default 12, >= 9)")
    groups.output.add_argument("--no-render", action="store_true", help="skip the pictures")


def stream_velocity(stream: int) -> np.ndarray:
    """Stream 0 moves towards -y (starts at y > 0), stream 1 towards +y; both +x."""
    a = math.radians(HALF_ANGLE_DEG) * (-1.0 if stream == 0 else 1.0)
    return SPEED * np.array([math.cos(a), math.sin(a), 0.0])


def nozzle(stream: int) -> np.ndarray:
    """Injection point of a stream: MEET_STEPS steps of flight before a lateral gap of GAP_AT_MEETING."""
    v = stream_velocity(stream)
    y_meet = 0.5 * GAP_AT_MEETING * (1.0 if stream == 0 else -1.0)
    return np.array([NOZZLE_X, y_meet - MEET_STEPS * DT * v[1], NOZZLE_Z])



def build(args):
    """Still air in a closed box; two nozzles release one particle per stream at the start of each of the first
    three steps (``PER_STREAM``), placed so that pair k overlaps at the end of step k + 5."""
    from hel_warp.errors import ConfigError

    if args.steps < MEET_STEPS + PER_STREAM + 1:
        raise ConfigError(f"--steps must be >= {MEET_STEPS + PER_STREAM + 1} so that every pair meets "
                          f"(got {args.steps})")
    if args.end_time is None:
        args.end_time = args.steps * DT
    flow = hc.Flow("three_streams", lo=BOX_LO, hi=BOX_HI, spacing=SPACING, gravity=(0.0, 0.0, -9.80665),
                   walls=hc.Walls(contact="point"))
    flow.species("pe", DIAMETER, material=hc.Material())
    for k in range(PER_STREAM):
        velocities = [stream_velocity(s) for s in (0, 1)]
        flow.release("pe", k * DT, [nozzle(0), nozzle(1)], speed=SPEED,
                     directions=[v / SPEED for v in velocities], stream=[0, 1])
    return flow


class History:
    """Observer: per step end, the parcels' x, v, alive, stream (slot order), the largest cell eps_s and the
    collision counts."""

    def __init__(self):
        self.history = []
        self.max_eps_s = 0.0

    def after_step(self, solver) -> None:
        p = solver.pool.particles
        eps = float(solver.fields.cell_eps_s.numpy().max())
        self.max_eps_s = max(self.max_eps_s, eps)
        self.history.append({"step": solver.step_count, "x": p.x.numpy().copy(), "v": p.v.numpy().copy(),
                             "alive": p.alive.numpy().copy(), "stream": p.stream.numpy().copy(),
                             "max_eps_s": eps, "counts": solver.collision_counts()})


def observers(args, flow) -> list:
    return [History()]


def _case_view(run):
    from types import SimpleNamespace

    record = run.solver.observers[0]
    return SimpleNamespace(history=record.history, max_eps_s=record.max_eps_s, collision=run.solver.collision,
                           steps_done=run.solver.step_count)


def outcome(case) -> dict:
    """Rebound or pass-through per stream, from the sign of v_y once each pair has met.

    Particle k (k = 0, 1, 2) of stream 0 starts with v_y < 0 (stream 1: > 0); it enters before step k + 1
    (1-based) and its pair overlaps at the end of step k + 5. The sign is read at the end of the run
    (every pair has met and been resolved: steps >= 9). ``outcome``: "rebound" when every particle reversed v_y, "pass-through" when
    none did, else "mixed"; also the mean lateral velocity per stream and the largest cell eps_s.
    """
    last = case.history[-1]
    alive = last["alive"].astype(bool)
    result = {"collisions": case.collision.name, "steps": case.steps_done, "max_cell_eps_s": case.max_eps_s,
              "streams": {}}
    outcomes = []
    for stream in (0, 1):
        sel = alive & (last["stream"] == stream)
        vy0 = stream_velocity(stream)[1]
        vy = last["v"][sel, 1].astype(float)
        reversed_ = np.sign(vy) == -np.sign(vy0)
        outcome = "rebound" if reversed_.all() else ("pass-through" if not reversed_.any() else "mixed")
        outcomes.append(outcome)
        result["streams"][str(stream)] = {"vy_initial": float(vy0), "vy_final": vy.tolist(),
                                          "vy_final_mean": float(vy.mean()) if vy.size else None,
                                          "outcome": outcome}
    result["outcome"] = outcomes[0] if outcomes[0] == outcomes[1] else "mixed"
    result["collision_counts_total"] = {k: int(sum(h["counts"].get(k, 0) for h in case.history))
                                        for k in ("detected_pairs", "surrogate_calls")}
    return result



def summary(run) -> dict:
    return outcome(_case_view(run))


def finish(run, summary: dict) -> None:
    if not run.args.no_render:
        summary["pictures"] = render(_case_view(run), str(run.out))


def report(run, result: dict) -> str:
    s = result["streams"]
    return (f"three_streams [{result['collisions']}]: {result['outcome']} (stream 0 v_y {s['0']['vy_initial']:+.3f} -> "
            f"{s['0']['vy_final_mean']:+.3f} m/s, stream 1 {s['1']['vy_initial']:+.3f} -> "
            f"{s['1']['vy_final_mean']:+.3f} m/s), max cell eps_s {result['max_cell_eps_s']:.4f} -> {run.out}")


# ------------------------------------------------------------------------------------------ pictures

COLOURS = ("red", "blue")


def _frames(case) -> dict:
    """before: all injected, no pair met (end of step 3); at: first pair overlapping (step 5); after: last."""
    n = len(case.history)
    return {"before": case.history[min(PER_STREAM, n) - 1], "at": case.history[min(MEET_STEPS, n) - 1],
            "after": case.history[-1]}


def _render_pyvista(frame, trail, path: str, title: str) -> None:
    import pyvista as pv

    pv.OFF_SCREEN = True
    plotter = pv.Plotter(off_screen=True, window_size=(900, 500))
    plotter.set_background("white")
    alive = frame["alive"].astype(bool)
    for stream in (0, 1):
        sel = alive & (frame["stream"] == stream)
        for x in frame["x"][sel]:
            plotter.add_mesh(pv.Sphere(radius=0.5 * DIAMETER, center=tuple(float(c) for c in x)),
                             color=COLOURS[stream])
        pts = np.asarray(trail[stream], dtype=float)
        if len(pts):
            plotter.add_points(pts, color=COLOURS[stream], point_size=4, opacity=0.4)
    plotter.add_text(title, font_size=10, color="black")
    plotter.view_xy()
    plotter.camera.zoom(1.4)
    plotter.screenshot(path)
    plotter.close()


def _render_matplotlib(frame, trail, path: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4))
    alive = frame["alive"].astype(bool)
    for stream in (0, 1):
        pts = np.asarray(trail[stream], dtype=float)
        if len(pts):
            ax.plot(pts[:, 0] * 1e3, pts[:, 1] * 1e3, ".", color=COLOURS[stream], alpha=0.3, ms=3)
        sel = alive & (frame["stream"] == stream)
        for x in frame["x"][sel]:
            ax.add_patch(plt.Circle((x[0] * 1e3, x[1] * 1e3), 0.5 * DIAMETER * 1e3, color=COLOURS[stream]))
    ax.set_aspect("equal")
    ax.set_xlabel("x, mm")
    ax.set_ylabel("y, mm")
    ax.set_title(title)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def render(case, out: str) -> list[str]:
    """before.png, at.png, after.png in ``out`` (positions up to each frame as faint trails)."""
    os.makedirs(out, exist_ok=True)
    paths = []
    for name, frame in _frames(case).items():
        trail = {0: [], 1: []}
        for h in case.history[:frame["step"]]:
            for stream in (0, 1):
                sel = h["alive"].astype(bool) & (h["stream"] == stream)
                trail[stream].extend(h["x"][sel].tolist())
        path = os.path.join(out, f"{name}.png")
        title = f"{case.collision.name}: {name} (end of step {frame['step']}, t = {frame['step'] * DT * 1e3:.1f} ms)"
        try:
            _render_pyvista(frame, trail, path, title)
        except Exception:  # noqa: BLE001 - no OpenGL context here: fall back to a 2-D plot
            _render_matplotlib(frame, trail, path, title)
        paths.append(path)
    return paths



CASE = hc.Case("three_streams", build, doc=__doc__, options=options, summary=summary, observers=observers,
               report=report, finish=finish, weights=False,
               defaults={"collisions": "surrogate", "dt": DT, "end_time": None, "output_interval": DT})


def main(argv=None) -> int:
    return CASE.main(argv)


if __name__ == "__main__":
    sys.exit(main())

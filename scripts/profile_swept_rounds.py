"""Where the swept detection's rounds go on the colliding-streams rig: per kernel, per round, on saved states.

``capture`` runs the rig (``cases/colliding_streams.py`` as ``scripts/bench_rig.py`` builds it, surrogate with swept
detection) and saves the inputs of every ``SurrogateCollision.collide`` call (the parcel arrays and dt) to
``OUT/sNNN.npz``, with the rounds, collisions and wall clock of that call. ``profile`` replays saved states on a fresh
rig strategy and prints per state the rounds, ms per round and each round kernel's time (the launches recorded by
``kernels.collide.resolve_swept`` are timed one by one; on the CPU a launch returns when its kernel is done), and
per round the mean number of dirty parcels (``swept_find``'s working threads) and of parcels holding an event
(``swept_select``'s). ``--save-outputs DIR`` writes each state's velocities, spins, shifts, last-event times, counts
and rounds, to compare two versions of the code bit for bit (``compare``).

    python scripts/profile_swept_rounds.py capture --model MODEL --out /tmp/states [--dt 1e-3] [--end-time 0.014]
    python scripts/profile_swept_rounds.py profile --model MODEL /tmp/states/s007.npz [...] [--save-outputs DIR]
    python scripts/profile_swept_rounds.py compare DIR_A DIR_B
"""

from __future__ import annotations

import argparse
import collections
import glob
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

PARCEL_FIELDS = ("x", "v", "omega", "radius", "density", "weight", "stream", "alive")


def build_rig(model: str, dt: float, end_time: float, diameter: float):
    """The rig with the swept surrogate after its gas warm-up (``bench_rig.build_model``)."""
    import bench_rig

    from hel_warp.cli.commands._common import load_case_module

    case = load_case_module("colliding_streams")
    args = argparse.Namespace(diameter=diameter, dt=dt, end_time=end_time, model=model, paper_model=None,
                              detection="swept", force_model=True, cells=None, max_particles=None, device="cpu")
    return bench_rig.build_model(case, "surrogate", args)


def capture(args) -> None:
    import numpy as np

    rig = build_rig(args.model, args.dt, args.end_time, args.diameter)
    strategy = rig.solver.collision
    collide = strategy.collide
    os.makedirs(args.out, exist_ok=True)
    step = [0]

    def saving_collide(particles, dt=None):
        state = {f: getattr(particles, f).numpy().copy() for f in PARCEL_FIELDS}
        start = time.perf_counter()
        collide(particles, dt)
        seconds = time.perf_counter() - start
        rounds = int(strategy.swept.round.numpy()[0])
        calls = int(strategy.calls.numpy().sum())
        np.savez(os.path.join(args.out, f"s{step[0]:03d}.npz"), dt=dt, rounds=rounds, calls=calls, seconds=seconds,
                 **state)
        print(f"step {step[0]}: {int(state['alive'].sum())} parcels, {rounds} rounds, {calls} collisions, "
              f"collide {seconds:.3f} s", flush=True)
        step[0] += 1

    strategy.collide = saving_collide
    for _ in range(int(round(args.end_time / args.dt))):
        rig.solver.step()


def outputs(strategy, particles) -> dict:
    a = strategy.swept
    return {"v": particles.v.numpy(), "omega": particles.omega.numpy(), "shift": a.shift.numpy(),
            "t_last": a.t_last.numpy(), "calls": strategy.calls.numpy(), "collisions": strategy.collisions.numpy(),
            "detected": strategy.detected.numpy(), "guard": a.guard.numpy(), "wall_hits": a.wall_hits.numpy(),
            "rounds": a.round.numpy(), "event_rounds": strategy.event_rounds.numpy()}


class TimedCommand:
    """A recorded launch (``wp.launch(..., record_cmd=True)``) whose ``launch()`` adds its wall clock to ``seconds``
    under the kernel's name, and before ``swept_find`` / ``swept_select`` counts their working threads."""

    def __init__(self, command, name: str, seconds: dict, counts: dict, strategy):
        self.command, self.name, self.seconds, self.counts, self.strategy = command, name, seconds, counts, strategy

    def launch(self, *args, **kwargs):
        a = self.strategy.swept
        if self.name == "swept_find":
            self.counts["dirty"] += int(a.dirty.numpy().sum())
        elif self.name == "swept_select":
            from kernels.collide import EVENT_NONE_VALUE

            self.counts["event holders"] += int((a.event_key.numpy() != EVENT_NONE_VALUE).sum())
        start = time.perf_counter()
        result = self.command.launch(*args, **kwargs)
        self.seconds[self.name] += time.perf_counter() - start
        return result

    def __getattr__(self, name):
        return getattr(self.command, name)


def profile(args) -> None:
    import numpy as np
    import warp as wp

    import kernels.forest

    rig = build_rig(args.model, args.dt, args.dt, args.diameter)
    rig.solver.step()  # the strategy takes the rig's walls; every kernel compiled
    strategy = rig.solver.collision
    strategy.windows = args.windows if args.windows == "auto" else int(args.windows)
    strategy.ordering = "parallel"  # the rounds (what this script times kernel by kernel), not the CPU's queue
    particles = rig.pool.particles
    seconds, counts = collections.defaultdict(float), collections.defaultdict(int)
    launch = wp.launch

    def timed_launch(kernel, *a, **k):
        result = launch(kernel, *a, **k)
        return TimedCommand(result, kernel.key, seconds, counts, strategy) if k.get("record_cmd") else result

    wp.launch = kernels.forest.wp.launch = timed_launch
    for path in args.states:
        saved = np.load(path)
        for f in PARCEL_FIELDS:
            getattr(particles, f).assign(saved[f])
        seconds.clear()
        counts.clear()
        start = time.perf_counter()
        strategy.collide(particles, float(saved["dt"]))
        total = time.perf_counter() - start
        out = outputs(strategy, particles)
        rounds = max(1, int(out["rounds"][0]))
        print(f"{path}: collide {total:.3f} s, {strategy.counts()['windows']} windows, {rounds} rounds, "
              f"{int(out['calls'].sum())} collisions, "
              f"{1e3 * total / rounds:.2f} ms per round; mean per round (round 0 included): "
              + ", ".join(f"{value / rounds:.0f} {key}" for key, value in counts.items()))
        for name, value in sorted(seconds.items(), key=lambda kv: -kv[1]):
            print(f"    {name:28s} {value:8.3f} s  {1e6 * value / rounds:9.1f} us per round")
        print(f"    {'(outside the rounds)':28s} {total - sum(seconds.values()):8.3f} s")
        if args.save_outputs:
            os.makedirs(args.save_outputs, exist_ok=True)
            np.savez(os.path.join(args.save_outputs, os.path.basename(path)), **out)
    wp.launch = kernels.forest.wp.launch = launch


def compare(args) -> int:
    import numpy as np

    differing = 0
    for path in sorted(glob.glob(os.path.join(args.a, "*.npz"))):
        a, b = np.load(path), np.load(os.path.join(args.b, os.path.basename(path)))
        bad = [key for key in a.files if not np.array_equal(a[key], b[key])]
        differing += bool(bad)
        print(f"{os.path.basename(path)}: {'equal bit for bit' if not bad else 'DIFFERENT: ' + ', '.join(bad)}")
    return 1 if differing else 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("capture", "profile"):
        p = sub.add_parser(name)
        p.add_argument("--model", required=True, help="contact-form surrogate model directory")
        p.add_argument("--dt", type=float, default=1e-3, help="HEL time step, s (default 1e-3)")
        p.add_argument("--diameter", type=float, default=315e-6, help="particle diameter, m (default 315e-6)")
    cap = sub.choices["capture"]
    cap.add_argument("--out", required=True, help="directory of the saved states")
    cap.add_argument("--end-time", type=float, default=0.014, help="simulated time after the release, s")
    prof = sub.choices["profile"]
    prof.add_argument("states", nargs="+", help="saved states (capture's sNNN.npz)")
    prof.add_argument("--windows", default="auto", help="windows per step of the swept detection (auto or N)")
    prof.add_argument("--save-outputs", default=None, help="write each state's collide outputs here (compare)")
    cmp_ = sub.add_parser("compare")
    cmp_.add_argument("a")
    cmp_.add_argument("b")
    args = parser.parse_args(argv)

    from hel_warp.collisions.forest import quiet_warp

    quiet_warp()
    if args.command == "capture":
        capture(args)
    elif args.command == "profile":
        profile(args)
    else:
        return compare(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())

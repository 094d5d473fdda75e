"""What a run's collisions are like, per stream pair and size class: from the ``.npz`` that
``cases/colliding_streams.py --collision-events PATH`` writes (dem contact onsets, or the collisions the swept
surrogate resolves), several runs side by side.

    python scripts/collision_events.py DEM.npz SURROGATE.npz [--json]

Per run and group (all; left-left, left-right, right-right; for a mixture the cross-stream pairs by size class):
the count, the share that repeats a pair already met in the run (and within 1 ms of its last meeting), the median
normal approach speed and the shares below 0.05 / 0.2 / 0.5 m/s. Lasting contacts that chatter (many slow onsets of
the same pairs) show as a high repeat share with slow speeds; the rig's cross-stream onsets of the CFD-DEM read
as real impacts (few repeats, approach speeds of the streams' relative motion).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

SLOW = (0.05, 0.2, 0.5)
"""Approach speeds, m/s, whose shares are given."""


def load(path: str) -> dict:
    """The arrays of one ``--collision-events`` file (a clear error for anything else)."""
    try:
        d = np.load(path)
    except (OSError, ValueError) as exc:
        raise SystemExit(f"collision_events: cannot read {path}: {exc}")
    need = ("particle_a", "particle_b", "speed", "time", "stream_a", "stream_b")
    missing = [k for k in need if k not in d]
    if missing:
        raise SystemExit(f"collision_events: {path} lacks {', '.join(missing)}; write it with "
                         "cases/colliding_streams.py --collision-events")
    return {k: d[k] for k in d.files}


def repeats(a: np.ndarray, b: np.ndarray, t: np.ndarray, within: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Per event: whether its pair met before in the list, and whether that was less than ``within`` s earlier."""
    key = a.astype(np.int64) * (int(max(b.max(initial=0), a.max(initial=0))) + 1) + b.astype(np.int64)
    order = np.lexsort((t, key))
    k, ts = key[order], t[order]
    again = np.zeros(len(k), bool)
    again[1:] = k[1:] == k[:-1]
    soon = np.zeros(len(k), bool)
    soon[1:] = again[1:] & (ts[1:] - ts[:-1] < within)
    rep, rep_soon = np.empty(len(k), bool), np.empty(len(k), bool)
    rep[order], rep_soon[order] = again, soon
    return rep, rep_soon


def groups(d: dict) -> dict:
    """Masks of the groups of one run: all, each stream pair present, and for two size classes the cross-stream
    pairs by class (small-small, small-large, large-large; the classes split at the mean of the extreme radii)."""
    sa, sb = d["stream_a"], d["stream_b"]
    out = {"all": np.ones(len(sa), bool)}
    for x, y in sorted(set(zip(sa.tolist(), sb.tolist()))):
        out[f"streams {x}-{y}"] = (sa == x) & (sb == y)
    ra, rb = d.get("radius_a"), d.get("radius_b")
    if ra is not None and len(ra) and np.nanmax(ra) > 1.2 * np.nanmin(ra):
        cut = 0.5 * (np.nanmin(ra) + np.nanmax(ra))
        big_a, big_b = ra > cut, rb > cut
        cross = sa != sb
        out["cross small-small"] = cross & ~big_a & ~big_b
        out["cross small-large"] = cross & (big_a ^ big_b)
        out["cross large-large"] = cross & big_a & big_b
    return out


def summary(d: dict) -> dict:
    """The figures of every group of one run."""
    rep, soon = repeats(d["particle_a"], d["particle_b"], d["time"])
    res = {}
    for name, m in groups(d).items():
        n = int(m.sum())
        s = d["speed"][m]
        res[name] = {"count": n,
                     "repeat_share": float(rep[m].mean()) if n else None,
                     "repeat_within_1ms_share": float(soon[m].mean()) if n else None,
                     "median_speed": float(np.median(s)) if n else None,
                     **{f"share_below_{v:g}": (float(np.mean(s < v)) if n else None) for v in SLOW}}
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("files", nargs="+", help="--collision-events files")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)
    out = {path: summary(load(path)) for path in args.files}
    if args.json:
        print(json.dumps(out))
        return 0
    for path, res in out.items():
        print(path)
        for name, r in res.items():
            if not r["count"]:
                continue
            print(f"  {name:20s} {r['count']:9d}  repeats {r['repeat_share']:.3f} (within 1 ms "
                  f"{r['repeat_within_1ms_share']:.3f})  median speed {r['median_speed']:.3f} m/s  below "
                  + " / ".join(f"{v:g}: {r[f'share_below_{v:g}']:.3f}" for v in SLOW))
    return 0


if __name__ == "__main__":
    sys.exit(main())

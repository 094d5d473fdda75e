"""A tiny case script that honours the case contract of ``hel-warp ensemble`` without Warp (tests/test_ensemble.py).

A random walk of ``--steps`` steps, x_{k+1} = x_k + scale * z_k with z_k drawn from the generator seeded by
(seed, k), so a run resumed from its checkpoint ends exactly where an uninterrupted one does. Each step sleeps
``--sleep`` seconds (a member that lasts long enough to be interrupted) and writes ``OUT/checkpoint.npz``
atomically. The contract: ``--seed``, ``--out``, ``--overwrite``, ``--resume`` (left out of the options when the
environment holds ``TOY_NO_RESUME=1``: a case without it), ``--json`` (the last stdout line is the summary, also
written to ``OUT/summary.json`` with ``"status": "complete"``), ``--no-progress``; exit 0 ok, 1 a failed check
(``--check-fail-seed``: the summary is written, the check fails), 2 bad input (``--fail-seed``: one line
``toy: error: ...`` on stderr, nothing written).
``pooled_metrics`` is the ensemble's optional hook of a case module.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def pooled_metrics(member_dirs, reference_dirs=None) -> dict:
    """The hook of ``hel-warp ensemble``: the sum of the members' final positions, read from their folders."""
    xs = [json.loads((Path(d) / "summary.json").read_text())["x"] for d in member_dirs]
    return {"metrics": {"sum_x": sum(xs)}, "stderr": {"sum_x": 0.0},
            "reference_members": None if reference_dirs is None else len(reference_dirs)}


def main(argv=None) -> int:
    p = _Parser(prog="toy", description="random walk case for the ensemble tests")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    p.add_argument("--overwrite", action="store_true")
    if os.environ.get("TOY_NO_RESUME") != "1":
        p.add_argument("--resume", action="store_true")
    p.add_argument("--json", action="store_true")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--steps", type=int, default=4)
    p.add_argument("--scale", type=float, default=1.0)
    p.add_argument("--offset", type=float, default=0.0)
    p.add_argument("--sleep", type=float, default=0.0)
    p.add_argument("--fail-seed", type=int, action="append", default=[])
    p.add_argument("--check-fail-seed", type=int, action="append", default=[])
    args = p.parse_args(argv)
    resume = getattr(args, "resume", False)
    if args.seed in args.fail_seed:
        print(f"toy: error: seed {args.seed} refused on purpose", file=sys.stderr)
        return 2
    out = Path(args.out)
    if out.exists() and not (args.overwrite or resume):
        print(f"toy: error: {out} exists; use --overwrite or --resume", file=sys.stderr)
        return 2
    if out.exists() and args.overwrite:
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    x, start = args.offset, 0
    if resume and (out / "checkpoint.npz").exists():
        with np.load(out / "checkpoint.npz") as ck:
            x, start = float(ck["x"]), int(ck["step"])
        with open(out / "resumed_from.txt", "a") as fh:  # beside the summary, so the summary is the same
            fh.write(f"{start}\n")
    for k in range(start, args.steps):
        x += args.scale * float(np.random.default_rng([args.seed, k]).normal())
        time.sleep(args.sleep)
        np.savez(out / "checkpoint.tmp.npz", x=x, step=k + 1)
        os.replace(out / "checkpoint.tmp.npz", out / "checkpoint.npz")
    summary = {"case": "toy", "seed": args.seed, "x": x, "x2": x * x, "steps": args.steps, "flag": True,
               "label": "walk", "nested": {"half": 0.5 * x, "none": None}, "short": [x, 2 * x],
               "long": list(range(100)), "wall_clock_s": time.perf_counter(), "status": "complete"}
    check_failed = args.seed in args.check_fail_seed
    if check_failed:
        summary["check_errors"] = ["x out of range on purpose"]
    with open(out / "summary.json", "w") as fh:
        json.dump(summary, fh)
    if args.json:
        print(json.dumps(summary))
    if check_failed:
        print("toy: check failed: x out of range on purpose", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

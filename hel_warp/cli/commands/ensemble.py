"""``hel-warp ensemble``: a case script over seeds x parameter values on Dask, with means and standard errors."""

from __future__ import annotations

import argparse
import json
import sys

USAGE = ("hel-warp ensemble CASE.py --seeds A-B [--set NAME=V1,V2 ...] --out DIR [--scheduler ADDRESS] "
         "[--workers N] [--reference DIR] [--json] [--no-progress] -- [case args]")

DESCRIPTION = """\
Run CASE.py once per member of the product of the seeds and the --set values, each as one Dask task and one process
of its own (python CASE.py <case args> --NAME V ... --seed S --out DIR/<NAME>=<V>_..._seed<S> --json), then write
DIR/ensemble.json and print, per parameter combination, the mean and jackknife standard error of every metric the
case's JSON summary reports (with --reference, the difference from another ensemble and its error). Rerunning the
same command skips finished members and resumes interrupted ones from their checkpoint; a failed member is
reported with its one-line error and the rest go on. Exit code 0 when every member is ok, 1 when some are not.
Guide: docs/ensembles.md."""


def _add_options(p: argparse.ArgumentParser) -> None:
    from hel_warp.cli.commands._common import int_at_least

    p.add_argument("--seeds", metavar="A-B", help="the seeds, A to B inclusive (or a comma-separated list of seeds "
                                                  "and ranges); each goes to the case's --seed (required)")
    p.add_argument("--set", action="append", metavar="NAME=V1,V2", dest="sets",
                   help="sweep the case's --NAME over these values (repeatable: the product of all)")
    p.add_argument("--out", metavar="DIR", help="the ensemble's folder: one folder per member, ensemble.json "
                                                "(required)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="a running Dask scheduler (tcp://host:8786) or its scheduler file; default: a local cluster")
    p.add_argument("--workers", type=int_at_least(1), metavar="N",
                   help="single-threaded workers of the local cluster (default: the cores); not with --scheduler")
    p.add_argument("--reference", metavar="DIR",
                   help="another ensemble's DIR: each metric's difference from it, with its standard error")
    p.add_argument("--json", action="store_true", help="print ensemble.json's object (with 'run') as one line")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def add_parser(subparsers):
    p = subparsers.add_parser("ensemble", help="a case over seeds x parameter values on Dask (means, std. errors)",
                              description=DESCRIPTION, usage=USAGE,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_options(p)
    # argparse cannot take options after a positional and then a '--' list in one pass (a positional list after
    # the case swallows the options, or is matched empty at once); the rest is parsed again in run()
    p.add_argument("rest", nargs=argparse.REMAINDER, metavar="CASE.py ... -- CASE_ARGS",
                   help="the case script (a path, or a name in cases/), then after -- the options every member gets")
    p.set_defaults(_ensemble_parser=p)
    return p


def _parse_rest(args) -> None:
    """Fill ``args.case`` and ``args.case_args`` from ``args.rest`` (the case, options given after it, ``--``, the
    case's own options)."""
    from hel_warp.errors import ConfigError

    class _Parser(argparse.ArgumentParser):
        def error(self, message):  # one line through the command line's handler, exit code 2
            raise ConfigError(message)

    rest = list(args.rest)
    before, after = (rest[: rest.index("--")], rest[rest.index("--") + 1:]) if "--" in rest else (rest, [])
    if "-h" in before or "--help" in before:
        args._ensemble_parser.print_help()
        raise SystemExit(0)
    inner = _Parser(prog="hel-warp ensemble", add_help=False, argument_default=argparse.SUPPRESS, usage=USAGE)
    _add_options(inner)
    inner.add_argument("case", nargs="?")
    _, unknown = inner.parse_known_args(before, namespace=args)
    if unknown:
        raise ConfigError(f"unrecognized arguments: {' '.join(unknown)} (the case's own options go after --: "
                          f"hel-warp ensemble CASE.py --seeds A-B --out DIR -- {' '.join(unknown)})")
    args.case_args = after
    if getattr(args, "case", None) is None:
        raise ConfigError("no case script; give hel-warp ensemble CASE.py --seeds A-B --out DIR -- [case args]")
    missing = [opt for opt, value in (("--seeds", args.seeds), ("--out", args.out)) if value is None]
    if missing:
        raise ConfigError(f"{' and '.join(missing)} required: hel-warp ensemble CASE.py --seeds A-B --out DIR")
    if args.scheduler and args.workers is not None:
        raise ConfigError("--workers sizes the local cluster; with --scheduler the cluster's workers run the members")


def run(args) -> int:
    from hel_warp.studies.ensemble import format_table, parse_seeds, parse_sets, run_ensemble

    _parse_rest(args)
    seeds = parse_seeds(args.seeds)
    sets = parse_sets(args.sets)
    result = run_ensemble(args.case, seeds, sets, args.out, args.case_args, scheduler=args.scheduler,
                          workers=args.workers, reference=args.reference, progress=not args.no_progress,
                          say=lambda line: print(line, file=sys.stderr))
    if args.json:
        print(json.dumps(result))
    else:
        print(format_table(result))
        run_info = result["run"]
        print(f"\n{len(run_info['ran'])} members run, {run_info['skipped']} already finished; "
              f"{run_info['wall_s']:.1f} s; {run_info['out']}/ensemble.json")
    not_ok = [e for e in result["members"] if e["status"] != "ok"]
    pooled_failed = any("error" in (c.get("pooled") or {}) for c in result["combinations"])
    return 1 if not_ok or pooled_failed else 0

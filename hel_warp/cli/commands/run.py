"""``hel-warp run CASE_SCRIPT [case options...]``: run a case script, passing its options through.

``CASE_SCRIPT`` is a path to a Python file (``cases/colliding_streams.py``) or the name of a script in
``cases/`` (``colliding_streams``). The script is called, in order of preference, through

- ``main(argv) -> int``: its own argument parsing (``argv`` = the options after the script);
- ``add_arguments(parser)`` and ``run(args) -> int``: options parsed strictly here (a typo is an error);
- otherwise it is executed as ``__main__`` with ``sys.argv = [CASE_SCRIPT, *options]``.

The scripts in ``cases/`` describe their flow with the case API (``hel_warp.case``), which gives every one of them
the shared options: --out, --overwrite | --resume, --end-time, --dt, --collisions, --model, --seed, --device,
--output-interval, --checkpoint-interval, --no-vtk, --json, --no-progress (``CASE_SCRIPT --help`` lists them
with the case's own). Example, a reduced colliding-streams rig (about 5,000 cells, 200 parcels, three steps of
KTGF; under a minute on one core)::

    hel-warp run colliding_streams --diameter 315e-6 --dt 1e-3 --collisions ktgf --end-time 0.003 \\
        --cells 5000 --max-particles 200 --out runs/streams --overwrite
"""

from __future__ import annotations

import argparse
import runpy
import sys
from pathlib import Path

from hel_warp.cli.commands._common import case_path, load_case_module



def add_parser(subparsers):
    p = subparsers.add_parser("run", help="run a HEL case script (e.g. cases/colliding_streams.py), options passed on",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("case", metavar="CASE_SCRIPT", help="case script path or name in cases/")
    p.add_argument("case_args", nargs=argparse.REMAINDER, help="options of the case (see CASE_SCRIPT --help)")
    return p


def _top_level_functions(path: Path) -> set[str]:
    """Names of the functions a script defines at top level (read without executing it)."""
    import ast

    tree = ast.parse(path.read_text(), filename=str(path))
    return {node.name for node in tree.body if isinstance(node, ast.FunctionDef)}


def run(args) -> int:
    path = case_path(args.case)
    argv = list(args.case_args)
    if argv[:1] == ["--"]:
        argv = argv[1:]
    defined = _top_level_functions(path)
    if "main" in defined or {"add_arguments", "run"} <= defined:
        module = load_case_module(str(path))
    if "main" in defined:
        return int(module.main(argv) or 0)
    if {"add_arguments", "run"} <= defined:
        parser = argparse.ArgumentParser(prog=f"hel-warp run {args.case}", description=module.__doc__)
        module.add_arguments(parser)
        return int(module.run(parser.parse_args(argv)) or 0)
    saved = sys.argv
    sys.argv = [str(path), *argv]
    try:
        runpy.run_path(str(path), run_name="__main__")
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        sys.argv = saved
    return 0

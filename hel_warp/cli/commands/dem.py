"""``hel-warp dem CASE [case options...]``: run an N-body DEM case script.

``CASE`` is a path to a Python file or the name of a script in ``cases/`` (``settling_column``).
A case module exposes ``add_arguments(parser)`` (its own options, parsed strictly: a typo is an
error) and ``run(args, *, progress: bool) -> int`` (build, simulate with a tqdm bar, write
``--out``, check physical facts; returns the exit code). ``hel-warp dem CASE --help`` lists the
case's options.
"""

from __future__ import annotations

import argparse

from hel_warp.errors import ConfigError



def add_parser(subparsers):
    p = subparsers.add_parser("dem", help="run an N-body DEM case script (e.g. cases/settling_column.py)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("case", help="case script path or name in cases/")
    p.add_argument("case_args", nargs=argparse.REMAINDER, help="options of the case (see CASE --help)")
    return p


def load_case(name: str):
    """Import a case script from a path or from ``cases/NAME.py``."""
    from hel_warp.cli.commands._common import case_path, load_case_module

    path = case_path(name)
    module = load_case_module(str(path))
    for attr in ("add_arguments", "run"):
        if not hasattr(module, attr):
            raise ConfigError(f"case {path} defines no {attr}(); a case exposes add_arguments(parser) and "
                              "run(args, progress=...)")
    return module


def run(args) -> int:
    from hel_warp.cli import _Parser

    if args.case in ("-h", "--help"):
        print(__doc__)
        return 0
    module = load_case(args.case)
    parser = _Parser(prog=f"hel-warp dem {args.case}", description=(module.__doc__ or "").split("\n\n")[0])
    module.add_arguments(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    case_args = parser.parse_args(args.case_args)
    return int(module.run(case_args, progress=not case_args.no_progress) or 0)

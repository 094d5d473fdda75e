"""The ``hel-warp`` command line.

Each subcommand lives in its own module ``hel_warp/cli/commands/<name>.py`` exposing
``add_parser(subparsers)`` (registers the options) and ``run(args) -> int``. Heavy imports
(warp, xgboost, optuna, pyvista) stay inside ``run`` so ``hel-warp --help`` is instant.

Every error raised on purpose (``HelWarpError``) and every bad option prints one line
``hel-warp: error: ...`` on stderr and exits with code 2, never a traceback. A ``--device`` is checked before
the command runs (``hel_warp.runs.run.check_device``), and Warp's own error for a CUDA device that is not there,
raised from inside a case script or a library call, is turned into the same one line.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from hel_warp.errors import HelWarpError

# name -> module under hel_warp.cli.commands; a module not (yet) present is skipped.
COMMANDS = ("timestep", "impact", "dem", "dataset", "train", "predict", "particle", "run", "report", "demo", "ensemble")


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit code 2 (argparse's default code too)
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="hel-warp", description=__doc__.splitlines()[0])
    from hel_warp import __version__

    parser.add_argument("--version", action="version", version=f"hel-warp {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    subparsers.required = True
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"hel_warp.cli.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"hel_warp.cli.commands.{name}":
                continue
            raise
        sub = module.add_parser(subparsers)
        sub.set_defaults(_run=module.run)
    return parser


_NO_CUDA = ('"cuda" device requested', "CUDA is not supported", "Invalid device identifier")


def refused(exc: Exception) -> int:
    """The one line ``hel-warp: error: ...`` of a run the user's input stops (a ``HelWarpError``, or Warp's
    RuntimeError for a CUDA device this machine lacks) on stderr, and exit code 2; anything else is re-raised."""
    if isinstance(exc, HelWarpError):
        message = str(exc)
    elif isinstance(exc, RuntimeError) and any(text in str(exc) for text in _NO_CUDA):
        message = f"Warp: {str(exc).splitlines()[0]}; use --device cpu"
    else:
        raise exc
    print(f"hel-warp: error: {message}", file=sys.stderr)
    return 2
"""Warp's RuntimeError messages for a device that is not on this machine (warp/_src/context.py)."""


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if getattr(args, "device", None) is not None:
            from hel_warp.runs.run import check_device

            check_device(args.device)
        code = args._run(args)
    except (HelWarpError, RuntimeError) as exc:
        return refused(exc)
    except KeyboardInterrupt:
        print("hel-warp: interrupted; rerun the same command to resume where supported", file=sys.stderr)
        return 130
    return int(code or 0)

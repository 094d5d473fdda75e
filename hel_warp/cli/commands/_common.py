"""Option parsing shared by the subcommands: vectors, finite numbers, JSON output, materials."""

from __future__ import annotations

import argparse
import json

from hel_warp.errors import ConfigError, finite_float  # noqa: F401  (re-exported for the commands)


def int_at_least(minimum: int):
    """argparse type: an integer >= ``minimum`` (anything else is refused with a one-line error)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value

    return parse


def vector3(text: str) -> tuple[float, float, float]:
    """argparse type: ``VX,VY,VZ`` -> a tuple of three finite floats."""
    parts = text.split(",")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected three comma-separated numbers VX,VY,VZ, got {text!r}")
    return tuple(finite_float(p) for p in parts)  # type: ignore[return-value]


def add_json_flag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")


def add_material_options(parser: argparse.ArgumentParser, suffix: str = "", *, defaults: bool = True) -> None:
    """Options ``--density``, ``--youngs``, ``--poisson``, ``--restitution``, ``--friction`` (+ suffix)."""
    from hel_warp.material import Material

    d = Material()
    helpless = {} if defaults else {"default": None}
    parser.add_argument(f"--density{suffix}", type=finite_float, **({"default": d.density} | helpless),
                        help="material density, kg/m^3 (default: polyethylene 1000)")
    parser.add_argument(f"--youngs{suffix}", type=finite_float, **({"default": d.youngs_modulus} | helpless),
                        help="Young's modulus, Pa (default 5e8)")
    parser.add_argument(f"--poisson{suffix}", type=finite_float, **({"default": d.poisson_ratio} | helpless),
                        help="Poisson ratio in (-1, 0.5) (default 0.4)")


def emit(result: dict, as_json: bool, text_lines: list[str] | None = None) -> None:
    """Print ``result`` as one JSON object, or as readable ``key: value`` lines."""
    if as_json:
        print(json.dumps(result))
        return
    if text_lines is not None:
        print("\n".join(text_lines))
        return
    for key, value in result.items():
        print(f"{key}: {value}")


def require(condition: bool, message: str) -> None:
    if not condition:
        raise ConfigError(message)


CASES_DIR = __import__("pathlib").Path(__file__).resolve().parents[3] / "cases"
"""The repository's case scripts."""


def case_path(name: str):
    """The script file of ``name`` (a path, or a name in ``cases/``); ConfigError listing the known cases."""
    from pathlib import Path

    path = Path(name)
    if not path.suffix and not path.is_file():
        path = CASES_DIR / f"{name}.py"
    if not path.is_file():
        known = sorted(p.stem for p in CASES_DIR.glob("*.py")) if CASES_DIR.is_dir() else []
        raise ConfigError(f"case script {name!r} not found (looked for {path}); known cases in {CASES_DIR}: {known}")
    return path


def load_case_module(name: str):
    """Import a case script (path or name in ``cases/``) as module ``hel_warp_case_<stem>``.

    The module is registered in ``sys.modules`` before it runs, as a normal import would be, so
    dataclasses and pickling-free introspection that look the module up by name work.
    """
    import importlib.util
    import sys

    path = case_path(name)
    module_name = f"hel_warp_case_{path.stem}"
    spec = importlib.util.spec_from_file_location(module_name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(module_name, None)
        raise
    return module

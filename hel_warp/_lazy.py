"""Public names of a room, imported on first use.

A room's ``__init__`` lists its names and the module that defines each; ``from hel_warp.gas import GasSolver``
then imports ``hel_warp.gas.solver`` only when asked. Importing every module of a room up front would cost the
Warp module builds of rooms a script never uses, and would make rooms that use one another import in a cycle."""

from __future__ import annotations

import importlib


def exports(package: str, names: dict[str, str]):
    """``__getattr__`` and ``__dir__`` for ``package`` whose public ``names`` map to their module (relative)."""

    def __getattr__(name):
        module = names.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f"{package}.{module}"), name)

    def __dir__():
        return sorted(names)

    return __getattr__, __dir__

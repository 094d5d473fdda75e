"""hel_warp: a particle engine for gas-solid flows on NVIDIA Warp.

The project's rooms (docs/developer/architecture.md): ``kernels`` (Warp kernels only), ``hel_warp`` (the host-side
engine), ``surrogate`` (offline data set, training, flattening). Inside ``hel_warp``:

- ``case``: the case API a user describes a flow with (``from hel_warp import case as hc``);
- ``hel``: the HEL step (``HelSolver``, ``HelConfig``) and the ``none`` and ``ktgf`` collision terms;
- ``gas``: grid, geometry and the gas solver;
- ``parcels``: parcel state, injection and the two-way coupling;
- ``collisions``: HELSCM's surrogate, the cell detection, the DEM and CFD-DEM, contact laws, the forest evaluator;
- ``runs``: the time loop, output, checkpoints, the report;
- ``studies``: ensembles of runs;
- ``cli``: the ``hel-warp`` command and its subcommands;
- ``material``, ``errors``: shared by all.
"""

from hel_warp.errors import ConfigError, HelWarpError
from hel_warp.material import Material, TimeStep

__version__ = "0.1.0"

__all__ = ["ConfigError", "HelWarpError", "Material", "TimeStep", "HelSolver", "HelConfig", "__version__"]

from hel_warp._lazy import exports as _exports

__getattr__, _dir = _exports(__name__, {"HelSolver": "hel", "HelConfig": "hel"})


def __dir__():
    return sorted(set(__all__) | set(_dir()))

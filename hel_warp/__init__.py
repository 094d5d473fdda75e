"""hel_warp: a particle engine for gas-solid flows on NVIDIA Warp.

Rooms (docs/developer/architecture.md): ``kernels`` (Warp kernels only), ``hel_warp`` (host-side
engine, CLI), ``surrogate`` (offline data set, training, flattening).
"""

from hel_warp.errors import ConfigError, HelWarpError
from hel_warp.material import Material, TimeStep

__version__ = "0.1.0"

__all__ = ["ConfigError", "HelWarpError", "Material", "TimeStep", "__version__"]

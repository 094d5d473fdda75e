"""The case API: describe a gas-solid flow in a short script and run it with every output the engine has.

A flow is a :class:`Flow` (domain, grid, geometry, gas and its boundaries, gravity, particle species, fills,
injectors, probes); :class:`Case` gives it the shared command line and run loop (``hel-warp run CASE.py``).
See ``docs/case-api.md`` and the scripts in ``cases/``.
"""

from hel_warp.case.build import Settings, Simulation, build
from hel_warp.case.flow import (COLLISION_MODELS, FACES, RANDOM_CLOSE_PACKING, Fill, Flow, Gas, Injector, Inlet,
                                Outlet, Species, Walls)
from hel_warp.case.probes import BedHeight, Plane, Pressure, PressureDrop
from hel_warp.case.runner import Case, Run, floats, ints, weights_of
from hel_warp.case.schedule import Constant, Levels, Profile, Ramp
from hel_warp.gas.grid import Box, Channel, Cylinder
from hel_warp.material import Material

__all__ = ["BedHeight", "Box", "COLLISION_MODELS", "Case", "Channel", "Constant", "Cylinder", "FACES", "Fill",
           "Flow", "Gas", "Injector", "Inlet", "Levels", "Material", "Outlet", "Plane", "Pressure", "PressureDrop",
           "Profile", "RANDOM_CLOSE_PACKING", "Ramp", "Run", "Settings", "Simulation", "Species", "Walls", "build",
           "floats", "ints", "weights_of"]

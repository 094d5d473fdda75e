"""The gas: the Cartesian grid and the flow geometry, and the incompressible gas solver on it.

- ``grid``: ``Grid`` (cubic cells, periodic axes), the geometry as a union of ``Box``, ``Channel`` and ``Cylinder``
  shapes (signed distance), boundary ``Patch``es.
- ``solver``: ``GasSolver`` and ``GasConfig``: projection on the fluid cells with a volume-fraction weighted
  pressure equation, preconditioned CG (``multigrid``), implicit drag exchange with the parcels.
- ``multigrid``: the aggregation V-cycle that preconditions the pressure CG.
"""

from hel_warp._lazy import exports

__getattr__, __dir__ = exports(__name__, {
    "Grid": "grid", "Box": "grid", "Channel": "grid", "Cylinder": "grid", "Patch": "grid", "FlowDomain": "grid",
    "Geometry": "grid", "GasConfig": "solver", "GasSolver": "solver", "GasField": "solver",
})

"""The collision models side by side, and the DEM they are measured against.

- ``models``: HELSCM, the surrogate collision model (``SurrogateCollision``: swept, overlap or cell detection;
  ``SurrogatePaperCollision``: the paper's form). ``none`` and ``ktgf`` are short enough to live with the step in
  ``hel_warp.hel``.
- ``cells``: the cell detection of weighted parcels (Bird's NTC per collision cell) and the MP-PIC packing stress.
- ``cfd_dem``: ``DemCollision``, the CFD-DEM reference: the soft-sphere DEM sub-stepped inside a HEL step.
- ``dem``: ``DEMSolver``, the N-body soft-sphere DEM (Hertz-Mindlin, or a linear spring-dashpot).
- ``contact_law``: the contact laws and their calibration to a restitution coefficient.
- ``impact``: batched binary collisions (``hel-warp impact``, the data set's generator).
- ``forest``: the trained XGBoost model as flat node arrays evaluated in Warp kernels.
- ``pairs``: pair detection and per-stream-pair counts shared by the strategies.
- ``mixture``: size mixtures: species, fractions, pair types and their kinetic theory.
"""

from hel_warp._lazy import exports

__getattr__, __dir__ = exports(__name__, {
    "SurrogateCollision": "models", "SurrogatePaperCollision": "models", "CellCollisions": "cells",
    "CellConfig": "cells", "DemCollision": "cfd_dem", "DEMSolver": "dem", "DEMConfig": "dem",
    "FlatForest": "forest", "ForestPredictor": "forest", "PairDetector": "pairs",
})

"""A run's life and what it leaves: the time loop, its output and checkpoints, the report.

- ``run``: ``Run`` and ``RunConfig``: steps to an end time, snapshots and checkpoints at intervals, ``--resume``,
  the kernel load kept out of the timings.
- ``io``: ``RunWriter``: particle snapshots in ``run.zarr`` and VTK files.
- ``report``: ``hel-warp report``: a run folder (or several) to figures and ``summary.md``.
- ``counters``: kernel launches, graph launches and device reads counted per step.
"""

from hel_warp._lazy import exports

__getattr__, __dir__ = exports(__name__, {
    "Run": "run", "RunConfig": "run", "RunWriter": "io", "Counts": "counters",
})

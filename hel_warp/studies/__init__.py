"""Studies of many runs: ``ensemble`` (``hel-warp ensemble``: seeds times parameter values on a Dask cluster, means
and jackknife errors) and ``rig_ensemble`` (the colliding-streams rig's per-section figures against a reference)."""

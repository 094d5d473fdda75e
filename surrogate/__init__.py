"""The offline side of HELSCM: collision data set (configurations, batched DEM binary impacts,
zarr store), training, model artifact and flattening (see docs/developer/architecture.md "Surrogate pipeline").

Submodules are imported on use (``surrogate.configurations``, ``surrogate.dataset``) so that
importing the package stays cheap.
"""

"""The floor every wing stands on: array helpers (``arrays``), files written whole
(``files``), where everything lives (``paths``), Zarr stores (``stores``), the errors of
bad input (``errors``), dtype names (``dtypes``), the torch device (``devices``) and the
component registry (``registry``). Imports nothing from the other wings (the registry
names their loaders as strings, resolved on first use).
"""

"""The floor every wing stands on: array helpers (``arrays``), files written whole
(``files``), where everything lives (``paths``), Zarr stores (``stores``), runs of one
folder at a time (``runs``), the errors of bad input (``errors``), dtype names
(``dtypes``) and the torch device (``devices``). Imports nothing from the other wings.
"""

"""The workflow's stages, one module per Snakemake rule, named after it.

Each module holds the function its rule runs (inputs are store paths, output is a
store) and the readers later stages use on that store; :mod:`.jobs` is the table of
those functions that the rules' one script (``workflow/scripts/stage.py``), the tests
and the benchmarks share. ``record`` is the stage's hashed record from
:mod:`vprflow.planning.plan` (``record["params"]`` holds the stage's own parameters); it is
written into the output store's attributes so every store documents itself.

Per-image stages (features, segments, descriptors) take ``start``/``stop``: a shard
of the concatenated image list (references first, then queries); :mod:`.gather`
concatenates the shards. Reading order: dataset, features, segments, vocabulary, pca,
descriptors, gather, recall, report.
"""

"""The workflow's stages, one module per Snakemake rule, named after it.

Each stage's function, named ``<verb>_<stage>`` (``build_images``, ``compute_features``,
``fit_pca``, ``compute_recall``, ...), takes one :class:`~vprflow.stages.base.Job` (its
record, input stores by name, output, image range and how to run) and writes its output
store.
Later stages read a store through :mod:`.readers` (every store's arrays and their
names) and a method's ranking through :mod:`.retrieval`; no stage imports another.
:mod:`.jobs` binds each row of :data:`vprflow.planning.plan.STAGES` to its function and
runs it for the rules' one script (``workflow/scripts/stage.py``), the tests and the
benchmarks. ``record`` is the stage's hashed record from
:mod:`vprflow.planning.plan` (``record["params"]`` holds the stage's own parameters); it is
written into the output store's attributes so every store documents itself.

Sharded stages (features, segments, descriptors over all images, references first; the
segment search over the reference images) run one job per ``start``/``stop`` range;
:mod:`.gather` concatenates the shards, :func:`.search.merge_search` merges search
shards. Reading order, as the data flows: dataset (the ``images`` and ``dataset``
stages), features, segments, vocabulary, pca, descriptors, search, matches, rerank,
recall, then the outputs that are no stages: report, figures, export.
"""

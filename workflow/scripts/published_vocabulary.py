from vprflow.aggregation.vocabularies import fetch_vocabulary
from vprflow.stages.runner import run_stage

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(sm.log[0], lambda: fetch_vocabulary(sm.params.url, sm.params.sha256, sm.output[0]), 1)

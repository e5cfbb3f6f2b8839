from vprflow.runner import run_stage
from vprflow.vocabularies import fetch_vocabulary

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(sm.log[0], lambda: fetch_vocabulary(sm.params.url, sm.params.sha256, sm.output[0]), 1)

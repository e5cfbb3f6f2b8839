from vprflow.planning.checkpoints import fetch_checkpoint
from vprflow.stages.runner import run_stage

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(sm.log[0], lambda: fetch_checkpoint(sm.params.url, sm.params.sha256, sm.output[0]), 1)

from vprflow.runner import run_stage
from vprflow.stages.jobs import combine_shards

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0], lambda: combine_shards(list(sm.input), sm.params.record, sm.output[0]), sm.threads
)

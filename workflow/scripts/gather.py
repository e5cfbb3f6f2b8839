from vprflow.stages.jobs import combine_shards
from vprflow.stages.runner import run_stage

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0], lambda: combine_shards(list(sm.input), sm.params.record, sm.output[0]), sm.threads
)

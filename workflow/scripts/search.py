from vprflow.runner import run_stage
from vprflow.stages.search import search_shard

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0],
    lambda: search_shard(
        sm.input.dataset,
        sm.input.descriptors,
        sm.params.cfg,
        sm.output[0],
        start=int(sm.wildcards.start),
        stop=int(sm.wildcards.stop),
        device=sm.params.run["device"],
    ),
    sm.threads,
)

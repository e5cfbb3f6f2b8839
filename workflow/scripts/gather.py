from vprflow.runner import run_stage
from vprflow.stages.gather import gather
from vprflow.stages.search import merge_search

sm = snakemake  # noqa: F821 (injected by Snakemake)
# Search shards hold per-shard top-k lists: merged, not concatenated.
combine = merge_search if sm.wildcards.stage == "search" else gather
run_stage(sm.log[0], lambda: combine(list(sm.input), sm.params.cfg, sm.output[0]), sm.threads)

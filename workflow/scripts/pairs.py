from vprflow.runner import run_stage
from vprflow.stages.export import write_pairs

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0],
    lambda: write_pairs(sm.input.dataset, sm.input.recall, sm.output.pairs, sm.output.kapture),
)

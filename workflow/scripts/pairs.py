from vprflow.stages.export import write_pairs
from vprflow.stages.runner import run_stage

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0],
    lambda: write_pairs(
        sm.input.dataset,
        sm.input.recall,
        sm.output.pairs,
        sm.output.kapture,
        sm.params.depth,
        sm.input.descriptors,
        sm.input.get("search"),
    ),
)

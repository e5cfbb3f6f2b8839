from vprflow.evaluation.published_rows import write_published_table
from vprflow.stages.runner import run_stage

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0],
    lambda: write_published_table(
        sm.wildcards.dataset, sm.input[0], sm.output[0], sm.params.changes
    ),
)

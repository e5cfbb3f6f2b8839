from vprflow.stages.report import write_recall_csv
from vprflow.stages.runner import run_stage

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0],
    lambda: write_recall_csv(
        sm.wildcards.dataset, sm.params.runs, list(sm.input.recalls), sm.output[0]
    ),
    sm.threads,
)

from vprflow.stages.figures import write_recall_table
from vprflow.stages.runner import run_stage

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(sm.log[0], lambda: write_recall_table(sm.wildcards.dataset, sm.input[0], sm.output[0]))

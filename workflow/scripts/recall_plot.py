from vprflow.stages.figures import plot_recall
from vprflow.stages.runner import run_stage

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0],
    lambda: plot_recall(
        sm.wildcards.dataset,
        sm.input.dataset,
        sm.params.methods,
        list(sm.input.recalls),
        sm.output[0],
    ),
)

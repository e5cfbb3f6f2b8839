from vprflow.runner import run_stage
from vprflow.stages.figures import plot_recall

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

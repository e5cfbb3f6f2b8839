from vprflow.runner import run_stage
from vprflow.stages import fit_pca_stage

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0],
    lambda: fit_pca_stage(
        sm.input.dataset,
        sm.input.features,
        sm.input.segments,
        sm.input.vocabulary,
        sm.params.cfg,
        sm.output[0],
    ),
    sm.threads,
)

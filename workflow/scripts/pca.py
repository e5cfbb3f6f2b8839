from vprflow.runner import run_stage
from vprflow.stages.pca import fit_pca_stage

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0],
    lambda: fit_pca_stage(dict(sm.input.items()), sm.params.cfg, sm.output[0]),
    sm.threads,
)

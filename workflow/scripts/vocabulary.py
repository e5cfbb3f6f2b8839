from vprflow.runner import run_stage
from vprflow.stages.vocabulary import fit_vocabulary

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0],
    lambda: fit_vocabulary(sm.input.dataset, sm.input.features, sm.params.cfg, sm.output[0]),
    sm.threads,
)

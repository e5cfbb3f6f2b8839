from vprflow.logs import run_logged
from vprflow.stages import evaluate

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_logged(
    sm.log[0],
    lambda: evaluate(sm.input.dataset, sm.input.descriptors, sm.params.cfg, sm.output[0]),
)

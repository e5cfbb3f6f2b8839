from vprflow.runner import run_stage
from vprflow.stages.gather import gather

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(sm.log[0], lambda: gather(list(sm.input), sm.params.cfg, sm.output[0]), sm.threads)

from vprflow.logs import run_logged
from vprflow.stages import gather

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_logged(sm.log[0], lambda: gather(list(sm.input), sm.params.cfg, sm.output[0]))

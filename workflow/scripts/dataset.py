from vprflow.logs import run_logged
from vprflow.stages import build_dataset

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_logged(
    sm.log[0],
    lambda: build_dataset(sm.params.name, sm.params.cfg, sm.params.data_root, sm.output[0]),
)

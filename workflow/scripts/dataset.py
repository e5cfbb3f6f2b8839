from vprflow.runner import run_stage
from vprflow.stages.dataset import build_dataset

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0],
    lambda: build_dataset(
        sm.params.name, sm.params.cfg, sm.params.data_root, sm.output[0], sm.params.fingerprints
    ),
    sm.threads,
)

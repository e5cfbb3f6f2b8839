from vprflow.runner import run_stage
from vprflow.stages.descriptors import compute_descriptors

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0],
    lambda: compute_descriptors(
        dict(sm.input.items()),
        sm.params.cfg,
        sm.output[0],
        start=int(sm.wildcards.start),
        stop=int(sm.wildcards.stop),
        threads=sm.threads,
    ),
    sm.threads,
)

from vprflow.stages.export import export_descriptors
from vprflow.stages.runner import run_stage

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0],
    lambda: export_descriptors(
        sm.wildcards.dataset,
        sm.wildcards.method,
        sm.input.images,
        sm.input.descriptors,
        sm.output[0],
    ),
)

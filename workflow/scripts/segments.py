from vprflow.runner import run_stage
from vprflow.stages.segments import compute_segments

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0],
    lambda: compute_segments(
        sm.input.dataset,
        sm.params.cfg,
        sm.output[0],
        data_root=sm.params.data_root,
        device=sm.params.run["device"],
        batch_size=sm.params.run["batch_size"],
        start=int(sm.wildcards.start),
        stop=int(sm.wildcards.stop),
    ),
    sm.threads,
)

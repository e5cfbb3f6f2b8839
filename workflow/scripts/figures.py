from vprflow.stages.figures import draw_figure
from vprflow.stages.runner import run_stage

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0],
    lambda: draw_figure(
        sm.params.figure,
        dict(sm.input.items()),
        sm.params.data_root,
        sm.wildcards.method,
        sm.params.settings,
        sm.output[0],
    ),
)

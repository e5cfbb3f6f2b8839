from vprflow.runner import run_stage
from vprflow.stages.recall import evaluate

sm = snakemake  # noqa: F821 (injected by Snakemake)
run_stage(
    sm.log[0],
    lambda: evaluate(
        sm.input.dataset,
        sm.input.descriptors,
        sm.params.cfg,
        sm.output[0],
        search_path=sm.input.get("search"),
    ),
    sm.threads,
)

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
        exact_search_path=sm.input.get("exact_search"),
    ),
    sm.threads,
)

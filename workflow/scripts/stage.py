from vprflow.stages.jobs import Job, run_job
from vprflow.stages.runner import run_stage

sm = snakemake  # noqa: F821 (injected by Snakemake)
params, wildcards = dict(sm.params.items()), dict(sm.wildcards.items())
job = Job(
    record=params["record"],
    inputs=dict(sm.input.items()),
    out=sm.output[0],
    start=int(wildcards["start"]) if "start" in wildcards else None,
    stop=int(wildcards["stop"]) if "stop" in wildcards else None,
    data_root=params.get("data_root", ""),
    run=params.get("run", {}),
    threads=sm.threads,
    fingerprints=params.get("fingerprints"),
)
run_stage(sm.log[0], lambda: run_job(job), sm.threads)

# A sharded stage's store, combined from its shards (vprflow.stages.jobs): the stages in
# SHARDED_STAGES (common.smk) run as many small jobs, each over a range of images.
rule gather:
    input:
        shard_inputs,
    output:
        directory(store_pattern("{stage}")),
    log:
        log_pattern("{stage}", "gather"),
    wildcard_constraints:
        stage=SHARDED_STAGES,
    conda:
        "../envs/vprflow.yaml"
    resources:
        mem_mb=lambda wildcards, attempt: 4000 * attempt,
        runtime=lambda wildcards, attempt: 60 * attempt,
    params:
        record=gather_record,
    script:
        "../scripts/gather.py"

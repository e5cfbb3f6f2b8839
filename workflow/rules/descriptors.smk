rule descriptors:
    input:
        unpack(stage_inputs("descriptors")),
    output:
        temp(directory(shard_pattern("descriptors"))),
    log:
        log_pattern("descriptors", "{start}-{stop}"),
    benchmark:
        benchmark_pattern("descriptors", "{start}-{stop}")
    conda:
        "../envs/vprflow.yaml"
    threads: 2
    resources:
        mem_mb=lambda wildcards, attempt: 4000 * attempt,
        runtime=lambda wildcards, attempt: 60 * attempt,
    params:
        record=stage_record("descriptors"),
    script:
        "../scripts/stage.py"

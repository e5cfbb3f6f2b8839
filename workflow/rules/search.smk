rule search:
    input:
        unpack(stage_inputs("search")),
    output:
        temp(directory(shard_pattern("search"))),
    log:
        log_pattern("search", "{start}-{stop}"),
    benchmark:
        benchmark_pattern("search", "{start}-{stop}")
    conda:
        "../envs/vprflow.yaml"
    threads: 2
    resources:
        gpu=gpu_request("search"),
        mem_mb=lambda wildcards, attempt: 4000 * attempt,
        runtime=lambda wildcards, attempt: 60 * attempt,
    params:
        record=stage_record("search"),
        run=stage_run_params("search"),
    script:
        "../scripts/stage.py"

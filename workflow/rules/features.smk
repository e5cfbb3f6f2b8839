rule features:
    input:
        unpack(stage_inputs("features")),
    output:
        temp(directory(shard_pattern("features"))),
    log:
        log_pattern("features", "{start}-{stop}"),
    benchmark:
        benchmark_pattern("features", "{start}-{stop}")
    conda:
        "../envs/vprflow.yaml"
    threads: 4
    resources:
        mem_mb=lambda wildcards, attempt: 16000 * attempt,
        runtime=lambda wildcards, attempt: 120 * attempt,
        gpu=gpu_request("features"),
    params:
        record=stage_record("features"),
        run=stage_run_params("features"),
        data_root=data_root_param,
    script:
        "../scripts/stage.py"

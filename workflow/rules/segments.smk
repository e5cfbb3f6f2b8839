rule segments:
    input:
        unpack(stage_inputs("segments")),
    output:
        temp(directory(shard_pattern("segments"))),
    log:
        log_pattern("segments", "{start}-{stop}"),
    benchmark:
        benchmark_pattern("segments", "{start}-{stop}")
    conda:
        "../envs/vprflow.yaml"
    threads: 4
    resources:
        mem_mb=lambda wildcards, attempt: 16000 * attempt,
        runtime=lambda wildcards, attempt: 180 * attempt,
        gpu=gpu_request("segments"),
    params:
        record=stage_record("segments"),
        run=stage_run_params("segments"),
        data_root=data_root_param,
    script:
        "../scripts/stage.py"

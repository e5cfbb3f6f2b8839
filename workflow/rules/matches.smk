rule matches:
    input:
        unpack(stage_inputs("matches")),
    output:
        directory(store_pattern("matches")),
    log:
        log_pattern("matches"),
    benchmark:
        benchmark_pattern("matches")
    conda:
        "../envs/vprflow.yaml"
    threads: 2
    resources:
        gpu=gpu_request("matches"),
        mem_mb=lambda wildcards, attempt: 8000 * attempt,
        runtime=lambda wildcards, attempt: 120 * attempt,
    params:
        record=stage_record("matches"),
        run=stage_run_params("matches"),
    script:
        "../scripts/stage.py"

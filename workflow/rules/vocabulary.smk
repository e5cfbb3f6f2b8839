rule vocabulary:
    input:
        unpack(stage_inputs("vocabulary")),
    output:
        directory(store_pattern("vocabulary")),
    log:
        log_pattern("vocabulary"),
    benchmark:
        benchmark_pattern("vocabulary")
    conda:
        "../envs/vprflow.yaml"
    threads: 2
    resources:
        gpu=gpu_request("vocabulary"),
        mem_mb=lambda wildcards, attempt: 4000 * attempt,
        runtime=lambda wildcards, attempt: 60 * attempt,
    params:
        record=stage_record("vocabulary"),
        run=stage_run_params("vocabulary"),
    script:
        "../scripts/stage.py"

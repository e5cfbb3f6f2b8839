rule rerank:
    input:
        unpack(stage_inputs("rerank")),
    output:
        directory(store_pattern("rerank")),
    log:
        log_pattern("rerank"),
    benchmark:
        benchmark_pattern("rerank")
    conda:
        "../envs/vprflow.yaml"
    threads: 2
    resources:
        gpu=gpu_request("rerank"),
        mem_mb=lambda wildcards, attempt: 8000 * attempt,
        runtime=lambda wildcards, attempt: 120 * attempt,
    params:
        record=stage_record("rerank"),
        run=stage_run_params("rerank"),
    script:
        "../scripts/stage.py"

rule pca:
    input:
        unpack(stage_inputs("pca")),
    output:
        directory(store_pattern("pca")),
    log:
        log_pattern("pca"),
    benchmark:
        benchmark_pattern("pca")
    conda:
        "../envs/vprflow.yaml"
    threads: 2
    resources:
        mem_mb=lambda wildcards, attempt: 4000 * attempt,
        runtime=lambda wildcards, attempt: 60 * attempt,
    params:
        record=stage_record("pca"),
    script:
        "../scripts/stage.py"

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
    params:
        cfg=stage_params("descriptors"),
    script:
        "../scripts/descriptors.py"

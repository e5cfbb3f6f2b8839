rule descriptors:
    input:
        unpack(stage_inputs("descriptors")),
    output:
        temp(directory("results/cache/descriptors/{key}.shards/{start}-{stop}.zarr")),
    log:
        "logs/descriptors/{key}.{start}-{stop}.log",
    benchmark:
        "logs/descriptors/{key}.{start}-{stop}.benchmark.tsv"
    conda:
        "../envs/vprflow.yaml"
    threads: 2
    params:
        cfg=stage_params("descriptors"),
    script:
        "../scripts/descriptors.py"

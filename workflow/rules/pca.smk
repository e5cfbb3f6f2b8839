rule pca:
    input:
        unpack(stage_inputs("pca")),
    output:
        directory("results/cache/pca/{key}.zarr"),
    log:
        "logs/pca/{key}.log",
    benchmark:
        "logs/pca/{key}.benchmark.tsv"
    conda:
        "../envs/vprflow.yaml"
    threads: 2
    params:
        cfg=stage_params("pca"),
    script:
        "../scripts/pca.py"

rule vocabulary:
    input:
        unpack(stage_inputs("vocabulary")),
    output:
        directory("results/cache/vocabulary/{key}.zarr"),
    log:
        "logs/vocabulary/{key}.log",
    benchmark:
        "logs/vocabulary/{key}.benchmark.tsv"
    conda:
        "../envs/vprflow.yaml"
    threads: 2
    params:
        cfg=stage_params("vocabulary"),
    script:
        "../scripts/vocabulary.py"

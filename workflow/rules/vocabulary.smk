rule vocabulary:
    input:
        unpack(stage_inputs("vocabulary")),
    output:
        directory("results/cache/vocabulary/{key}.zarr"),
    log:
        "logs/vocabulary/{key}.log",
    conda:
        "../envs/vprflow.yaml"
    params:
        cfg=stage_params("vocabulary"),
    script:
        "../scripts/vocabulary.py"

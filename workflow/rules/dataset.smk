rule dataset:
    input:
        dataset_inputs,
    output:
        directory("results/cache/dataset/{key}.zarr"),
    log:
        "logs/dataset/{key}.log",
    conda:
        "../envs/vprflow.yaml"
    params:
        cfg=stage_params("dataset"),
        name=lambda wildcards: planned("dataset", wildcards).dataset,
        data_root=CONFIG["data_root"],
    script:
        "../scripts/dataset.py"

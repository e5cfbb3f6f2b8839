rule segments:
    input:
        unpack(stage_inputs("segments")),
    output:
        temp(directory("results/cache/segments/{key}.shards/{start}-{stop}.zarr")),
    log:
        "logs/segments/{key}.{start}-{stop}.log",
    benchmark:
        "logs/segments/{key}.{start}-{stop}.benchmark.tsv"
    conda:
        "../envs/vprflow.yaml"
    threads: 4
    resources:
        gpu=gpu_request("segments"),
    params:
        cfg=stage_params("segments"),
        run=stage_run_params("segments"),
        data_root=data_root_param,
    script:
        "../scripts/segments.py"

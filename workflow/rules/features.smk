rule features:
    input:
        unpack(stage_inputs("features")),
    output:
        temp(directory("results/cache/features/{key}.shards/{start}-{stop}.zarr")),
    log:
        "logs/features/{key}.{start}-{stop}.log",
    benchmark:
        "logs/features/{key}.{start}-{stop}.benchmark.tsv"
    conda:
        "../envs/vprflow.yaml"
    threads: 4
    resources:
        gpu=gpu_request("features"),
    params:
        cfg=stage_params("features"),
        run=stage_run_params("features"),
        data_root=data_root_param,
    script:
        "../scripts/features.py"


rule gather:
    input:
        shard_inputs,
    output:
        directory("results/cache/{stage}/{key}.zarr"),
    log:
        "logs/{stage}/{key}.gather.log",
    wildcard_constraints:
        stage=SHARDED,
    conda:
        "../envs/vprflow.yaml"
    params:
        cfg=gather_params,
    script:
        "../scripts/gather.py"

rule recall:
    input:
        unpack(stage_inputs("recall")),
    output:
        directory("results/cache/recall/{key}.zarr"),
    log:
        "logs/recall/{key}.log",
    benchmark:
        "logs/recall/{key}.benchmark.tsv"
    conda:
        "../envs/vprflow.yaml"
    threads: 2
    params:
        cfg=stage_params("recall"),
    script:
        "../scripts/recall.py"


rule report:
    input:
        unpack(report_inputs),
    output:
        csv="results/recall_{dataset}.csv",
        predictions="results/predictions_{dataset}.csv",
    log:
        "logs/report/{dataset}.log",
    conda:
        "../envs/vprflow.yaml"
    params:
        runs=report_runs,
    script:
        "../scripts/report.py"


# Writing two small CSV files is not worth a cluster job.
localrules:
    report,

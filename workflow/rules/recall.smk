from vprflow.core.paths import PREDICTIONS_CSV, PUBLISHED_CSV, RECALL_CSV


rule recall:
    input:
        unpack(stage_inputs("recall")),
    output:
        directory(store_pattern("recall")),
    log:
        log_pattern("recall"),
    benchmark:
        benchmark_pattern("recall")
    conda:
        "../envs/vprflow.yaml"
    threads: 2
    resources:
        mem_mb=lambda wildcards, attempt: 4000 * attempt,
        runtime=lambda wildcards, attempt: 60 * attempt,
    params:
        record=stage_record("recall"),
    script:
        "../scripts/stage.py"


rule recall_csv:
    input:
        unpack(report_inputs),
    output:
        report(
            RECALL_CSV,
            caption="../report/recall_csv.rst",
            category="{dataset}",
            subcategory="Recall",
            labels={
                "figure": "Recall@N table (CSV, every parameter)",
                "method": "all",
            },
        ),
    log:
        "logs/recall_csv/{dataset}.log",
    conda:
        "../envs/vprflow.yaml"
    params:
        runs=report_runs,
    script:
        "../scripts/recall_csv.py"


rule predictions:
    input:
        unpack(prediction_inputs),
    output:
        PREDICTIONS_CSV,
    log:
        "logs/predictions/{dataset}.log",
    conda:
        "../envs/vprflow.yaml"
    params:
        runs=report_runs,
    script:
        "../scripts/predictions.py"


# A preset's published recall beside this run's rows (docs/datasets.md): not a
# default target, asked for by name (`snakemake results/published_pitts30k.csv`).
rule published:
    input:
        published_input,
    output:
        PUBLISHED_CSV,
    log:
        "logs/published/{dataset}.log",
    conda:
        "../envs/vprflow.yaml"
    # How this run's rows differ from the published setting: a change reruns this table.
    params:
        changes=published_differences,
    script:
        "../scripts/published_rows.py"


# Writing small CSV files is not worth a cluster job.
localrules:
    recall_csv,
    predictions,
    published,


# A failed run must not leave a results table that looks current (e.g. one method of
# several failed); a good run supersedes the tables an earlier failure withdrew
# (Invocation.failed, Invocation.succeeded).
onerror:
    INVOCATION.failed()


onsuccess:
    INVOCATION.succeeded()

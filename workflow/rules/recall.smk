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
# several failed): the tables of the datasets it asked for that are older than their
# recall stores are renamed to *.stale. Other datasets' tables are no business of this run.
onerror:
    if RUNS_JOBS:
        # Another run of this folder deletes this one's stores: say so beside the failure.
        _others = other_runs(RUN_MARKER.parent, RUN_MARKER) or OTHER_RUNS
        if _others:
            print(f"vprflow: {collision_message(_others)}")
        asked = requested_datasets(CONFIG, workflow.dag_settings.targets)
        for table in withdraw_stale_reports(PLAN, PREFIX, asked):
            print(f"vprflow: {table} is out of date after the failure (renamed)")


# A good run supersedes the tables an earlier failure withdrew, and names the tables of
# the datasets it was asked for.
onsuccess:
    if RUNS_JOBS:
        for stale in clear_superseded(PREFIX):
            print(f"vprflow: removed {stale}: the table beside it is current")
        asked = requested_datasets(CONFIG, workflow.dag_settings.targets)
        print("\n".join(closing_lines(PLAN, PREFIX, asked)))

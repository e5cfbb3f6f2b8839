# The report's figures: rules of their own, outside the content-addressed cache. Their
# settings (`figures:`) are params, so changing one reruns only figures. Each names its
# figure in `params`: a host workflow's `use rule * from vprflow as vpr_*` renames rules.
# A report made without the run's options (its data_root, say) fails naming each gap
# (Invocation.begin).
from vprflow.core.paths import FIGURE, RECALL_CSV, RECALL_PLOT, RECALL_TABLE
from vprflow.planning.reports import FIGURES


rule recall_table:
    input:
        RECALL_CSV,
    output:
        report(
            RECALL_TABLE,
            caption="../report/recall_table.rst",
            category="{dataset}",
            subcategory="Recall",
            labels={"figure": "Recall@N table", "method": "all"},
        ),
    log:
        "logs/figures/{dataset}/recall_table.log",
    conda:
        "../envs/vprflow.yaml"
    script:
        "../scripts/recall_table.py"


rule recall_plot:
    input:
        unpack(report_inputs),
    output:
        report(
            RECALL_PLOT,
            caption="../report/recall_plot.rst",
            category="{dataset}",
            subcategory="Recall",
            labels={"figure": "Recall@N curves", "method": "all"},
        ),
    log:
        "logs/figures/{dataset}/recall_plot.log",
    conda:
        "../envs/vprflow.yaml"
    params:
        methods=lambda wildcards: [run["method"] for run in report_runs(wildcards)],
    script:
        "../scripts/recall_plot.py"


# One rule per figure of the table, named after it.
for _figure, _entry in FIGURES.items():

    rule:
        name:
            _figure
        input:
            unpack(figure_stores(_figure)),
        output:
            report(
                FIGURE.replace("{figure}", _figure),
                caption=f"../report/{_figure}.rst",
                category="{dataset}",
                subcategory=_entry.heading,
                labels={"figure": _entry.label, "method": "{method}"},
            ),
        log:
            f"logs/figures/{{dataset}}/{_figure}/{{method}}.log",
        # A few seconds of matplotlib: not worth a cluster job.
        localrule: True
        conda:
            "../envs/vprflow.yaml"
        params:
            figure=_figure,
            data_root=data_root_param,
            settings=CONFIG["figures"],
        script:
            "../scripts/figures.py"


# A few seconds of matplotlib each: not worth a cluster job.
localrules:
    recall_table,
    recall_plot,

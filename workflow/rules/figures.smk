# The report's figures: rules of their own, outside the content-addressed cache. Their
# settings (`figures:`) are params, so changing one reruns only figures. Each names its
# figure in `params`: a host workflow's `use rule * from vprflow as vpr_*` renames rules.
from vprflow.planning.reports import report_error, report_gaps

# A report made without the run's options (its data_root, say) would look for other
# keys' stores and leave items out without an error: it fails instead, naming each gap.
if workflow.is_main_process and COMMAND.makes_report:
    _gaps = report_gaps(
        PLAN, CONFIG, requested_datasets(CONFIG, COMMAND.targets), PREFIX
    )
    if _gaps:
        raise PlanError(report_error(_gaps))


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
        methods=lambda wildcards: [run.method for run in PLAN.runs[wildcards.dataset]],
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
                figure_pattern(_figure),
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

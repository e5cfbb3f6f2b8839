# The report's figures: rules of their own, outside the content-addressed cache. Their
# settings (`figures:`) are params, so changing one reruns only figures. Each names its
# figure in `params`: a host workflow's `use rule * from vprflow as vpr_*` renames rules.


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


rule retrievals:
    input:
        unpack(figure_stores("retrievals")),
    output:
        report(
            figure_pattern("retrievals"),
            caption="../report/retrievals.rst",
            category="{dataset}",
            subcategory="Retrievals",
            labels={"figure": "retrievals", "method": "{method}"},
        ),
    log:
        "logs/figures/{dataset}/retrievals/{method}.log",
    conda:
        "../envs/vprflow.yaml"
    params:
        figure="retrievals",
        data_root=data_root_param,
        settings=CONFIG["figures"],
    script:
        "../scripts/figures.py"


rule segment_matches:
    input:
        unpack(figure_stores("segment_matches")),
    output:
        report(
            figure_pattern("segment_matches"),
            caption="../report/segment_matches.rst",
            category="{dataset}",
            subcategory="SegVLAD segment matches",
            labels={"figure": "segment matches", "method": "{method}"},
        ),
    log:
        "logs/figures/{dataset}/segment_matches/{method}.log",
    conda:
        "../envs/vprflow.yaml"
    params:
        figure="segment_matches",
        data_root=data_root_param,
        settings=CONFIG["figures"],
    script:
        "../scripts/figures.py"


rule support_maps:
    input:
        unpack(figure_stores("support_maps")),
    output:
        report(
            figure_pattern("support_maps"),
            caption="../report/support_maps.rst",
            category="{dataset}",
            subcategory="SNSM support maps",
            labels={"figure": "support maps", "method": "{method}"},
        ),
    log:
        "logs/figures/{dataset}/support_maps/{method}.log",
    conda:
        "../envs/vprflow.yaml"
    params:
        figure="support_maps",
        data_root=data_root_param,
        settings=CONFIG["figures"],
    script:
        "../scripts/figures.py"


# A few seconds of matplotlib each: not worth a cluster job.
localrules:
    recall_table,
    recall_plot,
    retrievals,
    segment_matches,
    support_maps,

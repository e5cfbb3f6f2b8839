# vprflow: training-free visual place recognition as a content-addressed workflow.
# The rules live in workflow/rules/; this file only includes them.


include: "workflow/rules/common.smk"
include: "workflow/rules/dataset.smk"
include: "workflow/rules/features.smk"
include: "workflow/rules/segments.smk"
include: "workflow/rules/vocabulary.smk"
include: "workflow/rules/pca.smk"
include: "workflow/rules/descriptors.smk"
include: "workflow/rules/recall.smk"


rule all:
    default_target: True
    input:
        "results/recall_corridor.csv",

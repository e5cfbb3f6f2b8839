# Public datasets on demand (docs/usage.md, "Getting the data"): `snakemake --cores 1
# results/downloads/<dataset>.json` fetches the dataset's `download` archive, verifies
# it and lays out its folder under data_root when the folder is missing, then writes
# this record. Nothing here lists images, so the target works while the data is absent.
# `download` is a Snakemake checkpoint (the only one: everywhere else in vprflow a
# checkpoint is a trained model's weights file): a run that needs a sample dataset
# whose folder is missing plans its stores once this job laid it out (`downloaded` in
# common.smk).
from vprflow.core.paths import (
    DOWNLOAD_LOG,
    DOWNLOAD_RECORD,
    PUBLISHED_VOCABULARY,
    dataset_folder,
)
from vprflow.aggregation.vocabularies import (
    PUBLISHED as PUBLISHED_VOCABULARIES,
    vocabulary_url,
)
from vprflow.data.download import download_entry, manifest_inputs
from vprflow.planning.checkpoints import (
    ABSOLUTE_OUTPUT,
    checkpoint_url,
    fetchable_paths,
    output_pattern,
)

# Shipped manifests are named relative to workflow/ (found while this file is parsed).
WORKFLOW_DIR = Path(workflow.current_basedir).parent
# The trained checkpoints the plan reads (a re-plan after a download changes none).
CHECKPOINTS = INVOCATION.plan.checkpoints


# Network access happens where Snakemake runs, not in a cluster job.
localrules:
    download,
    published_vocabulary,
    trained_checkpoint,
    trained_checkpoint_absolute,


checkpoint download:
    input:
        manifest=lambda wildcards: manifest_inputs(
            started().config, wildcards.dataset, WORKFLOW_DIR
        ),
    output:
        DOWNLOAD_RECORD,
    log:
        DOWNLOAD_LOG,
    conda:
        "../envs/vprflow.yaml"
    params:
        entry=lambda wildcards: download_entry(CONFIG, wildcards.dataset),
        folder=lambda wildcards: str(
            dataset_folder(CONFIG["data_root"], CONFIG["datasets"][wildcards.dataset])
        ),
    message:
        "vprflow: dataset {wildcards.dataset}: downloading into {params.folder} (progress: {log})"
    script:
        "../scripts/download.py"


# A vocabulary the SegVLAD authors publish (vprflow.aggregation.vocabularies), fetched once; the
# vocabulary stage checks the file's SHA-256 again, so one put here by hand must match.
rule published_vocabulary:
    output:
        PUBLISHED_VOCABULARY,
    log:
        "logs/published_vocabulary/{name}.log",
    conda:
        "../envs/vprflow.yaml"
    params:
        url=lambda wildcards: vocabulary_url(wildcards.name),
        sha256=lambda wildcards: PUBLISHED_VOCABULARIES[wildcards.name].sha256,
    script:
        "../scripts/published_vocabulary.py"


# Every trained model's checkpoint the plan reads that can be downloaded
# (vprflow.planning.checkpoints): `snakemake trained_checkpoints` fetches the missing ones.
# Those to fetch by hand are named once the command is known (Invocation.begin).
rule trained_checkpoints:
    input:
        lambda wildcards: fetchable_paths(started().plan.checkpoints),


# One published checkpoint, at the path its backbone entry names; kept only when its SHA-256
# is the published one (where there is one), so an interrupted or wrong download leaves none.
rule trained_checkpoint:
    output:
        "{checkpoint}",
    log:
        "logs/trained_checkpoint/{checkpoint}.log",
    wildcard_constraints:
        checkpoint=output_pattern(fetchable_paths(CHECKPOINTS, absolute=False)),
    conda:
        "../envs/vprflow.yaml"
    params:
        # They take `output`, so no rerun trigger: the plan hashes the file itself.
        url=lambda wildcards, output: checkpoint_url(published_checkpoint(output)),
        sha256=lambda wildcards, output: published_checkpoint(output).sha256,
    message:
        "vprflow: fetching {output} from {params.url} (log: {log})"
    script:
        "../scripts/trained_checkpoint.py"


# A checkpoint at an absolute path: its log under logs/trained_checkpoint/absolute/.
use rule trained_checkpoint as trained_checkpoint_absolute with:
    output:
        ABSOLUTE_OUTPUT,
    log:
        "logs/trained_checkpoint/absolute/{checkpoint}.log",
    wildcard_constraints:
        checkpoint=output_pattern(
            [p[1:] for p in fetchable_paths(CHECKPOINTS, absolute=True)]
        ),

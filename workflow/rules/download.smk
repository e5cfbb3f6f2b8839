# Public datasets on demand (README.md, "Getting the data"): `snakemake --cores 1
# results/downloads/<dataset>.json` fetches the dataset's `download` archive, verifies
# it and lays out its folder under data_root when the folder is missing, then writes
# this record. Nothing here lists images, so the target works while the data is absent.
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

# Shipped manifests are named relative to workflow/ (found while this file is parsed).
WORKFLOW_DIR = Path(workflow.current_basedir).parent


# Network access happens where Snakemake runs, not in a cluster job.
localrules:
    download,
    published_vocabulary,


rule download:
    input:
        manifest=lambda wildcards: manifest_inputs(
            CONFIG, wildcards.dataset, WORKFLOW_DIR
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

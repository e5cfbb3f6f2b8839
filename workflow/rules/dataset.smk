from vprflow.core.paths import FINGERPRINTS


# A dataset's two stores: `images` (what the images are: list, order, content, reader)
# and `dataset` (the whole dataset as recall and the figures read it: the images store's
# lists and what is true about them, the ground truth), so a ground-truth change reruns
# no model stage. No file inputs: the keys cover the images' and ground-truth
# files' contents (see vprflow.planning.fingerprints.dataset_contents), and their location must
# not trigger a rerun.
rule images:
    output:
        directory(store_pattern("images")),
    log:
        log_pattern("images"),
    conda:
        "../envs/vprflow.yaml"
    resources:
        mem_mb=lambda wildcards, attempt: 4000 * attempt,
        runtime=lambda wildcards, attempt: 60 * attempt,
    params:
        record=stage_record("images"),
        data_root=data_root_param,
        # The plan's memo of file hashes: names a file that changed after planning.
        fingerprints=PREFIX + FINGERPRINTS,
    script:
        "../scripts/stage.py"


rule dataset:
    input:
        unpack(stage_inputs("dataset")),
    output:
        directory(store_pattern("dataset")),
    log:
        log_pattern("dataset"),
    conda:
        "../envs/vprflow.yaml"
    resources:
        mem_mb=lambda wildcards, attempt: 4000 * attempt,
        runtime=lambda wildcards, attempt: 60 * attempt,
    params:
        record=stage_record("dataset"),
        data_root=data_root_param,
        fingerprints=PREFIX + FINGERPRINTS,
    script:
        "../scripts/stage.py"

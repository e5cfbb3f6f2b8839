# No file inputs: the key covers the images' and ground truth's contents (see
# vprflow.fingerprints.dataset_contents), and their location must not trigger a rerun.
rule dataset:
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
        # The plan's memo of file hashes: names a file that changed after planning.
        fingerprints=PREFIX + FINGERPRINTS,
    script:
        "../scripts/stage.py"

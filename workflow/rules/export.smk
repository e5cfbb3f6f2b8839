# A method's descriptors of a dataset as one .npz file, on request:
#   snakemake --cores 1 results/export/<dataset>/<method>.npz


rule export:
    input:
        unpack(export_stores),
    output:
        EXPORT,
    log:
        "logs/export/{dataset}/{method}.log",
    conda:
        "../envs/vprflow.yaml"
    script:
        "../scripts/export.py"


localrules:
    export,

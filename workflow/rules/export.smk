# A method's descriptors of a dataset as one .npz file, and a method's (or re-ranked
# row's) retrievals as hloc's and kapture's pairs files, `pairs_depth` references a
# query, on request:
#   snakemake --cores 1 results/export/<dataset>/<method>.npz
#   snakemake --cores 1 results/pairs/<dataset>/<method>/pairs.txt
from vprflow.core.paths import EXPORT, KAPTURE_PAIRS, PAIRS


# The export reads no ground truth: a ground-truth change leaves it as it is.
rule export:
    input:
        unpack(method_stores_of("images", "descriptors")),
    output:
        EXPORT,
    log:
        "logs/export/{dataset}/{method}.log",
    conda:
        "../envs/vprflow.yaml"
    script:
        "../scripts/export.py"


# The descriptors (and segment search) rank past the recall's depth.
rule pairs:
    input:
        unpack(method_stores_of("dataset", "recall", "descriptors", "search")),
    output:
        pairs=PAIRS,
        kapture=KAPTURE_PAIRS,
    log:
        "logs/pairs/{dataset}/{method}.log",
    conda:
        "../envs/vprflow.yaml"
    # Not in any store's key: a new depth rewrites these files alone.
    params:
        depth=CONFIG["pairs_depth"],
    script:
        "../scripts/pairs.py"


localrules:
    export,
    pairs,

"""vprflow: training-free visual place recognition experiments as a Snakemake workflow."""

import sys

from vprflow.data.download import download_dataset, write_record
from vprflow.stages.runner import run_stage

sm = snakemake  # noqa: F821 (injected by Snakemake)


def main():
    manifest = sm.input.manifest[0] if sm.input.manifest else None
    record = download_dataset(sm.wildcards.dataset, sm.params.entry, sm.params.folder, manifest)
    if record["downloaded"] and not record["sha256_pinned"]:
        print(
            f"vprflow: warning: {record['url']} has no sha256 in the config; it downloaded "
            f"with sha256 {record['sha256']}: pin it as "
            f"datasets.{record['dataset']}.download.sha256 (log: {sm.log[0]})",
            file=sys.__stderr__,
        )
    write_record(record, sm.output[0])


run_stage(sm.log[0], main, sm.threads)

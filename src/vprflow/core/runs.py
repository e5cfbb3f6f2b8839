"""Runs of the workflow in one working folder at once, told apart by a marker file each.

Snakemake locks a working folder while a run writes to it; ``--nolock`` lifts the lock.
Two runs of one folder then delete each other's stores (Snakemake removes a job's
outputs before running it), and what fails is a job of either run, with Snakemake's
"Missing files after 5 seconds" or a store that "does not exist". Each run that runs
jobs leaves a marker under ``.snakemake/vprflow-runs/`` (its host, process and targets)
while it lasts, so a run that finds another's can say so, at its start and when it fails.
"""

from __future__ import annotations

import json
import os
import re
import time
from pathlib import Path

from vprflow.core.files import TAG, is_abandoned, write_text_atomic, writer_tag

RUNS = ".snakemake/vprflow-runs"


def start_run(root: str | Path = "", targets=()) -> Path:
    """Leave this process's marker in the folder ``root`` (a host workflow's prefix, or
    the working folder); markers of runs that ended without removing theirs are removed."""
    folder = Path(root) / RUNS
    folder.mkdir(parents=True, exist_ok=True)
    other_runs(folder)  # removes the abandoned
    marker = folder / f"{writer_tag()}.json"
    record = {"pid": os.getpid(), "started": time.strftime("%Y-%m-%d %H:%M:%S")}
    write_text_atomic(marker, json.dumps({**record, "targets": list(targets)}))
    return marker


def end_run(marker: Path) -> None:
    Path(marker).unlink(missing_ok=True)


def other_runs(folder: str | Path, own: Path | None = None) -> list[dict]:
    """The live runs whose markers are in ``folder`` (not ``own``), each as its marker's
    record with its ``host``; a marker whose process is gone is removed."""
    folder, found = Path(folder), []
    if not folder.is_dir():
        return found
    for marker in sorted(folder.glob("*.json")):
        match = re.fullmatch(TAG + r"\.json", marker.name)
        if match is None or (own is not None and marker.name == Path(own).name):
            continue
        if is_abandoned(marker, match["host"], int(match["pid"])):
            marker.unlink(missing_ok=True)
            continue
        try:
            record = json.loads(marker.read_text())
        except (OSError, ValueError):
            record = {}
        found.append({"targets": [], **record, "pid": int(match["pid"]), "host": match["host"]})
    return found


def runs_here() -> list[dict]:
    """The live runs of the working folder (:func:`other_runs` of its markers), the run of
    the calling job included."""
    return other_runs(RUNS)


def collision_message(runs: list[dict]) -> str:
    """What to tell a user whose run shares its folder with ``runs`` (:func:`other_runs`)."""
    each = "; ".join(
        f"pid {r['pid']} on {r['host']}"
        + (f", since {r['started']}" if r.get("started") else "")
        + (f", targets {' '.join(r['targets'])}" if r["targets"] else "")
        for r in runs
    )
    return (
        f"another run is writing this folder's results ({each}): two runs of one folder "
        "delete each other's stores (Snakemake removes a job's outputs before it runs), "
        "and a job of either fails with 'Missing files after ... seconds' or 'store ... "
        "does not exist'. Snakemake's lock prevents this; --nolock bypasses it: let one "
        "run finish, or give each its own folder (--directory)"
    )

"""Two runs of one working folder at once (--nolock): each names the other."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from synthetic import make_dataset
from workflow_helpers import snakemake, toy_config, write_config

from vprflow.core.files import host_name
from vprflow.core.runs import RUNS, collision_message, end_run, other_runs, start_run


def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def _marker(folder, pid: int, targets=("results/recall_toy.csv",)):
    folder.mkdir(parents=True, exist_ok=True)
    marker = folder / f"{host_name()}-{pid}-0123abcd.json"
    marker.write_text(json.dumps({"pid": pid, "started": "06:00", "targets": list(targets)}))
    return marker


def test_a_run_finds_the_live_runs_of_its_folder_and_drops_the_markers_of_ended_ones(tmp_path):
    folder = tmp_path / RUNS
    live = _marker(folder, os.getppid())
    dead = _marker(folder, _dead_pid())
    own = start_run(tmp_path, ["results/recall_corridor.csv"])
    assert own.parent == folder and not dead.exists()
    (other,) = other_runs(folder, own)
    assert other == {
        "pid": os.getppid(),
        "host": host_name(),
        "started": "06:00",
        "targets": ["results/recall_toy.csv"],
    }
    assert json.loads(own.read_text())["pid"] == os.getpid()
    end_run(own)
    assert not own.exists() and live.exists()


def test_the_collision_message_names_the_other_run_snakemakes_lock_and_nolock():
    message = collision_message([{"pid": 42, "host": "node1", "started": "06:00", "targets": []}])
    assert message.startswith("another run is writing this folder's results (pid 42 on node1")
    assert "Snakemake's lock prevents this; --nolock bypasses it" in message
    assert "Missing files after" in message and "does not exist" in message


@pytest.mark.workflow
def test_a_run_beside_another_live_run_of_its_folder_says_so_and_removes_its_marker(tmp_path):
    make_dataset(tmp_path / "data" / "toy", n_places=4)
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        _marker(tmp_path / RUNS, other.pid)
        config_path = write_config(tmp_path, toy_config(tmp_path / "data"))
        # A target that fails while planning: the run needs no job to say it.
        result = snakemake(
            tmp_path, config_path, "--nolock", "results/recall_toyy.csv", check=False
        )
    finally:
        other.kill()
        other.wait()
    text = result.stdout + result.stderr
    assert f"vprflow: another run is writing this folder's results (pid {other.pid} on" in text
    assert [m.name for m in (tmp_path / RUNS).iterdir()] == [
        f"{host_name()}-{other.pid}-0123abcd.json"
    ]

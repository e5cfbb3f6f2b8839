"""What a workflow script runs a stage in: its log and its thread budget."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

PROGRAM = """
import sys
from vprflow.stages.runner import run_stage

def stage():
    import faiss
    import torch
    print("threads", torch.get_num_threads(), faiss.omp_get_max_threads(), file=sys.__stdout__)
    if {fail}:
        raise ValueError("bad input x.png")
    import time
    print("cpu", time.process_time(), file=sys.__stdout__)

run_stage({log!r}, stage, 1)
"""


@pytest.mark.parametrize("fail", [False, True])
def test_stage_libraries_imported_inside_keep_the_thread_budget(tmp_path, fail):
    """torch and faiss imported by the stage itself (not by the runner) use one thread;
    a failure goes to the log and to stderr, naming the problem."""
    log = tmp_path / "stage.log"
    result = subprocess.run(
        [sys.executable, "-c", PROGRAM.format(fail=fail, log=str(log))],
        capture_output=True,
        text=True,
    )
    assert "threads 1 1" in result.stdout, result.stdout + result.stderr
    if fail:
        assert result.returncode != 0
        assert "ValueError: bad input x.png" in result.stderr
        assert "Traceback" in log.read_text() and "bad input x.png" in log.read_text()
    else:
        assert result.returncode == 0, result.stderr
        # The last log line: the process's CPU so far, at least what the stage had used.
        line = log.read_text().splitlines()[-1]
        found = re.search(
            r"resources: stage ([\d.]+) s wall; process ([\d.]+) s CPU, peak RSS (\d+) MiB", line
        )
        assert found, line
        spent = float(result.stdout.split("cpu ")[1].split()[0])
        assert float(found[2]) >= spent - 0.01 > 0
        assert int(found[3]) > 50  # torch alone is more
        assert "CUDA" not in line  # the stage ran on the CPU


AT_EXIT = """
import atexit, gc, sys
from vprflow.stages.runner import run_stage

# Registered first, so it runs after anything run_stage registers.
atexit.register(lambda: print("frozen", gc.get_freeze_count() > 0, file=sys.__stdout__))

def stage():
    if {fail}:
        raise ValueError("bad input x.png")

run_stage({log!r}, stage, 1)
"""


@pytest.mark.parametrize("fail", [False, True])
def test_a_finished_stage_leaves_its_objects_to_the_os_at_exit(tmp_path, fail):
    """No last garbage collection once the job's output is whole (a process that imported
    torch spent ~0.35 s in it); a failed job's process ends as Python ends it."""
    log = tmp_path / "stage.log"
    result = subprocess.run(
        [sys.executable, "-c", AT_EXIT.format(fail=fail, log=str(log))],
        capture_output=True,
        text=True,
    )
    assert result.returncode == (1 if fail else 0), result.stderr
    assert f"frozen {not fail}" in result.stdout, result.stdout + result.stderr


FAILING = """
import sys
from vprflow.core.errors import DatasetError
from vprflow.stages.runner import run_stage

def stage():
    raise {error}("folder data/x does not exist")

run_stage({log!r}, stage, 1)
"""


@pytest.mark.parametrize("error", ["DatasetError", "KeyError"])
def test_an_error_raised_on_purpose_shows_its_message_and_log_without_a_traceback(tmp_path, error):
    """The console shows a deliberate error's message and the log's path, and nothing
    under it; a bug (a built-in exception) keeps its traceback there. The log holds the
    traceback either way."""
    log = tmp_path / "stage.log"
    result = subprocess.run(
        [sys.executable, "-c", FAILING.format(error=error, log=str(log))],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 1
    message = "folder data/x does not exist"
    shown = repr(message) if error == "KeyError" else message  # str(KeyError) quotes
    assert f"vprflow: {error}: {shown} (log: {log})" in result.stderr
    assert ("Traceback" in result.stderr) == (error == "KeyError"), result.stderr
    if error == "DatasetError":
        assert result.stderr.strip().splitlines()[-1].endswith(f"(log: {log})")
    assert "Traceback" in log.read_text()
    assert "folder data/x does not exist" in log.read_text()


class _FakeCuda:
    """torch.cuda as the runner sees it after a stage used two devices."""

    def __init__(self, initialised: bool):
        self.initialised = initialised

    def is_initialized(self):
        return self.initialised

    def device_count(self):
        return 2

    def max_memory_allocated(self, device):
        return [3 << 20, 5 << 20][device]


@pytest.mark.parametrize("initialised", [False, True])
def test_the_resources_line_states_peak_cuda_memory_only_where_the_stage_used_cuda(
    tmp_path, monkeypatch, initialised
):
    from types import SimpleNamespace

    from vprflow.stages.runner import run_stage

    monkeypatch.setitem(
        sys.modules,
        "torch",
        SimpleNamespace(cuda=_FakeCuda(initialised), set_num_threads=lambda n: None),
    )
    log = tmp_path / "stage.log"
    run_stage(str(log), lambda: None)
    line = log.read_text().splitlines()[-1]
    assert re.search(r"peak RSS \d+ MiB", line), line
    assert ("; peak CUDA 5 MiB allocated" in line) == initialised, line


def test_a_jobs_threads_sleep_when_idle_set_before_its_libraries_load():
    """A stage script's imports (workflow/scripts/stage.py) set OpenMP's and OpenBLAS's
    idle threads to sleep before numpy, torch or faiss load, which read them once; a
    user's own value wins."""
    program = (
        "import os, sys\n"
        "from vprflow.stages.jobs import Job, run_job\n"
        "from vprflow.stages.runner import run_stage\n"
        "loaded = sorted({'numpy', 'torch', 'faiss'} & set(sys.modules))\n"
        "print(loaded, os.environ['OMP_WAIT_POLICY'], os.environ['OPENBLAS_THREAD_TIMEOUT'])\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY",)}
    env["OPENBLAS_THREAD_TIMEOUT"] = "6"
    result = subprocess.run(
        [sys.executable, "-c", program], capture_output=True, text=True, env=env, check=True
    )
    assert result.stdout.split() == ["[]", "PASSIVE", "6"]
    env.pop("OPENBLAS_THREAD_TIMEOUT")
    result = subprocess.run(
        [sys.executable, "-c", program], capture_output=True, text=True, env=env, check=True
    )
    assert result.stdout.split() == ["[]", "PASSIVE", "4"]

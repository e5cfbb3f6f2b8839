"""How a workflow script runs a stage: logging to its log file, and a thread budget.

Progress bars, log messages and any traceback go to the rule's log file. Numeric
libraries (BLAS via numpy, torch, faiss) are held to the rule's ``threads``: two
jobs on two cores that each start a full BLAS thread pool oversubscribe the CPU,
which slows small matrix products by an order of magnitude.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import logging
import os
import resource
import sys
import time
import traceback
from collections.abc import Callable

from threadpoolctl import threadpool_limits

# Idle OpenMP threads (torch, faiss) sleep instead of spinning: between the many small
# per-image operations of a stage, spinning threads took the cores that zarr's codec
# threads and BLAS needed (a per-image stage ran at 1/5 of its arithmetic speed).
# Set before torch or faiss start their OpenMP runtime; a user's own value wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# numpy's OpenBLAS runs its own threads, not OpenMP's: after each call they spin for
# 2^28 cycles (~0.1 s) unless told otherwise. 2^4 cycles lets them sleep at once: the
# roadscene table in one process took 30.8 instead of 38.5 CPU s on two threads, and
# 28.9 instead of 30.1 s of wall. The kernels and their partition of the work are the
# same, so the results are too. Set before numpy loads OpenBLAS (a job imports numpy
# after this module).
os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "4")


def run_stage(log_path: str, function: Callable[[], None], threads: int = 1) -> None:
    """Run ``function`` with stderr and the ``vprflow`` logger writing to ``log_path``
    and at most ``threads`` threads in BLAS, torch and faiss.

    A failure is written to the log (with traceback) and named on stderr in one line
    with the log's path. An error vprflow raises on purpose (:func:`deliberate`) then
    ends the process with exit status 1: its message says what is wrong and what to do,
    and a traceback under it on the console would bury it. Any other exception (a bug)
    is re-raised, traceback and all. Call it as a workflow script's whole work: a
    deliberate error leaves by ``SystemExit``.
    """
    # torch and faiss are imported only by the stages that use them (importing both
    # costs ~2 s a job): one imported later reads these variables when it starts.
    for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[variable] = str(threads)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(threads)
    if "faiss" in sys.modules:
        sys.modules["faiss"].omp_set_num_threads(threads)
    with (
        open(log_path, "w") as log_file,
        contextlib.redirect_stderr(log_file),
        threadpool_limits(limits=threads),
    ):
        handler = logging.StreamHandler(log_file)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
        logger = logging.getLogger("vprflow")
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)
        started = time.perf_counter()
        try:
            function()
            cuda = _peak_cuda_mib()
            if cuda is None:
                logger.info(RESOURCES, *_resources(started))
            else:
                logger.info(RESOURCES + CUDA_PEAK, *_resources(started), cuda)
            # The job is done and its output whole: at the process's exit, no last
            # collection over every object alive (~0.35 s after torch's import; the memory
            # goes back to the OS all the same). Registered last, it runs first at exit.
            atexit.register(gc.freeze)
        except BaseException as error:
            traceback.print_exc(file=log_file)
            log_file.flush()
            # Also on the real stderr: the one line a user sees first names the problem.
            print(
                f"vprflow: {type(error).__name__}: {error} (log: {log_path})", file=sys.__stderr__
            )
            if deliberate(error):
                raise SystemExit(1) from None
            raise
        finally:
            logger.removeHandler(handler)


def deliberate(error: BaseException) -> bool:
    """Whether vprflow raised ``error`` on purpose: its class is one of vprflow's own
    (``DatasetError``, ``DownloadError``, ``CheckpointError``, ...), each raised where a
    message names the fault. A built-in exception is a bug or a fault no check foresaw,
    and its traceback is what tells where."""
    return type(error).__module__.split(".")[0] == "vprflow"


# The job's last log line: exact CPU and peak memory of its process (all its threads, and
# any child it waited for). Snakemake's ``benchmark:`` files sample CPU every 30 s and so
# miss up to the last 30 s of a job's threads (a 38 s `matches` job on 2 threads: 20.9
# CPU s there, 60.5 by getrusage); benchmarks/bench_workflow.py reads this line instead.
RESOURCES = "resources: stage %.2f s wall; process %.2f s CPU, peak RSS %.0f MiB"
# Appended where the stage used CUDA: the most its tensors held at once on any device
# (torch's allocator; the process's own memory, not the cache it reserved).
CUDA_PEAK = "; peak CUDA %.0f MiB allocated"


def _resources(started: float) -> tuple[float, float, float]:
    """(wall seconds since ``started``; CPU seconds and peak RSS in MiB of this process
    from its start)."""
    own, children = (
        resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
    )
    cpu = own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime
    # ru_maxrss is KiB on Linux, bytes on macOS.
    peak = max(own.ru_maxrss, children.ru_maxrss) / (
        1 << 20 if sys.platform == "darwin" else 1 << 10
    )
    return time.perf_counter() - started, cpu, peak


def _peak_cuda_mib() -> float | None:
    """The largest ``torch.cuda.max_memory_allocated`` over the devices, in MiB, where
    this process used CUDA; None where it did not (torch not imported, or CUDA never
    initialised: every CPU run)."""
    torch = sys.modules.get("torch")
    if torch is None or not torch.cuda.is_initialized():
        return None
    peaks = [torch.cuda.max_memory_allocated(i) for i in range(torch.cuda.device_count())]
    return max(peaks, default=0) / (1 << 20)

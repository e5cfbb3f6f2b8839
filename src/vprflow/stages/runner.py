"""How a workflow script runs a stage: logging to its log file, and a thread budget.

Progress bars, log messages and any traceback go to the rule's log file. Numeric
libraries (BLAS via numpy, torch, faiss) are held to the rule's ``threads``: two
jobs on two cores that each start a full BLAS thread pool oversubscribe the CPU,
which slows small matrix products by an order of magnitude.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import traceback
from collections.abc import Callable

# Idle OpenMP threads (torch, faiss) sleep instead of spinning: between the many small
# per-image operations of a stage, spinning threads took the cores that zarr's codec
# threads and BLAS needed (a per-image stage ran at 1/5 of its arithmetic speed).
# Set before torch or faiss start their OpenMP runtime; a user's own value wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def run_stage(log_path: str, function: Callable[[], None], threads: int = 1) -> None:
    """Run ``function`` with stderr and the ``vprflow`` logger writing to ``log_path``
    and at most ``threads`` threads in BLAS, torch and faiss.

    A failure is written to the log (with traceback) and re-raised, so Snakemake
    reports it and the log says why.
    """
    from threadpoolctl import threadpool_limits

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
        try:
            function()
        except BaseException as error:
            traceback.print_exc(file=log_file)
            log_file.flush()
            # Also on the real stderr: the one line a user sees first names the problem.
            print(
                f"vprflow: {type(error).__name__}: {error} (log: {log_path})", file=sys.__stderr__
            )
            raise
        finally:
            logger.removeHandler(handler)

"""Send a stage's progress bars, log messages and traceback to its Snakemake log file."""

from __future__ import annotations

import contextlib
import logging
import sys
import traceback
from collections.abc import Callable


def run_logged(log_path: str, function: Callable[[], None]) -> None:
    """Run ``function`` with stderr and the ``vprflow`` logger writing to ``log_path``.

    A failure is written to the log (with traceback) and re-raised, so Snakemake
    reports it and the log says why.
    """
    with open(log_path, "w") as log_file, contextlib.redirect_stderr(log_file):
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

"""What a ``snakemake`` command asks for, read while Snakemake reads the workflow.

Snakemake includes the Snakefile before it decides what to do with it: while the plan
is built it knows whether the run is a dry run (``workflow.output_settings.dryrun``) and
whether this process is the main one, but not the targets nor whether the command runs
the workflow at all (``--lint``, ``--summary``, ``--report``, ``--dag``, ...). Those are
read from the command line with Snakemake's own argument parser, so its spellings,
aliases, grouped short flags and ``--`` are its own. Once jobs are scheduled the rules
ask Snakemake instead (``workflow.dag_settings.targets``, ``workflow.dryrun``).
"""

from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass

# Snakemake's parsed options (their ``dest``) that make a command do something else
# than run the workflow (snakemake.cli.args_to_api): it reads, lists, draws, lints,
# unlocks or cleans, and runs no job.
NOT_RUNNING = (
    "lint",
    "list_rules",
    "list_target_rules",
    "print_compilation",
    "containerize",
    "generate_unit_tests",
    "export_cwl",
    "dag",
    "rulegraph",
    "filegraph",
    "d3dag",
    "summary",
    "detailed_summary",
    "list_changes",
    "list_input_changes",
    "list_params_changes",
    "list_untracked",
    "unlock",
    "cleanup_metadata",
    "cleanup_shadow",
    "conda_cleanup_envs",
    "conda_create_envs_only",
    "list_conda_envs",
    "container_cleanup_images",
    "archive",
    "delete_all_output",
    "delete_temp_output",
)


@dataclass(frozen=True)
class Command:
    """A ``snakemake`` command as Snakemake parses it."""

    targets: tuple[str, ...] = ()
    # Whether it runs the workflow (a dry run counts): not a utility (NOT_RUNNING) nor
    # a report made from the results on disk.
    runs_workflow: bool = True
    # ``--report`` without ``--report-after-run``: a report from the results on disk.
    makes_report: bool = False


def read_command(argv: list[str]) -> Command:
    """``sys.argv`` of a ``snakemake`` process, parsed by Snakemake's own parser. A
    process that is no ``snakemake`` command line (Snakemake driven through its Python
    API) reads as a run without targets."""
    from snakemake.cli import get_argument_parser

    try:
        with contextlib.redirect_stderr(io.StringIO()):
            args = get_argument_parser().parse_args(argv[1:])
    except SystemExit:
        return Command()
    makes_report = bool(args.report) and not args.report_after_run
    utility = any(getattr(args, name, None) for name in NOT_RUNNING)
    return Command(tuple(args.targets), not (utility or makes_report), makes_report)

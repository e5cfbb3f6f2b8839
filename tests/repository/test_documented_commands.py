"""Every `snakemake` command that README.md, docs/ and the comments of the config and
profile files give runs as written.

The commands are collected from the files themselves (code blocks, inline `...` spans,
indented command lines in YAML comments), so a command added to a document is tested
without touching this file. Each one is

* parsed with Snakemake's own argument parser, and checked for what that parser accepts
  but Snakemake then trips over: a target after `--configfile` (or `--config`,
  `--set-resources`, ...) is read as one more value of that option; every config file
  must exist, every target must be a results path or a rule name;
* dry-run (`-n` in front) against the shipped data (corridor, roadscene from
  $VPRFLOW_DATA) and a miniature of each preset a command names, in a scratch copy of
  the repository laid out as the documents assume (`data/`, `../shared/data`, a stand-in
  for each checkpoint under `models/`), unless PARSE_ONLY says why not.

Placeholders (`<preset>`) take the values in PLACEHOLDERS; an optional `[...]` part of a
synopsis is left out, and so are `NAME=value` settings before the command. The dry runs
share one Python process: a fresh Snakemake that imports the package for each would take
several times as long.
"""

from __future__ import annotations

import contextlib
import functools
import glob
import importlib.util
import io
import os
import re
import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml
from workflow_helpers import dry_run

REPO = Path(__file__).resolve().parents[2]
# Where documented commands live. benchmarks/README.md is left out: it records the
# commands measurements were taken with (other checkouts, `<worktree>` paths), not
# commands to type.
SOURCES = (
    "README.md",
    "docs/*.md",
    "config/*.md",
    "config/*.yaml",
    ".test/config/*.yaml",
    "workflow/profiles/README.md",
    "workflow/profiles/*/config.yaml",
    ".snakemake-workflow-catalog.yml",
)
# Values for the documents' placeholders: a preset, a sample set, a dataset and one of
# its methods, a rule.
PLACEHOLDERS = {
    "preset": "17places",
    "name": "roadscene",
    "dataset": "corridor",
    "method": "segvlad",
    "rule": "recall",
}
# Config files the reader writes, from the document that names them: they must be the
# ones the documents describe, and the commands that read them are parse-only (they
# describe the reader's own images and model folders).
READERS_FILES = {
    "config/mine.yaml": "README.md, Your own images",
    "config/cluster.yaml": "docs/cluster.md, Before the first GPU run",
    "config/smoke.yaml": "docs/cluster.md, Before the first GPU run",
}
# Files a config names that are not shipped and that planning only hashes: the trained
# models' checkpoints. The scratch copy holds a stand-in for each.
STAND_IN_KEYS = ("checkpoint",)
TARGET = re.compile(r"results/\S+|[A-Za-z_]\w*")
# Options whose every value has a shape; a value without it is a word that was meant
# for something else (a target, most often).
VALUE_SHAPES = {
    "config": re.compile(r"[A-Za-z_][\w.]*=.*"),
    "resources": re.compile(r"\w+=.+"),
    "default_resources": re.compile(r"\w+=.+"),
    "set_resources": re.compile(r"\w+:\w+=.+"),
    "set_threads": re.compile(r"\w+=\d+"),
    "cache": re.compile(r"\w+"),
}


@dataclass(frozen=True)
class Command:
    source: str  # file:line where the command starts
    text: str  # the command as written (continuation lines joined)
    argv: tuple[str, ...]  # its arguments after `snakemake`, placeholders filled in

    def args(self, pwd: Path) -> list[str]:
        return [a.replace("$PWD", str(pwd)) for a in self.argv]


def _fill_placeholders(text: str, where: str) -> str:
    def value(match: re.Match) -> str:
        name = match.group(1)
        assert name in PLACEHOLDERS, f"{where}: add a value for <{name}> to PLACEHOLDERS"
        return PLACEHOLDERS[name]

    return re.sub(r"<(\w+)>", value, text)


def _without_optional_parts(tokens: list[str]) -> list[str]:
    """A synopsis's `[--config ...]` / `[targets]` left out (quoted brackets stay)."""
    kept, depth = [], 0
    for token in tokens:
        if depth == 0 and not token.startswith("["):
            kept.append(token)
            continue
        depth += token.count("[") - token.count("]")
    return kept


# `snakemake` where a shell line starts a command: at its start or after `&&`, `;`, `|`,
# past a `$ ` prompt and `NAME=value` environment settings.
COMMAND_WORD = re.compile(
    r"(?:^|[;&|])\s*(?:\$\s+)?(?:[A-Za-z_]\w*=\S*\s+)*(?:python -m )?snakemake(?:\s|$)"
)
ENVIRONMENT = re.compile(r"[A-Za-z_]\w*=.*")


def commands_in(text: str, where: str) -> list[tuple[str, list[str]]]:
    """The `snakemake` commands of one shell line: ``(as written, arguments)`` each, with
    `&&` / `;` / `|` chains split and `# comments` dropped."""
    if not COMMAND_WORD.search(text):  # not a shell line, or no snakemake command in it
        return []
    lexer = shlex.shlex(_fill_placeholders(text, where), posix=True, punctuation_chars=";&|")
    lexer.whitespace_split = True
    try:
        tokens, segment = list(lexer), []
    except ValueError as error:  # an unbalanced quote
        raise AssertionError(f"{where}: {text!r} is not a shell command line") from error
    found = []
    for token in [*tokens, ";"]:
        if token and set(token) <= set(";&|"):
            if segment[:1] == ["snakemake"] or segment[:3] == ["python", "-m", "snakemake"]:
                start = 1 if segment[0] == "snakemake" else 3
                argv = _without_optional_parts(segment[start:])
                found.append((" ".join(segment), argv))
            segment = []
        elif segment or not (token == "$" or ENVIRONMENT.fullmatch(token)):
            segment.append(token)
    return found


def _line_of(text: str, offset: int) -> int:
    return text.count("\n", 0, offset) + 1


def _code_lines(lines: list[tuple[int, str]]) -> list[tuple[int, str]]:
    """Shell lines with their `\\` continuations joined, each at its first line."""
    joined, start, parts = [], None, []
    for number, line in lines:
        if start is None:
            start = number
        if line.rstrip().endswith("\\"):
            parts.append(line.rstrip()[:-1])
            continue
        joined.append((start, " ".join([*parts, line])))
        start, parts = None, []
    if parts:
        joined.append((start, " ".join(parts)))
    return joined


FENCE = re.compile(r"^[ \t]*```[^\n]*\n(.*?)^[ \t]*```", re.M | re.S)
SPAN = re.compile(r"`([^`]+)`")


def _markdown(text: str) -> tuple[list[tuple[int, str]], list[tuple[int, str]]]:
    """(code lines, inline spans) of a Markdown file, each with its line number."""
    code = []
    for block in FENCE.finditer(text):
        first = _line_of(text, block.start(1))
        code += _code_lines(list(enumerate(block.group(1).splitlines(), first)))
    # Blank out the blocks, keeping the line count, so spans are prose only.
    prose = FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)
    spans = [(_line_of(prose, m.start()), m.group(1)) for m in SPAN.finditer(prose)]
    return code, spans


def _yaml(text: str) -> tuple[list[tuple[int, str]], list[tuple[int, str]]]:
    """(code lines, inline spans) of a YAML file: command lines are the comment lines
    indented past `#` (``#   snakemake ...``); spans come from comments and values."""
    bodies, code = [], []
    for number, line in enumerate(text.splitlines(), 1):
        comment = re.match(r"^\s*# ?(.*)$", line)
        bodies.append(comment.group(1) if comment else line)
        if comment and re.match(r"\s{2,}\S", comment.group(1)):
            code.append((number, comment.group(1)))
    prose = "\n".join(bodies)
    spans = [(_line_of(prose, m.start()), m.group(1)) for m in SPAN.finditer(prose)]
    return _code_lines(code), spans


def documented_commands() -> list[Command]:
    commands = []
    for pattern in SOURCES:
        for path in sorted(glob.glob(str(REPO / pattern), include_hidden=True)):
            relative = Path(path).relative_to(REPO).as_posix()
            text = Path(path).read_text()
            code, spans = (_markdown if path.endswith(".md") else _yaml)(text)
            for number, line in code + [(n, " ".join(s.split())) for n, s in spans]:
                where = f"{relative}:{number}"
                for written, argv in commands_in(line, where):
                    # A bare `snakemake` in prose names the program.
                    if argv:
                        commands.append(Command(where, written, tuple(argv)))
    return commands


COMMANDS = documented_commands()


def test_the_commands_are_found_in_every_kind_of_place():
    """The collector reads code blocks, `&&` chains, continuation lines, inline spans
    over two lines and YAML comments: a change in how it reads the files cannot make
    commands vanish unseen."""
    found = {(c.source.split(":")[0], " ".join(c.argv)) for c in COMMANDS}
    trained = "results/recall_pitts30k.csv --configfile config/config.yaml config/trained.yaml"
    assert {
        ("README.md", "--cores 2 --config data_root=../shared/data"),  # after two `&&`
        ("docs/methods.md", f"--cores 2 {trained}"),  # a continuation line
        ("docs/datasets.md", f"--cores 2 {trained}"),  # a span over two lines
        ("config/trained.yaml", f"--cores 2 {trained}"),  # a YAML comment
        ("config/config.yaml", "--cores 2 results/recall_roadscene.csv"),  # a span in one
    } <= found
    assert len(COMMANDS) > 20


def test_a_command_line_is_split_at_chains_comments_and_optional_parts():
    line = 'pip install -e ".[dev]" && snakemake --cores 2 [--config data_root=...] [targets]  # x'
    assert [argv for _, argv in commands_in(line, "here")] == [["--cores", "2"]]
    line = "snakemake --config 'targets=[roadscene]' results/recall_<name>.csv; X=1 snakemake -n"
    assert [argv for _, argv in commands_in(line, "here")] == [
        ["--config", "targets=[roadscene]", "results/recall_roadscene.csv"],
        ["-n"],
    ]
    assert [argv for _, argv in commands_in("$ snakemake --unlock", "here")] == [["--unlock"]]
    assert commands_in("workflow/scripts/*.py  read snakemake.input, call it's", "here") == []


# ---------------------------------------------------------------------------- parsing


@functools.cache
def _parser():
    from snakemake.cli import get_argument_parser

    return get_argument_parser()


def _parse(argv: list[str]):
    """Snakemake's own parse of ``argv``: (namespace, None) or (None, its error)."""
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr):
        try:
            return _parser().parse_args(argv), None
        except SystemExit:
            return None, stderr.getvalue().strip().splitlines()[-1]
        except ValueError as error:  # an option's own type, e.g. --default-resources
            return None, f"{type(error).__name__}: {error}"


def parse_problems(argv: list[str]) -> list[str]:
    """What Snakemake's parser accepts in ``argv`` but Snakemake then trips over."""
    args, error = _parse(argv)
    if error:
        return [error]
    problems = []
    for value in map(str, args.configfile or []):
        if Path(value).suffix not in {".yaml", ".yml", ".json"}:
            problems.append(
                f"--configfile takes {value!r} as a config file: put targets before "
                "--configfile, which reads every word after it as one"
            )
        elif not (REPO / value).is_file() and value not in READERS_FILES:
            problems.append(f"--configfile {value}: no such file in the repository")
    for dest, shape in VALUE_SHAPES.items():
        values = getattr(args, dest, None)
        for value in values if isinstance(values, list) else []:
            if not shape.fullmatch(value):
                option = "--" + dest.replace("_", "-")
                problems.append(f"{option} takes {value!r} as one of its values")
    for target in args.targets:
        if not TARGET.fullmatch(target):
            problems.append(f"target {target!r} is neither a results/ path nor a rule")
    for dest in ("profile", "workflow_profile"):
        value = getattr(args, dest, None)
        for profile in map(str, value if isinstance(value, list) else [value] if value else []):
            if profile != "none" and not (REPO / profile).is_dir():
                problems.append(f"--{dest.replace('_', '-')} {profile}: no such profile folder")
    return problems


@pytest.mark.parametrize("command", COMMANDS, ids=lambda c: f"{c.source} {c.text}")
def test_documented_command_parses_as_meant(command):
    problems = parse_problems(command.args(REPO))
    assert not problems, f"{command.source}: {command.text}: {problems}"


def _shipped(paths: list[str], repo: Path = REPO) -> set[str] | None:
    """Which of ``paths`` git tracks in ``repo`` (None outside a git checkout). Shipped
    means tracked: a reader who follows the documents writes these files into this very
    checkout (config/mine.yaml is git-ignored for them), so being there says nothing."""
    listed = subprocess.run(
        ["git", "-C", str(repo), "ls-files", "-z", "--", *paths],
        capture_output=True,
        text=True,
    )
    return set(listed.stdout.split("\0")) - {""} if listed.returncode == 0 else None


def test_the_readers_own_config_files_are_the_ones_their_documents_describe():
    shipped = _shipped(list(READERS_FILES))
    for path, where in READERS_FILES.items():
        document = REPO / where.split(",")[0]
        if shipped is not None:  # outside git nothing tells the reader's file from ours
            assert path not in shipped, f"{path} is shipped: take it out of READERS_FILES"
        assert path in document.read_text(), f"{document.name} no longer describes {path}"


def test_a_readers_file_written_into_the_checkout_is_not_shipped_until_git_tracks_it(tmp_path):
    repo, plain = tmp_path / "repo", tmp_path / "plain"
    for folder in (repo / "config", plain):
        folder.mkdir(parents=True)
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    (repo / "config" / "mine.yaml").write_text("targets: [mine]\n")
    (repo / "config" / "config.yaml").write_text("targets: []\n")
    subprocess.run(["git", "-C", str(repo), "add", "config/config.yaml"], check=True)
    both = ["config/mine.yaml", "config/config.yaml"]
    assert _shipped(both, repo) == {"config/config.yaml"}
    subprocess.run(["git", "-C", str(repo), "add", "config/mine.yaml"], check=True)
    assert _shipped(both, repo) == set(both)
    assert _shipped(both, plain) is None


# The form the documents used to give: Snakemake read the target as a second config file.
TARGET_AFTER_CONFIGFILE = (
    "--cores",
    "2",
    "--configfile",
    "config/config.yaml",
    "config/trained.yaml",
    "results/recall_corridor.csv",
)


def test_a_target_after_configfile_is_a_problem_named_as_such():
    problems = parse_problems(list(TARGET_AFTER_CONFIGFILE))
    assert problems == [
        "--configfile takes 'results/recall_corridor.csv' as a config file: put targets "
        "before --configfile, which reads every word after it as one"
    ]
    assert parse_problems(["--cores", "2", "--default-resources", "results/recall_x.csv"])
    assert parse_problems(["--cores", "2", "--configfile", "config/none.yaml"])
    fixed = ["--cores", "2", "results/recall_corridor.csv", *TARGET_AFTER_CONFIGFILE[2:5]]
    assert not parse_problems(fixed)


# ---------------------------------------------------------------------------- dry runs

# Commands that are parsed and checked but not dry-run, and why: (test on the parsed
# arguments, reason). Every other command is dry-run.
PARSE_ONLY = (
    (
        lambda args: args.report is not None,
        "a report needs a finished run's results (conftest.py's corridor_run makes one)",
    ),
    (
        lambda args: any(str(f) in READERS_FILES for f in args.configfile or []),
        "reads a config file of the reader's own, for their own images",
    ),
)


def _needs(args) -> str | None:
    """Why this machine cannot dry-run a command that is meant to be dry-run."""
    deployment = {getattr(m, "name", str(m)).lower() for m in args.software_deployment_method}
    if "conda" in deployment and shutil.which("conda") is None:
        return "--sdm conda: conda is not installed here"
    if any("slurm" in Path(profile).name for profile in args.profile or []):
        if importlib.util.find_spec("snakemake_executor_plugin_slurm") is None:
            return 'the SLURM executor is an extra: pip install -e ".[slurm]"'
    return None


def _unique(commands: list[Command]) -> dict[tuple[str, ...], list[Command]]:
    found = {}
    for command in commands:
        found.setdefault(command.argv, []).append(command)
    return found


UNIQUE = _unique(COMMANDS)


@functools.cache
def _dry_run_plan() -> dict[tuple[str, ...], str | None]:
    """argv -> None (dry-run) or why it is not."""
    plan = {}
    for argv in UNIQUE:
        args, _ = _parse(list(argv))
        reasons = [] if args is None else [r for test, r in PARSE_ONLY if test(args)]
        plan[argv] = reasons[0] if reasons else None
    return plan


def _stand_in_files(config_files: list[Path]) -> set[str]:
    """The files ``STAND_IN_KEYS`` name in these config files."""

    def walk(node):
        if isinstance(node, dict):
            for key, value in node.items():
                if key in STAND_IN_KEYS and isinstance(value, str):
                    yield value
                else:
                    yield from walk(value)
        elif isinstance(node, list):
            for value in node:
                yield from walk(value)

    return {f for path in config_files for f in walk(yaml.safe_load(path.read_text()))}


def named_presets(commands: list[Command]) -> set[str]:
    """The dataset presets the commands' targets name (`results/recall_<preset>.csv`)."""
    from vprflow.data.presets import presets

    named = set()
    for command in commands:
        args, _ = _parse(list(command.argv))
        for target in args.targets if args else []:
            for name in presets():
                if re.search(rf"(?:^|[/_]){re.escape(name)}(?:[./]|$)", target):
                    named.add(name)
    return named


def scratch_repository(root: Path, data_root: Path, preset_names: set[str]) -> Path:
    """``root/repo``: the workflow (linked), config/ and .test/config/ (copied), data/
    and ../shared/data (one folder: the shipped data's corridor and roadscene, and a
    miniature of each preset named; a preset whose folder is there joins every plan)
    and a stand-in for each checkpoint a config names."""
    from preset_miniatures import MINIATURES

    from vprflow.data.presets import presets

    data = root / "shared" / "data"
    data.mkdir(parents=True)
    for name in ("corridor", "roadscene"):
        (data / name).symlink_to(data_root / name)
    for name in sorted(preset_names):
        MINIATURES[name](data / presets()[name].dataset["path"], np.random.default_rng(0))
    repo = root / "repo"
    repo.mkdir()
    (repo / "workflow").symlink_to(REPO / "workflow")
    (repo / "data").symlink_to(data)
    shutil.copytree(REPO / "config", repo / "config")
    shutil.copytree(REPO / ".test" / "config", repo / ".test" / "config")
    configs = [*(repo / "config").glob("*.yaml"), *(repo / ".test" / "config").glob("*.yaml")]
    for name in _stand_in_files(configs):
        stand_in = repo / name
        stand_in.parent.mkdir(parents=True, exist_ok=True)
        stand_in.write_bytes(b"a stand-in: planning hashes a checkpoint, never loads it")
    return repo


@pytest.fixture(scope="module")
def dry_runs(tmp_path_factory, data_root) -> dict[tuple[str, ...], dict]:
    """argv -> {"code", "output"} of its dry run in the scratch repository, for every
    command meant to be dry-run here, and for TARGET_AFTER_CONFIGFILE."""
    root = tmp_path_factory.mktemp("documented")
    repo = scratch_repository(root, data_root, named_presets(COMMANDS))
    wanted = [TARGET_AFTER_CONFIGFILE]
    for argv, reason in _dry_run_plan().items():
        args, _ = _parse(list(argv))
        if reason is None and args is not None and _needs(args) is None:
            wanted.append(argv)
    environment = {**os.environ, "SLURM_CONF": os.devnull, "PWD": str(repo)}
    results = []
    for argv in wanted:
        command = [sys.executable, "-m", "snakemake", "-n", *Command("", "", argv).args(repo)]
        done = dry_run(command, repo, environment)
        output = done.stdout + done.stderr
        results.append({"code": done.returncode, "output": output})
    return dict(zip(wanted, results, strict=True))


@pytest.mark.workflow
@pytest.mark.data
def test_a_target_after_configfile_fails_the_dry_run_too(dry_runs):
    result = dry_runs[TARGET_AFTER_CONFIGFILE]
    assert result["code"] != 0
    assert "No such file or directory: 'results/recall_corridor.csv'" in result["output"]


@pytest.mark.workflow
@pytest.mark.data
@pytest.mark.parametrize(
    "argv", list(UNIQUE), ids=lambda a: f"{UNIQUE[a][0].source} {UNIQUE[a][0].text}"
)
def test_documented_command_dry_runs(argv, dry_runs):
    where = ", ".join(c.source for c in UNIQUE[argv])
    reason = _dry_run_plan()[argv]
    if reason is not None:
        pytest.skip(f"parse-only: {reason}")
    args, _ = _parse(list(argv))
    assert args is not None, where  # the parse test says why
    missing = _needs(args)
    if missing is not None:
        pytest.skip(missing)
    result = dry_runs[argv]
    assert result["code"] == 0, f"{where}: {UNIQUE[argv][0].text}\n{result['output']}"
    assert re.search(r"This was a dry-run|Nothing to be done|Unlocked", result["output"]), (
        where,
        result["output"],
    )

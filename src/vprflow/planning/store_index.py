"""Which store serves which experiment: ``results/cache/index.tsv`` and the
``logs/by-method/`` links, for people finding their way among content-addressed keys."""

from __future__ import annotations

import os
from pathlib import Path

from vprflow.core.files import write_text_atomic
from vprflow.core.paths import INDEX, log_pattern, store_path
from vprflow.planning.plan import Plan


def stage_users(plan: Plan) -> dict[tuple[str, str], set[tuple[str, str]]]:
    """``(stage, key) -> {(dataset, method)}``: which rows of which tables use a store."""
    users: dict[tuple[str, str], set[tuple[str, str]]] = {}

    def visit(stage: str, key: str, row: tuple[str, str]) -> None:
        users.setdefault((stage, key), set()).add(row)
        for upstream in plan.get(stage, key).inputs.values():
            visit(*upstream, row)

    for dataset, runs in plan.runs.items():
        for run in runs:
            visit("recall", run.recall_key, (dataset, run.method))
    return users


def write_index(plan: Plan, root: str = "") -> Path:
    """``<root>results/cache/index.tsv``: every store of the current config with its
    stage, key, dataset, the methods using it and its log folder; and
    ``<root>logs/by-method/<dataset>/<method>/<stage>`` links to those log folders.
    Written atomically and only when changed; links are replaced, never half made."""
    users = stage_users(plan)
    lines = ["stage\tkey\tdataset\tmethods\tstore\tlogs"]
    for (stage, key), rows in sorted(users.items()):
        datasets = sorted({d for d, _ in rows})
        methods = sorted({m for _, m in rows})
        logs = str(Path(log_pattern(stage).format(key=key)).parent)
        lines.append(
            "\t".join(
                [stage, key, ",".join(datasets), ",".join(methods), store_path(stage, key), logs]
            )
        )
        for dataset, method in rows:
            link = Path(root) / "logs" / "by-method" / dataset / method / stage
            link.parent.mkdir(parents=True, exist_ok=True)
            target = os.path.relpath(Path(root) / logs, link.parent)
            if link.is_symlink() and os.readlink(link) == target:
                continue
            tmp = link.with_name(f".{stage}.{os.getpid()}.tmp")
            tmp.unlink(missing_ok=True)
            tmp.symlink_to(target, target_is_directory=True)
            os.replace(tmp, link)
    index = Path(root) / INDEX
    text = "\n".join(lines) + "\n"
    if not index.exists() or index.read_text() != text:
        write_text_atomic(index, text)
    return index

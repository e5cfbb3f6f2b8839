"""A preset's published recall beside vprflow's: ``results/published_<dataset>.csv``.

One row per published row of the preset (``data/presets.yaml``: the papers' and the
trained models' authors' Recall@1 / @5, in percent), with the vprflow method that
reproduces it (``row``) and that method's Recall@1 / @5 from the dataset's recall
table, also in percent. Empty where the row names no vprflow method, or where the table
has no row of that method (a trained method without ``trained_baselines: true``). A row
this run makes otherwise than the published setting says how in its ``protocol``
(:mod:`vprflow.planning.published` decides).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping, Sequence

from vprflow.core.files import write_text_atomic
from vprflow.data.presets import presets

COLUMNS = (
    "method",
    "paper",
    "published_recall@1",
    "published_recall@5",
    "row",
    "recall@1",
    "recall@5",
    "protocol",
)


def percent(fraction: str) -> str:
    """A recall table's fraction (``0.916000``) as the papers print recall: percent, here
    with two decimals (the table's six keep four significant digits of a percentage)."""
    return f"{100 * float(fraction):.2f}"


def published_rows(
    published: Sequence[dict],
    recall_rows: Sequence[dict[str, str]],
    changes: Mapping[str, str] | None = None,
) -> list[dict[str, str]]:
    """The published rows, in their order, each with vprflow's Recall@1 / @5 (percent)
    of the method its ``row`` names and that row's ``protocol`` (a preset's recall table
    says whether the config changed the preset's protocol), read from ``recall_rows``
    (a ``results/recall_<dataset>.csv`` as ``csv.DictReader`` rows). ``changes``: by
    method, how this run makes the row otherwise than the published setting, appended
    to its protocol."""
    by_method = {row["method"]: row for row in recall_rows}
    changes = changes or {}
    out = []
    for entry in published:
        ours = by_method.get(entry.get("row", ""))
        protocol = (ours or {}).get("protocol", "")
        if ours and changes.get(entry["row"]):
            protocol += f"; not the published setting: {changes[entry['row']]}"
        out.append(
            {
                "method": entry["method"],
                "paper": entry["paper"],
                "published_recall@1": str(entry["recall@1"]),
                "published_recall@5": str(entry["recall@5"]),
                "row": entry.get("row", ""),
                "recall@1": percent(ours["recall@1"]) if ours else "",
                "recall@5": percent(ours["recall@5"]) if ours else "",
                "protocol": protocol,
            }
        )
    return out


def write_published_table(
    dataset: str, recall_csv: str, out: str, changes: Mapping[str, str] | None = None
) -> None:
    """``results/published_<dataset>.csv`` of the preset ``dataset`` from its recall
    table ``recall_csv`` (``changes``: :func:`published_rows`'); a dataset that is no
    preset has no published rows: an error that names it."""

    preset = presets().get(dataset)
    if preset is None:
        raise ValueError(
            f"dataset {dataset!r} is not a vprflow preset, so it has no published rows "
            f"(docs/datasets.md lists the presets: {', '.join(presets())})"
        )
    with open(recall_csv, newline="") as f:
        recall_rows = list(csv.DictReader(f))
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(published_rows(preset.published, recall_rows, changes))
    write_text_atomic(out, text.getvalue())

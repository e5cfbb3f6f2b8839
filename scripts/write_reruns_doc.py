"""Regenerate the table of docs/usage.md's "What a change reruns" from the plan
(vprflow.planning.reruns): for each setting, the stages whose keys a change gives a new value.

python scripts/write_reruns_doc.py
"""

from pathlib import Path

from vprflow.planning.reruns import reruns_doc, with_table

REPO = Path(__file__).resolve().parents[1]
usage = REPO / "docs" / "usage.md"
table = reruns_doc(
    REPO / "config" / "config.yaml", REPO / "workflow" / "schemas" / "config.schema.yaml"
)
usage.write_text(with_table(usage.read_text(), table))

"""Regenerate docs/datasets.md from the presets (src/vprflow/presets.yaml).

python scripts/write_datasets_doc.py
"""

from pathlib import Path

from vprflow.presets import datasets_doc

REPO = Path(__file__).resolve().parents[1]
(REPO / "docs" / "datasets.md").write_text(datasets_doc())

"""Regenerate config/README.md from the schema's descriptions.

python scripts/write_config_readme.py
"""

from pathlib import Path

from vprflow.config import config_readme, load_schema

REPO = Path(__file__).resolve().parents[1]
schema = load_schema(REPO / "workflow" / "schemas" / "config.schema.yaml")
(REPO / "config" / "README.md").write_text(config_readme(schema))

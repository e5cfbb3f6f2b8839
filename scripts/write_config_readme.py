"""Regenerate config/README.md from the schema's descriptions.

python scripts/write_config_readme.py
"""

from pathlib import Path

import yaml

from vprflow.planning.config import config_readme, load_schema

REPO = Path(__file__).resolve().parents[1]
schema = load_schema(REPO / "workflow" / "schemas" / "config.schema.yaml")
shipped = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
(REPO / "config" / "README.md").write_text(config_readme(schema, shipped))

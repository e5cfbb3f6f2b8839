"""Regenerate config/README.md from the schema's descriptions, the registry's kind and
search-index defaults and the shipped config/config.yaml.

python scripts/write_config_readme.py

A doc generator, so it lives here rather than in the package: nothing the workflow runs
needs it. ``tests/planning/test_registry.py`` loads it (tests/script_helpers.py) to check that
config/README.md is current.
"""

from __future__ import annotations

import json
from pathlib import Path

import yaml

from vprflow.models.kinds import BACKBONES, SEGMENTERS
from vprflow.planning.config import METHOD_DEFAULT_SECTIONS, load_schema
from vprflow.search.indexes import SEARCH_INDEXES

REPO = Path(__file__).resolve().parents[1]

_README_HEAD = """# Configuration

`config/config.yaml` is the configuration the workflow reads (pass another with
`--configfile`). It is validated against `workflow/schemas/config.schema.yaml`: an
unknown key is an error that names it, and so is a key that the entry's kind does not
read (a ground truth's `kind`, a backbone's `backbone`, a segmenter's `segmenter`, a
re-ranker's `kind`, a vocabulary's `source`): the error lists the kind's keys. Every
`default` below is filled in before anything is hashed, so a store's key and attributes
record what ran. Names of datasets, methods, backbones, segmenters and re-rankers are
plain names (letters, digits, `_`, `.`, `-`, starting with a letter or digit): they
become file and folder names under `results/` and `logs/`.

A method's settings are, later winning: the top-level sections
({sections}),
then the dataset's `defaults`, then the method's own. Backbone and segmenter entries
also get their kind's defaults (`src/vprflow/models/kinds.py`), and a method's
`retrieval.params` its index's (`src/vprflow/search/defaults.py`), listed below by kind
and by index. A default followed by a condition in brackets applies only then. What the
methods compute is in `docs/methods.md`.

This file is generated from the schema's descriptions and config/config.yaml by
`python scripts/write_config_readme.py`; `tests/planning/test_registry.py` checks it is current.
"""


def _allowed(prop: dict) -> str:
    if "enum" in prop:
        return " / ".join(f"`{v}`" for v in prop["enum"])
    if "const" in prop:
        return f"`{prop['const']}`"
    if "oneOf" in prop:
        return " or ".join(_allowed(p) for p in prop["oneOf"])
    if "$ref" in prop:
        name = prop["$ref"].rsplit("/", 1)[-1]
        return _REF_TEXT.get(name, f"see `{name}`")
    kind = prop.get("type", "")
    if kind == "array":
        return f"list of {_allowed(prop.get('items', {}))}"
    if kind == "object" and isinstance(prop.get("additionalProperties"), dict):
        return f"name -> {_allowed(prop['additionalProperties'])}"
    bounds = [f"{op} {prop[key]}" for key, op in _BOUNDS if key in prop]
    kind = " or ".join(kind) if isinstance(kind, list) else kind
    return ", ".join([kind, *bounds]) if kind else ""


_REF_TEXT = {"size": "[width, height]", "name": "plain name"}
_BOUNDS = (("minimum", ">="), ("exclusiveMinimum", ">"), ("maximum", "<="))


def _table(title: str, definition: dict, kinds: dict | None = None) -> list[str]:
    """A section's table; ``kinds``: the registry's kinds whose defaults its entries get."""
    required = set(definition.get("required", []))
    defaults = _conditional_defaults(definition)
    for kind in (kinds or {}).values():
        for name, value in kind.defaults.items():
            defaults.setdefault(name, {}).setdefault(json.dumps(value), []).append(kind.name)
    lines = [f"## `{title}`", ""]
    if definition.get("description"):
        lines += [definition["description"], ""]
    lines += ["| key | allowed | default | meaning |", "|---|---|---|---|"]
    for name, prop in definition.get("properties", {}).items():
        default = "required" if name in required else ""
        if "default" in prop:
            default = f"`{json.dumps(prop['default'])}`"
        elif name in defaults:
            default = ", ".join(
                f"`{value}` ({', '.join(where)})" for value, where in defaults[name].items()
            )
        meaning = prop.get("description", "").replace("|", "\\|")
        lines.append(f"| `{name}` | {_allowed(prop)} | {default} | {meaning} |")
    return [*lines, ""]


def _conditional_defaults(definition: dict) -> dict[str, dict[str, list[str]]]:
    """Key -> default -> the conditions under which it applies, from the definition's
    ``allOf`` of ``if``/``then`` (e.g. ``kind utm``)."""
    found: dict[str, dict[str, list[str]]] = {}
    for part in definition.get("allOf", []):
        condition = part.get("if", {}).get("properties", {})
        when = " and ".join(f"{k} {v['const']}" for k, v in condition.items() if "const" in v)
        for name, prop in part.get("then", {}).get("properties", {}).items():
            if "default" in prop:
                found.setdefault(name, {}).setdefault(json.dumps(prop["default"]), []).append(when)
    return found


def _search_index_table() -> list[str]:
    lines = [
        "## `retrieval.params` by index",
        "",
        "Each index's parameters and their defaults (`src/vprflow/search/defaults.py`), filled "
        "into a method's `retrieval.params` before hashing; `null` = chosen by `vprflow.search` "
        "(`nlist`, `m`: from the data; `margin`: by `candidate_dtype`). An approximate "
        "index's table also reports an exact search's recall.",
        "",
        "| index | exact | parameters (default) |",
        "|---|---|---|",
    ]
    for index in SEARCH_INDEXES.values():
        params = ", ".join(f"`{k}` (`{json.dumps(v)}`)" for k, v in index.defaults.items())
        exact = "yes" if index.exact else "no"
        lines.append(f"| `{index.name}` | {exact} | {params or 'none'} |")
    return [*lines, ""]


def config_readme(schema: dict, shipped: dict | None = None) -> str:
    """``config/README.md``: what the shipped config (``shipped``, config/config.yaml as
    read) defines, then every key of the schema, its allowed values, default (the
    schema's, its kind's from the registry) and meaning (the schema's ``description``s),
    and each search index's parameter defaults."""
    sections = ", ".join(f"`{name}`" for name in METHOD_DEFAULT_SECTIONS)
    lines = [_README_HEAD.replace("{sections}", sections)]
    if shipped is not None:
        lines += _shipped_tables(shipped)
    lines += _table("top level", schema)
    kinds = {"backbone": BACKBONES, "segmenter": SEGMENTERS}
    for name, definition in schema["definitions"].items():
        if "properties" not in definition:
            continue
        lines += _table(name, definition, kinds.get(name))
        for sub, prop in definition["properties"].items():
            if "properties" in prop:
                lines += _table(f"{name}.{sub}", prop)
        if name == "retrieval":
            lines += _search_index_table()
    return "\n".join(lines).rstrip() + "\n"


# What a shipped entry is, in a table cell: the keys that tell entries apart.
_SHIPPED_KEYS = {
    "backbones": ("backbone", "model", "layer", "facet", "file"),
    "segmenters": ("segmenter", "model", "n_segments", "file"),
    "rerankers": ("kind", "features"),
}


def _flow(value) -> str:
    """``value`` as one line of YAML, as a config would write it."""
    return yaml.safe_dump(value, default_flow_style=True, width=10**6).strip()


def _shipped_tables(shipped: dict) -> list[str]:
    """The entries config/config.yaml defines (backbones, segmenters, re-rankers,
    methods, datasets) and its ``data_root``, one table row each."""

    def cell(entry: dict, keys) -> str:
        return ", ".join(f"{k}: `{entry[k]}`" for k in keys if entry.get(k) is not None)

    lines = [
        "## What `config/config.yaml` ships",
        "",
        f"`data_root` is `{shipped['data_root']}` (relative to the directory Snakemake runs "
        "in; `--config data_root=...` points elsewhere). `device` is "
        f"`{shipped.get('device', 'auto')}`; `targets`: "
        f"{', '.join(f'`{t}`' for t in shipped.get('targets', [])) or 'none'}.",
        "",
    ]
    for section, keys in _SHIPPED_KEYS.items():
        lines += [f"`{section}`:", "", "| name | what |", "|---|---|"]
        lines += [f"| `{n}` | {cell(e, keys)} |" for n, e in shipped.get(section, {}).items()]
        lines.append("")
    lines += ["`methods` (an aggregator, and what the method overrides):", ""]
    lines += ["| name | aggregator | overrides |", "|---|---|---|"]
    for name, method in shipped["methods"].items():
        overrides = {k: v for k, v in method.items() if k != "aggregator"}
        text = ", ".join(f"`{_flow({k: v})}`" for k, v in overrides.items()) or "-"
        lines.append(f"| `{name}` | `{method['aggregator']}` | {text} |")
    lines += ["", "`datasets` (the papers' datasets are presets: docs/datasets.md):", ""]
    lines += ["| name | methods | re-ranked |", "|---|---|---|"]
    for name, dataset in shipped.get("datasets", {}).items():
        methods = ", ".join(f"`{m}`" for m in dataset.get("methods", []))
        rerank = "; ".join(
            f"`{m}` by {', '.join(f'`{r}`' for r in rs)}"
            for m, rs in (dataset.get("rerank") or {}).items()
        )
        lines.append(f"| `{name}` | {methods} | {rerank or '-'} |")
    return [*lines, ""]


def main() -> None:
    schema = load_schema(REPO / "workflow" / "schemas" / "config.schema.yaml")
    shipped = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    (REPO / "config" / "README.md").write_text(config_readme(schema, shipped))


if __name__ == "__main__":
    main()

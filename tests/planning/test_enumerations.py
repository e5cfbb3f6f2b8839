"""Every enumeration the config schema shows comes from the code's constant (``x-enum``),
so the schema cannot drift from what the code accepts; the few the schema types itself
are ones the code holds no list of."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from vprflow.core.errors import ConfigError
from vprflow.planning.config import ENUM_MODULES, enum_values, load_schema, validate_config

REPO = Path(__file__).resolve().parents[2]
SCHEMA_PATH = REPO / "workflow" / "schemas" / "config.schema.yaml"
PACKAGE = REPO / "src" / "vprflow"

# Enums typed in the schema file, each with why: the code branches on each value and
# holds no list of them, so the schema's list is the only one.
HAND_TYPED = {
    "#/definitions/dataset/properties/ground_truth/properties/source": "coordinates "
    "reader: `exif` or the file",
    "#/definitions/dataset/properties/ground_truth/properties/query_index": "vprbench "
    "reader: `position` or the first column",
    "#/definitions/dataset/properties/ground_truth/properties/dims": "a count of columns",
    "#/definitions/dataset/properties/ground_truth/properties/city": "MSLS: a city the "
    "list paths name, or all",
    "#/definitions/vocabulary/properties/source": "the vocabulary stage and the plan branch on it",
    "#/definitions/vocabulary/properties/fit_on": "the dataset's image roles",
    "#/definitions/segvlad/properties/mask_to_patch": "the descriptors stage makes it "
    "segvlad's crop_aligned flag",
    "#/properties/device": "resolve_device takes more (cuda:N, mps) than a config offers",
}


def _walk(part, where: str = "#"):
    """``(place, schema object)`` of every object in ``part``."""
    if isinstance(part, dict):
        yield where, part
        for key, value in part.items():
            yield from _walk(value, f"{where}/{key}")
    elif isinstance(part, list):
        for index, item in enumerate(part):
            yield from _walk(item, f"{where}/{index}")


def _raw() -> dict:
    return yaml.safe_load(SCHEMA_PATH.read_text())


def _code_constants() -> dict[str, frozenset]:
    """``module:NAME`` -> its values, for every module-level literal tuple, list or dict
    (its keys) of strings in the package, read from the source (no import)."""
    found = {}
    for path in PACKAGE.rglob("*.py"):
        module = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        for node in ast.parse(path.read_text()).body:
            if not isinstance(node, ast.Assign) or len(node.targets) != 1:
                continue
            target = node.targets[0]
            if not isinstance(target, ast.Name) or not target.id.isupper():
                continue
            items = node.value.keys if isinstance(node.value, ast.Dict) else None
            if isinstance(node.value, (ast.Tuple, ast.List)):
                items = node.value.elts
            if items and all(isinstance(i, ast.Constant) for i in items):
                found[f"{module}:{target.id}"] = frozenset(i.value for i in items)
    return found


def test_every_enum_of_the_schema_file_is_an_x_enum_or_a_documented_exception():
    typed = {where for where, part in _walk(_raw()) if "enum" in part}
    assert typed == set(HAND_TYPED)


def test_no_hand_typed_enum_restates_a_constant_of_the_code():
    constants = _code_constants()
    raw = dict(_walk(_raw()))
    for where in HAND_TYPED:
        values = frozenset(raw[where]["enum"])
        same = [name for name, code in constants.items() if code == values]
        assert not same, f"schema {where} restates {same}: name it with x-enum"


def test_every_x_enum_resolves_to_its_constant_and_the_loaded_schema_enums_it():
    raw = dict(_walk(_raw()))
    loaded = dict(_walk(load_schema(SCHEMA_PATH)))
    references = {where: part["x-enum"] for where, part in raw.items() if "x-enum" in part}
    assert len(references) >= 12  # the twelve enumerations, some used twice
    for where, reference in references.items():
        values = enum_values(reference)
        assert values and loaded[where]["enum"] == values, where
        for ref in [reference] if isinstance(reference, str) else reference:
            module, _, name = ref.partition(":")
            assert module in ENUM_MODULES, (where, ref)
            assert name.isupper(), (where, ref)


def test_the_enum_modules_and_config_validation_import_no_torch():
    # Planning (and Snakemake's parse of the workflow) validates configs on machines
    # that need no torch; an x-enum in a module importing it would undo that.
    code = (
        "import sys, yaml\n"
        "from vprflow.planning.config import ENUM_MODULES, validate_config\n"
        "import importlib\n"
        "for name in ENUM_MODULES:\n"
        "    importlib.import_module(name)\n"
        "    assert 'torch' not in sys.modules, name\n"
        f"config = yaml.safe_load(open({str(REPO / 'config' / 'config.yaml')!r}))\n"
        "config['data_root'] = '/nowhere'\n"
        f"validate_config(config, {str(SCHEMA_PATH)!r})\n"
        "assert 'torch' not in sys.modules, 'validate_config'\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def test_a_value_outside_a_code_constant_is_refused_naming_the_key_and_the_values():
    from vprflow.data.images import RESIZE_METHODS

    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["backbones"]["daisy"]["resize"] = "bicubic"
    with pytest.raises(ConfigError, match="backbones.daisy.resize") as error:
        validate_config(config, SCHEMA_PATH)
    assert all(value in str(error.value) for value in RESIZE_METHODS)


@pytest.mark.parametrize(
    ("x_enum", "named"),
    [
        ("vprflow.data.images:NO_SUCH_LIST", "NO_SUCH_LIST"),
        ("vprflow.models.vit:FACETS", "ENUM_MODULES"),
        ("vprflow.data.images:RESIZE_METHODS extra", "RESIZE_METHODS extra"),
        (["vprflow.data.images:RESIZE_METHODS"] * 2, "twice"),
    ],
)
def test_a_bad_x_enum_is_refused_naming_its_place_and_reference(tmp_path, x_enum, named):
    raw = _raw()
    raw["definitions"]["pca"]["properties"]["solver"]["x-enum"] = x_enum
    path = tmp_path / "schema.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(ValueError, match="definitions/pca/properties/solver") as error:
        load_schema(path)
    assert named in str(error.value)


def test_an_enum_beside_an_x_enum_is_refused(tmp_path):
    raw = _raw()
    raw["definitions"]["pca"]["properties"]["solver"]["enum"] = ["exact"]
    path = tmp_path / "schema.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(ValueError, match="solver: both an enum and an x-enum"):
        load_schema(path)

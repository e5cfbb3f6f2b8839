"""Config validation: a key is read by its section's kind or refused, names that become
paths are plain, and a config that expands without bound is refused fast."""

from __future__ import annotations

import copy

import pytest
import yaml
from workflow_helpers import REPO

from vprflow.core.paths import check_inside_outputs
from vprflow.planning.config import (
    MAX_SHOWN,
    ConfigError,
    check_config_files,
    kind_keys,
    load_schema,
    validate_config,
)

SCHEMA_PATH = REPO / "workflow" / "schemas" / "config.schema.yaml"


@pytest.fixture
def raw() -> dict:
    """The shipped config as written (before validation)."""
    return yaml.safe_load((REPO / "config" / "config.yaml").read_text())


def refused(config: dict) -> str:
    with pytest.raises(ConfigError) as error:
        validate_config(config, SCHEMA_PATH)
    return str(error.value)


# ------------------------------------------------------------ every key read by its kind


def test_a_ground_truth_key_of_another_kind_is_an_error_naming_it_the_kind_and_its_keys(raw):
    # {kind: utm, radius_m: 5} used to run at utm's default 25 m.
    raw["datasets"]["corridor"]["ground_truth"] = {"kind": "utm", "radius_m": 5}
    message = refused(raw)
    assert "datasets.corridor.ground_truth.radius_m" in message
    assert "kind 'utm' does not read 'radius_m'" in message
    assert "its keys: kind, radius" in message


@pytest.mark.parametrize(
    ("section", "name", "key", "value", "kind"),
    [
        ("backbones", "daisy", "layer", 3, "backbone 'daisy'"),
        ("backbones", "dinov3_vitl16", "pos_embed_interpolation", "original", "'dinov3'"),
        ("backbones", "dinov2_vitg14", "rings", 3, "'dinov2'"),
        ("segmenters", "slic", "points_per_side", 16, "segmenter 'slic'"),
        ("segmenters", "felzenszwalb", "n_segments", 10, "'felzenszwalb'"),
        ("rerankers", "ransac", "weighting", "similarity", "kind 'ransac'"),
        ("rerankers", "mnn", "threshold", 3.0, "kind 'mnn'"),
    ],
)
def test_an_entry_key_its_kind_does_not_read_is_an_error_naming_it(
    raw, section, name, key, value, kind
):
    raw[section][name][key] = value
    message = refused(raw)
    assert f"config key '{section}.{name}.{key}'" in message
    assert kind in message and "its keys:" in message


def test_a_vocabulary_key_its_source_does_not_read_is_an_error_at_every_level(raw):
    published = {"source": "published", "name": "urban"}
    top = copy.deepcopy(raw)
    top["vocabulary"] = {**published, "n_clusters": 64}
    assert "config key 'vocabulary.n_clusters': source 'published'" in refused(top)
    # A method's override merged over a published top-level source: ignored, so refused.
    method = copy.deepcopy(raw)
    method["vocabulary"] = published
    method["methods"]["anyloc_vlad"]["vocabulary"] = {"n_clusters": 8}
    assert "methods.anyloc_vlad.vocabulary.n_clusters" in refused(method)
    # A dataset's defaults with their own source.
    dataset = copy.deepcopy(raw)
    dataset["datasets"]["corridor"]["defaults"]["vocabulary"] = {"source": "file", "seed": 1}
    assert "datasets.corridor.defaults.vocabulary.seed" in refused(dataset)


def test_a_coordinates_truth_from_exif_refuses_a_file_it_would_not_read(raw):
    truth = {"kind": "coordinates", "source": "exif", "radius_m": 10, "file": "gps.csv"}
    raw["datasets"]["corridor"]["ground_truth"] = truth
    message = refused(raw)
    assert "datasets.corridor.ground_truth.file': source 'exif' does not read 'file'" in message
    truth["source"] = "file"
    validate_config(raw, SCHEMA_PATH)


def test_top_level_vocabulary_keys_may_serve_methods_of_other_sources(raw):
    # Top-level keys are every method's defaults: one method's published source does
    # not make them wrong for the others.
    raw["vocabulary"] = {"n_clusters": 16}
    raw["methods"]["anyloc_vlad"]["vocabulary"] = {"source": "published", "name": "urban"}
    validate_config(raw, SCHEMA_PATH)


def test_the_shipped_configs_and_every_preset_read_every_key_they_set(raw):
    from vprflow.data.presets import presets

    for name in presets():
        raw["datasets"][name] = {}
    validate_config(raw, SCHEMA_PATH)
    validate_config(yaml.safe_load((REPO / ".test/config/config.yaml").read_text()), SCHEMA_PATH)


def test_trained_baselines_is_a_boolean_false_by_default_and_refused_otherwise(raw):
    assert validate_config(copy.deepcopy(raw), SCHEMA_PATH)["trained_baselines"] is False
    # A string that reads as true is no boolean: refused by name before it adds methods.
    raw["trained_baselines"] = "yes"
    message = refused(raw)
    assert "config key 'trained_baselines'" in message and "boolean" in message


def test_each_kinds_keys_come_from_the_schemas_x_kinds():
    schema = load_schema(SCHEMA_PATH)
    truth = schema["definitions"]["dataset"]["properties"]["ground_truth"]
    keys = kind_keys(truth, "kind")
    assert keys["utm"] == ["kind", "radius"]
    assert keys["pairs"] == keys["none"] == ["kind"]
    assert "radius_m" in keys["coordinates"] and "radius" not in keys["coordinates"]


def _kind_descriptions(schema: dict) -> list[tuple[dict, str]]:
    """Each registry with the description of the schema key that names its entries."""
    from vprflow.data.ground_truth import KINDS
    from vprflow.evaluation.rerank import RERANKERS
    from vprflow.search.indexes import SEARCH_INDEXES

    definitions = schema["definitions"]
    truth = definitions["dataset"]["properties"]["ground_truth"]["properties"]
    return [
        (KINDS, truth["kind"]["description"]),
        (RERANKERS, definitions["reranker"]["properties"]["kind"]["description"]),
        (SEARCH_INDEXES, definitions["retrieval"]["properties"]["index"]["description"]),
    ]


def test_each_kinds_meaning_is_its_entrys_and_the_schema_file_states_none():
    # The schema file lists no kind in prose, which a new kind would leave stale; the
    # loaded schema (and config/README.md, made from it) states every entry's own line.
    written = _kind_descriptions(yaml.safe_load(SCHEMA_PATH.read_text()))
    loaded = _kind_descriptions(load_schema(SCHEMA_PATH))
    for (entries, raw_text), (_, text) in zip(written, loaded, strict=True):
        for name, entry in entries.items():
            assert entry.description, name
            assert f"{name} = " not in raw_text, name
            assert f"{name} = {entry.description}" in text, name


# ------------------------------------------------------------ names that become paths


@pytest.mark.parametrize(
    ("where", "edit"),
    [
        ("datasets", lambda c: c["datasets"].update({"../../x": c["datasets"]["corridor"]})),
        ("targets.0", lambda c: c.update(targets=["../../x"])),
        ("methods", lambda c: c["methods"].update({"a/b": {"aggregator": "gem"}})),
        ("rerankers", lambda c: c["rerankers"].update({"x+y": c["rerankers"]["mnn"]})),
        ("backbones", lambda c: c["backbones"].update({"..": {"backbone": "daisy"}})),
        ("segmenters", lambda c: c["segmenters"].update({".hidden": {"segmenter": "slic"}})),
        (
            "datasets.corridor.methods.5",
            lambda c: c["datasets"]["corridor"]["methods"].append("../x"),
        ),
        (
            "datasets.corridor.rerank",
            lambda c: c["datasets"]["corridor"]["rerank"].update({"/x": []}),
        ),
    ],
)
def test_a_name_that_becomes_a_path_must_be_plain(raw, where, edit):
    edit(raw)
    message = refused(raw)
    assert f"config key '{where}'" in message


def test_a_dataset_named_to_climb_out_of_results_is_refused_by_name(raw):
    raw["datasets"]["../../x"] = raw["datasets"]["corridor"]
    raw["targets"] = ["../../x"]
    message = refused(raw)
    assert "'../../x' is not a plain name" in message and "results/ and logs/" in message


def test_the_wildcards_admit_exactly_the_config_names_and_rows_joined_by_a_plus():
    # The schema's name (config entries) and paths.NAME_PATTERN (the `dataset` and
    # `method` wildcards, whose methods include rows `<method>+<reranker>`) agree.
    from vprflow.core.paths import NAME_PATTERN

    pattern = load_schema(SCHEMA_PATH)["definitions"]["name"]["pattern"]
    assert pattern == "^" + NAME_PATTERN.replace("+", "") + "$"


def test_shipped_names_are_plain_and_a_row_name_joins_two_with_a_plus():
    check_inside_outputs("results/recall_corridor.csv", {"dataset": "corridor"})
    check_inside_outputs("logs/export/corridor/anyloc_vlad+mnn.log")


@pytest.mark.parametrize(
    "path",
    ["logs/report/../../x.log", "results/figures/../../../x/a.png", "logs/..", "/tmp/x", "results"],
)
def test_an_output_path_that_leaves_results_and_logs_is_an_error_naming_the_name(path):
    with pytest.raises(ValueError, match="'../../x'.*outside results and logs/"):
        check_inside_outputs(path, {"dataset": "../../x"})


# ------------------------------------------------------------ a config too large to read


def alias_bomb(path, levels: int = 9) -> None:
    """A config whose `targets` expands to 9**levels strings by nested aliases."""
    lines = ["a0: &a0 [" + ", ".join(["lol"] * 9) + "]"]
    for i in range(1, levels):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]")
    lines += ["data_root: data", f"targets: *a{levels - 1}"]
    path.write_text("\n".join(lines) + "\n")


def test_a_yaml_alias_bomb_is_refused_in_seconds_naming_its_file(tmp_path):
    bomb = tmp_path / "bomb.yaml"
    alias_bomb(bomb)
    config = yaml.safe_load(bomb.read_text())  # as Snakemake reads it: shared, small
    # Refused by counting before validation (which used to run 75 s into a MemoryError);
    # no timing threshold here: the speed is in the benchmarks' remit, the refusal here.
    with pytest.raises(ConfigError, match="config file .*bomb.yaml expands to more than"):
        validate_config(config, SCHEMA_PATH, [REPO / "config" / "config.yaml", bomb])


def test_a_key_given_twice_in_one_mapping_is_refused_naming_the_file_and_both_lines(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text("datasets:\n  a: {path: a}\ntargets: [a]\ndatasets:\n  b: {path: b}\n")
    with pytest.raises(ConfigError) as error:
        check_config_files([path])
    assert str(error.value) == (
        f"config file {path}: key 'datasets' is given twice in one mapping, on line 1 and "
        "line 4; YAML would keep only the second (merge the two into one)"
    )
    nested = tmp_path / "nested.yaml"
    nested.write_text("pca:\n  dim: 64\n  whiten: true\n  dim: 128\n")
    with pytest.raises(
        ConfigError, match="key 'dim' is given twice in one mapping, on line 2 and line 4"
    ):
        check_config_files([nested])


def test_the_same_key_in_two_mappings_and_yaml_merge_keys_are_accepted(tmp_path):
    path = tmp_path / "ok.yaml"
    path.write_text(
        "base: &base {dim: 64}\npca: {<<: *base, whiten: false}\n"
        "methods:\n  a: {pca: {dim: 8}}\n  b: {pca: {dim: 8}}\n"
    )
    check_config_files([path])  # no error
    check_config_files([REPO / "config" / "config.yaml"])


def test_an_error_message_shows_at_most_a_bounded_part_of_a_value(raw):
    raw["targets"] = "x" * 100_000  # not a list: the message would print it whole
    message = refused(raw)
    assert len(message) < 3 * MAX_SHOWN
    assert "characters)" in message and "config key 'targets'" in message


# ------------------------------------------------------------ numbers as the schema means them


def with_yaml(raw: dict, text: str) -> dict:
    """``raw`` with the YAML ``text`` (a mapping of dotted key paths to values, as a
    user types them: ``.nan``, ``8.0``) set into it."""
    config = copy.deepcopy(raw)
    for dotted, value in yaml.safe_load(text).items():
        *parents, last = dotted.split(".")
        part = config
        for name in parents:
            part = part.setdefault(name, {})
        part[last] = value
    return config


@pytest.mark.parametrize(
    ("text", "key", "shown"),
    [
        (
            "datasets.corridor.ground_truth: {kind: coordinates, file: gps.csv, radius_m: .nan}",
            "datasets.corridor.ground_truth.radius_m",
            "nan",
        ),
        ("methods.gem.pooling: {gem_p: .inf}", "methods.gem.pooling.gem_p", "inf"),
        ("vocabulary.n_clusters: .nan", "vocabulary.n_clusters", "nan"),
        ("segmenters.slic.sigma: -.inf", "segmenters.slic.sigma", "-inf"),
        (
            "datasets.corridor.defaults: {pca: {dim: 128, whiten: false}, pooling: {gem_p: .nan}}",
            "datasets.corridor.defaults.pooling.gem_p",
            "nan",
        ),
        ("rerankers.ransac.threshold: .inf", "rerankers.ransac.threshold", "inf"),
        ("retrieval.params: {nprobe: .nan}", "retrieval.params.nprobe", "nan"),
    ],
)
def test_a_nan_or_infinite_number_is_refused_naming_its_key_and_value(raw, text, key, shown):
    message = refused(with_yaml(raw, text))
    assert f"config key '{key}': {shown} is not a finite number" in message
    # One line for the key, not the schema's type error beside it.
    assert message.count(f"'{key}'") == 1


def test_integers_written_as_floats_are_read_as_the_integers_they_name(raw):
    text = (
        "vocabulary.n_clusters: 8.0\n"
        "pca.dim: 16.0\n"
        "methods.segvlad: {aggregator: segvlad, segvlad: {order: 2.0}}\n"
        "datasets.corridor.resolution: [160.0, 120.0]\n"
        "datasets.corridor.recall_at: [1.0, 5.0]\n"
        "backbones.daisy.batch_size: 4.0\n"  # a oneOf of an integer and 'auto'
    )
    as_floats = validate_config(with_yaml(raw, text), SCHEMA_PATH)
    as_ints = validate_config(with_yaml(raw, text.replace(".0", "")), SCHEMA_PATH)
    # Equal as text too (8.0 == 8 in Python), so the store keys hashed from them are equal.
    assert yaml.safe_dump(as_floats) == yaml.safe_dump(as_ints)
    assert type(as_floats["vocabulary"]["n_clusters"]) is int
    assert as_floats["datasets"]["corridor"]["resolution"] == [160, 120]
    assert type(as_floats["backbones"]["daisy"]["batch_size"]) is int
    # A number the schema types `number` stays as written.
    assert raw["pooling"]["gem_p"] == 3.0 and type(as_floats["pooling"]["gem_p"]) is float


@pytest.mark.parametrize(
    ("text", "key", "says"),
    [
        ("vocabulary.n_clusters: 8.5", "vocabulary.n_clusters", "8.5 is not of type 'integer'"),
        ("pca.dim: 16.5", "pca.dim", "16.5 is not of type 'integer'"),
        ("backbones.daisy.batch_size: 2.5", "backbones.daisy.batch_size", "2.5 is not valid"),
    ],
)
def test_a_fraction_where_an_integer_is_expected_is_refused_naming_the_key(raw, text, key, says):
    assert f"config key '{key}': {says}" in refused(with_yaml(raw, text))


def with_snakemake_config(raw: dict, *entries: str) -> dict:
    """``raw`` with ``entries`` (``key=value``) merged over it as Snakemake's ``--config``
    merges them: through Snakemake's own parser, which keeps each value inside a mapping
    or a list a string."""
    from snakemake.cli import parse_config
    from snakemake.utils import update_config

    config = copy.deepcopy(raw)
    update_config(config, parse_config(list(entries)))
    return config


@pytest.mark.parametrize(
    ("entry", "key"),
    [
        ("backbones={daisy: {batch_size: 4}}", "backbones.daisy.batch_size"),
        ("backbones={daisy: {normalize: false}}", "backbones.daisy.normalize"),
        ("pca={dim: 16}", "pca.dim"),
        ("datasets={corridor: {resolution: [160, 120]}}", "datasets.corridor.resolution"),
        ("backbones=daisy", "backbones"),
        ("targets=corridor", "targets"),
    ],
)
def test_a_nested_config_value_snakemake_passes_as_a_string_is_refused_naming_configfile(
    raw, entry, key
):
    """A newcomer's `--config "backbones={daisy: {batch_size: 4}}"` was refused with
    "'4' is not valid under any of the given schemas" and no word of why it is a string."""
    message = refused(with_snakemake_config(raw, entry))
    line = next(line for line in message.splitlines() if f"config key '{key}'" in line)
    assert "Snakemake's --config keeps each value inside a mapping or list a string" in line
    assert line.endswith("give nested settings in a YAML file with --configfile")


@pytest.mark.parametrize(
    "config",
    [
        # A string that read as YAML would be refused as well: the value is at fault.
        lambda raw: with_snakemake_config(raw, "backbones={daisy: {batch_size: 0}}"),
        # Not a string at all.
        lambda raw: with_yaml(raw, "vocabulary.n_clusters: 8.5"),
    ],
)
def test_a_value_refused_for_itself_gets_no_word_of_snakemakes_strings(raw, config):
    message = refused(config(raw))
    assert "invalid configuration" in message and "--configfile" not in message


def test_validation_leaves_the_callers_config_as_it_was(raw):
    config = with_yaml(raw, "vocabulary.n_clusters: 8.0")
    before = copy.deepcopy(config)
    validate_config(config, SCHEMA_PATH)
    assert yaml.safe_dump(config) == yaml.safe_dump(before)


# ------------------------------------------------------------ through Snakemake


@pytest.mark.workflow
def test_a_dataset_named_to_climb_out_of_results_stops_the_run_and_writes_nothing(tmp_path):
    from workflow_helpers import snakemake, toy_config, write_config

    workdir = tmp_path / "a" / "b"
    workdir.mkdir(parents=True)
    config = toy_config(tmp_path / "data")
    config["datasets"]["../../x"] = config["datasets"].pop("toy")
    config["targets"] = ["../../x"]
    result = snakemake(workdir, write_config(tmp_path, config), check=False)
    assert result.returncode != 0
    assert "'../../x' is not a plain name" in result.stdout + result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "config.yaml"]
    assert not (workdir / "results").exists() and not (workdir / "logs").exists()


@pytest.mark.workflow
def test_a_yaml_alias_bomb_given_to_snakemake_fails_naming_the_file(tmp_path):
    from workflow_helpers import snakemake

    bomb = tmp_path / "bomb.yaml"
    alias_bomb(bomb)
    result = snakemake(tmp_path, bomb, "-n", check=False)
    assert result.returncode != 0
    assert f"config file {bomb} expands to more than" in result.stdout + result.stderr


@pytest.mark.workflow
def test_a_key_given_twice_in_a_config_file_stops_snakemake_naming_it_and_both_lines(tmp_path):
    """Pasting the README's `datasets:` block at the end of a config used to replace its
    datasets silently (and the error blamed `targets`)."""
    from workflow_helpers import snakemake, toy_config, write_config

    path = write_config(tmp_path, toy_config(tmp_path / "data"))
    first = next(
        i for i, line in enumerate(path.read_text().splitlines(), 1) if line == "datasets:"
    )
    pasted = "datasets:\n  mine: {path: mine, reference: db, query: q}\n"
    path.write_text(path.read_text() + pasted)
    last = len(path.read_text().splitlines()) - 1
    result = snakemake(tmp_path, path, "-n", check=False)
    assert result.returncode != 0
    assert (
        f"config file {path}: key 'datasets' is given twice in one mapping, on line {first} "
        f"and line {last}" in result.stdout + result.stderr
    )


def test_every_document_that_states_the_pairs_depth_states_the_schemas_default():
    """The pairs files' depth is the config key `pairs_depth` (it once was whatever the
    recall stored, documented as "the deepest Recall@N"): each document that gives its
    default gives the schema's, and none ties the pairs to the table's Recall@N."""
    import re

    default = load_schema(SCHEMA_PATH)["properties"]["pairs_depth"]["default"]
    stated = {}
    for path in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        text = " ".join(path.read_text().split())
        for value in re.findall(r"`pairs_depth`, default (\d+)", text):
            stated.setdefault(path.name, []).append(int(value))
        if path.name == "bad-inputs.md":
            continue  # it quotes what the pairs used to be documented as
        for sentence in re.split(r"(?<=\.) ", text):
            if "pairs" in sentence and "deepest Recall@N" in sentence:
                assert "export" not in sentence and "pairs.txt" not in sentence, sentence
    assert {"README.md", "usage.md"} <= stated.keys()
    assert all(v == default for values in stated.values() for v in values), stated

"""Dataset presets: the papers' datasets with their published protocols
(``presets.yaml``; docs/datasets.md is generated from it).

A preset is a dataset entry vprflow ships: the folder layout the authors' code or the
common downloader produces, the ground-truth rule, the resolution, which queries count
and the vocabulary the paper used. It joins a config's ``datasets`` when the config
names it (a ``datasets`` entry of that name, which may give only the keys it changes,
or a name in ``targets``) or when its folder exists under ``data_root`` and the config
defines the methods and models it runs (the shipped config does); so ``snakemake
results/recall_<preset>.csv`` needs no setting beyond the data. A folder decides rather
than the command line's targets because cluster jobs plan again from the config and the
file system alone.

A config entry of a preset's name changes only the keys it gives (``merge_entry``); the
settings tied to the preset's published features follow the features it chooses
(``follow_features``); ``preset: false`` keeps a full entry apart. Where the folder
exists in another layout, ``layout_hint`` says which and how to convert it.

Each published row may name the vprflow method that reproduces it (``row``); with the
config's ``trained_baselines: true`` a preset also runs the trained methods its rows
name (``with_trained_baselines``), so that one run rebuilds the paper's table.
"""

from __future__ import annotations

import copy
import sys
from collections.abc import Callable, Collection
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import yaml

from vprflow.core.errors import ConfigError, PlanError

PRESETS_FILE = Path(__file__).with_name("presets.yaml")
# Dataset keys that do not change what is evaluated or how it is counted: a config that
# changes only these still runs the preset's protocol.
NOT_PROTOCOL = ("methods", "defaults", "recall_at", "source", "download", "path", "rerank")
# Former preset names: a config or target that names one is an error that says where its
# protocol went (a silent alias would hide that `17places` changed meaning).
RENAMED = {
    "17places_pm15": (
        "preset '17places_pm15' was renamed to '17places' (Revisit-Anything's +-15 frames, "
        "queries with a positive: the SegVLAD paper's 95.3 Recall@1); AnyLoc's protocol "
        "(VPR-Bench's +-2 frames file, all queries: its 65.0) is now '17places_anyloc'"
    ),
}


@dataclass(frozen=True)
class Preset:
    """One published dataset: its config entry and what docs/datasets.md says of it."""

    name: str
    dataset: dict  # a config ``datasets`` entry
    title: str  # the dataset as the papers name it
    layout: str  # the folder tree the entry reads, as published
    protocol: str  # positives, queries counted, image size, vocabulary: in words
    code: str  # the published code the entry follows (repository, commit, files)
    # Recall the papers report: method, paper, R@1, R@5 and, where vprflow has the
    # method that reproduces it, ``row`` (that method's name in the recall table).
    published: tuple[dict, ...]
    # The same data in another published layout: name, reference, query, convert.
    other_layouts: tuple[dict, ...] = ()


# A published row's keys; ``row`` is optional.
PUBLISHED_KEYS = ("method", "paper", "recall@1", "recall@5")


@cache
def presets() -> dict[str, Preset]:
    """Every preset, by name, in the file's order."""
    raw = yaml.safe_load(PRESETS_FILE.read_text())
    for name, entry in raw.items():
        for row in entry.get("published") or ():
            _check_published_row(name, row)
    return {
        name: Preset(
            name=name,
            dataset=entry["dataset"],
            title=entry["title"],
            layout=entry["layout"].rstrip("\n"),
            protocol=" ".join(entry["protocol"].split()),
            code=" ".join(entry["code"].split()),
            published=tuple(entry.get("published", ())),
            other_layouts=tuple(
                {**o, "convert": " ".join(o["convert"].split())}
                for o in entry.get("other_layouts", ())
            ),
        )
        for name, entry in raw.items()
    }


def _check_published_row(name: str, row: dict) -> None:
    """A published row has the four keys, numbers for recall and, if any, a method name
    as ``row``: a typo would otherwise reach docs/datasets.md, or drop a trained row."""
    where = f"{PRESETS_FILE}: {name}: published row {row!r}"
    missing = [key for key in PUBLISHED_KEYS if key not in row]
    unknown = sorted(set(row) - {*PUBLISHED_KEYS, "row"})
    if missing or unknown:
        raise ValueError(
            f"{where}: missing {missing}, unknown {unknown} (keys: "
            f"{', '.join(PUBLISHED_KEYS)}, optional row)"
        )
    if not all(isinstance(row[k], (int, float)) for k in ("recall@1", "recall@5")):
        raise ValueError(f"{where}: recall@1 and recall@5 must be numbers")
    if "row" in row and not isinstance(row["row"], str):
        raise ValueError(f"{where}: row must be a method name, not {row['row']!r}")


def undefined_rows(methods) -> list[str]:
    """Every published row whose ``row`` names no method of ``methods`` (the method names
    of config/config.yaml and config/trained.yaml: tests/data/test_presets.py), each naming
    the preset, the row and the method."""
    return [
        f"preset {name!r}: published row {row['method']!r} ({row['paper']}) names method "
        f"{row['row']!r}, which neither config/config.yaml nor config/trained.yaml defines"
        for name, preset in presets().items()
        for row in preset.published
        if "row" in row and row["row"] not in methods
    ]


def is_trained_method(method: str, config: dict, trained_kinds: Collection[str]) -> bool:
    """Whether ``method`` of ``config`` runs a trained VPR model: the aggregator
    ``model`` (a model's own descriptor), or its own ``features`` a backbone entry of
    one of ``trained_kinds`` (config/trained.yaml's salad_tokens_vlad). A method the
    config lacks counts when it bears a trained kind's name, as config/trained.yaml
    names them."""
    settings = (config.get("methods") or {}).get(method)
    if not isinstance(settings, dict):
        return method in trained_kinds
    backbone = (config.get("backbones") or {}).get(settings.get("features")) or {}
    return settings.get("aggregator") == "model" or backbone.get("backbone") in trained_kinds


@dataclass(frozen=True)
class Components:
    """What the presets read of the code's components, given by planning (this wing
    imports none of theirs): the aggregators that need a vocabulary, the trained
    backbone kinds, and ``fill_backbone(entry)``, a backbone entry with its kind's
    defaults filled in."""

    vocabulary_aggregators: Collection[str]
    trained_kinds: Collection[str]
    fill_backbone: Callable[[dict], dict]


def with_trained_baselines(
    name: str, dataset: dict, config: dict, trained_kinds: Collection[str]
) -> dict:
    """The preset ``name``'s config entry ``dataset`` with the trained methods its
    published rows name appended to ``methods`` (in the rows' order, skipping those it
    runs already), when the config sets ``trained_baselines: true``; else unchanged. A
    trained row the config does not define is an error naming config/trained.yaml."""
    # `is True`: this runs before the schema checks the key's type, which then refuses
    # anything but a boolean.
    if config.get("trained_baselines") is not True:
        return dataset
    methods = list(dataset.get("methods") or ())
    defined = config.get("methods") or {}
    for row in presets()[name].published:
        method = row.get("row")
        if (
            method is None
            or method in methods
            or not is_trained_method(method, config, trained_kinds)
        ):
            continue
        if method not in defined:
            raise ConfigError(
                f"config key 'trained_baselines': datasets.{name} (preset {name!r}) runs "
                f"the trained method {method!r} of its published row {row['method']!r}, "
                "which this config does not define: add config/trained.yaml (snakemake "
                "--configfile config/config.yaml config/trained.yaml), which defines it, "
                "or set trained_baselines: false"
            )
        methods.append(method)
    return {**dataset, "methods": methods}


def merge_entry(base: dict, override: dict) -> dict:
    """``base`` with ``override``'s keys put over it, mappings merged key by key; a
    mapping that names another ``kind`` (a ground-truth rule) or ``source`` (a
    vocabulary) replaces the base's, whose other keys belong to that kind or source."""
    merged = copy.deepcopy(base)
    for key, value in override.items():
        old = merged.get(key)
        if (
            isinstance(old, dict)
            and isinstance(value, dict)
            and all(value.get(s, old.get(s)) == old.get(s) for s in ("kind", "source"))
        ):
            merged[key] = merge_entry(old, value)
        else:
            merged[key] = copy.deepcopy(value)
    return merged


def with_presets(config: dict, components: Components) -> dict:
    """``config["datasets"]`` completed with the presets it uses: those it names (its
    entry of the same name merged over the preset) and those whose folder exists under
    ``data_root``. Other presets stay out, so a missing one costs nothing. With
    ``trained_baselines: true`` each runs the trained methods its published rows name
    (:func:`with_trained_baselines`).

    An entry with ``preset: false`` is used as it is. A full entry (every required key)
    that bears a preset's name is merged with it all the same, and the log and the
    ``protocol`` column say so. When the entry (or a method it runs) chooses other
    features than the preset's, the settings tied to the published features follow
    (:func:`follow_features`) or planning stops naming the keys to set (for a method
    whose aggregator needs a vocabulary)."""
    datasets = dict(config.get("datasets") or {})
    targets = set(config.get("targets") or ())
    for name in sorted(RENAMED.keys() & (datasets.keys() | targets)):
        if (datasets.get(name) or {}).get("preset") is False:
            continue  # a dataset of the user's own that happens to bear the old name

        where = f"datasets.{name}" if name in datasets else "targets"
        raise ConfigError(f"config key '{where}': {RENAMED[name]}")
    for name, entry in datasets.items():
        if name not in presets() and isinstance(entry, dict) and "preset" in entry:
            datasets[name] = {k: v for k, v in entry.items() if k != "preset"}  # no preset
    for name, preset in presets().items():
        if name in datasets:
            entry = datasets[name] or {}
            if entry.get("preset") is False:
                continue  # the user's own dataset; protocol() says so
            base, notes = follow_features(name, preset.dataset, entry, config, components)
            datasets[name] = with_trained_baselines(
                name, merge_entry(base, entry), config, components.trained_kinds
            )
            if entry.get("preset") is None and all(key in entry for key in REQUIRED):
                datasets[name]["preset"] = True  # read (and removed) by protocol()
                taken = sorted(k for k in preset.dataset if k not in entry)
                notes.insert(
                    0,
                    f"datasets.{name} is a full entry and bears the name of the preset "
                    f"{name!r}: merged with it (from the preset: {', '.join(taken) or 'nothing'}"
                    "); set `preset: false` in the entry to use it alone, `preset: true` to "
                    "merge without this note",
                )
            _say(notes)
            _check_method_features(
                name, datasets[name], preset.dataset, config, components.vocabulary_aggregators
            )
        elif name in targets or (
            (Path(config["data_root"]) / preset.dataset["path"]).is_dir()
            and not undefined_components(preset.dataset, config)
        ):
            datasets[name], notes = follow_features(name, preset.dataset, {}, config, components)
            datasets[name] = with_trained_baselines(
                name, datasets[name], config, components.trained_kinds
            )
            _say(notes)
            _check_method_features(
                name, datasets[name], preset.dataset, config, components.vocabulary_aggregators
            )
    return datasets


# A dataset entry's required keys (the schema's): an entry with all of them is a full
# entry, a dataset of its own, not a change to a preset.
REQUIRED = ("path", "reference", "query", "resolution", "ground_truth", "methods")
_SAID: set[str] = set()


def _say(notes: list[str]) -> None:
    """Print each note once per process (the log of the run that plans)."""
    for note in notes:
        if note not in _SAID:
            _SAID.add(note)
            print(f"vprflow: {note}", file=sys.stderr)


def follow_features(
    name: str, preset: dict, entry: dict, config: dict, components: Components
) -> tuple[dict, list]:
    """The preset's entry made to follow the features ``entry`` chooses
    (``defaults.features``), and notes saying what followed. Tied to the preset's
    features (DINOv2 ViT-G/14 layer 31 value): its published vocabulary (centres of
    those 1,536-d features; the config's own vocabulary section, fitted on the map by
    default, takes its place unless the entry sets a ``vocabulary.source``) and its
    re-rankers on those features (each replaced by the config's re-ranker of the same
    kind and options on the chosen features, or dropped where there is none, unless the
    entry gives that method's ``rerank``). Unchanged when the entry keeps the features."""
    own = (preset.get("defaults") or {}).get("features")
    defaults = (entry.get("defaults") or {}) if isinstance(entry, dict) else {}
    chosen = defaults.get("features")
    if own is None:
        return preset, []
    if chosen is None or chosen == own:
        # The same entry name, but is it still the features the vocabulary is of?
        why = _not_published_features(own, config, components.fill_backbone)
        chosen, change = own, f"backbones.{own} ({why})"
        if why is None:
            return preset, []
    else:
        change = f"features {chosen!r} (not the preset's {own!r})"
    base, notes = copy.deepcopy(preset), []
    vocabulary = base["defaults"].get("vocabulary") or {}
    if vocabulary.get("source") == "published" and "source" not in (
        defaults.get("vocabulary") or {}
    ):
        del base["defaults"]["vocabulary"]
        source = (config.get("vocabulary") or {}).get("source", "map")
        notes.append(
            f"datasets.{name}: with {change}, the published vocabulary "
            f"{vocabulary['name']!r} (centres of DINOv2 ViT-G/14 layer 31 value features) "
            f"gives way to the config's `vocabulary` (source {source}); set "
            f"datasets.{name}.defaults.vocabulary to choose another"
        )
    if chosen == own:
        return base, notes  # re-rankers on the entry follow it by name
    pca = config.get("pca") or {}
    if "pca" not in defaults and pca.get("enabled", True):
        notes.append(
            f"datasets.{name}: the config's `pca` (dim {pca.get('dim', 1024)}, whiten "
            f"{pca.get('whiten', True)}) applies to {chosen!r}; the published 1024 whitened "
            "components are sized for 49,152-d DINOv2-G VLAD descriptors: set "
            f"datasets.{name}.defaults.pca for yours (corridor runs DAISY with dim 128, "
            "whiten false)"
        )
    rerankers = config.get("rerankers") or {}
    for method, names in (base.get("rerank") or {}).items():
        if method in (entry.get("rerank") or {}):
            continue
        kept = []
        for reranker in names:
            spec = rerankers.get(reranker) or {}
            if spec.get("features") != own:
                kept.append(reranker)
                continue
            twins = [
                other
                for other, o in rerankers.items()
                if o.get("features") == chosen
                and {k: v for k, v in o.items() if k != "features"}
                == {k: v for k, v in spec.items() if k != "features"}
            ]
            if len(twins) == 1:
                kept.append(twins[0])
            what = f"re-ranker {twins[0]!r}" if len(twins) == 1 else "nothing (dropped)"
            notes.append(
                f"datasets.{name}: rerank.{method}: {reranker!r} matches {own}'s features, "
                f"replaced by {what} on {chosen!r}; set datasets.{name}.rerank.{method} "
                "to choose"
            )
        base["rerank"][method] = kept
    return base, notes


def _not_published_features(
    entry_name: str, config: dict, fill_backbone: Callable[[dict], dict]
) -> str | None:
    """How the config's backbone entry ``entry_name`` differs from DINOv2 ViT-G/14 layer
    31 value, the features of the published 1,536-d vocabularies, or None where it does
    not (as far as the entry tells: a local model directory is taken for ViT-G/14)."""
    spec = (config.get("backbones") or {}).get(entry_name)
    if not isinstance(spec, dict):
        return None
    try:
        filled = fill_backbone(spec)
    except Exception:  # an invalid entry: the schema says why
        return None
    if filled.get("backbone") != "dinov2":
        return f"backbone {filled.get('backbone')}"
    model = str(filled.get("model"))
    hub = model.startswith("facebook/dinov2-") and not Path(model).exists()
    differences = [
        f"{key} {filled.get(key)}"
        for key, value in (("layer", 31), ("facet", "value"))
        if filled.get(key) != value
    ]
    differences += [f"model {model}"] if hub and model != "facebook/dinov2-giant" else []
    differences += ["checkpoint (fine-tuned weights)"] if filled.get("checkpoint") else []
    return ", ".join(differences) or None


def _check_method_features(
    name: str, dataset: dict, preset: dict, config: dict, vocabulary_aggregators: Collection[str]
) -> None:
    """Planning stops when a method the dataset runs (by an aggregator of
    ``vocabulary_aggregators``, those that need a vocabulary) has features of its own
    while the dataset's vocabulary is still the preset's published one, fitted on other
    features: the keys to set are named (the vocabulary stage would fail after the fetch
    and the features otherwise)."""

    defaults = dataset.get("defaults") or {}
    vocabulary = defaults.get("vocabulary") or {}
    own = (preset.get("defaults") or {}).get("features")
    if vocabulary.get("source") != "published" or defaults.get("features") != own:
        return
    for method in dataset.get("methods") or ():
        settings = (config.get("methods") or {}).get(method) or {}
        features = settings.get("features")
        if (
            features in (None, own)
            or settings.get("aggregator") not in vocabulary_aggregators
            or "source" in (settings.get("vocabulary") or {})
        ):
            continue

        raise PlanError(
            f"datasets.{name} (preset {name!r}) runs method {method!r} on features "
            f"{features!r}, but its vocabulary is the published {vocabulary['name']!r}, "
            f"centres of the preset's {own!r} features: set methods.{method}.vocabulary."
            f"source (map fits it on {features!r}; published with a vocabulary of those "
            f"features), or datasets.{name}.defaults.vocabulary"
        )


def undefined_components(dataset: dict, config: dict) -> list[str]:
    """The methods, backbones, segmenters and re-rankers a dataset entry names that
    ``config`` does not define: a preset found by its folder joins only a config that can
    run it (a small config of one's own need not define the papers' models)."""
    defaults = dataset.get("defaults") or {}
    wanted = [("methods", m) for m in dataset["methods"]]
    wanted += [(section, defaults[key]) for key, section in _NAMED if key in defaults]
    rerank = dataset.get("rerank") or {}
    wanted += [("rerankers", r) for m in dataset["methods"] for r in rerank.get(m, ())]
    return [f"{section}.{name}" for section, name in wanted if name not in config.get(section, {})]


_NAMED = (("features", "backbones"), ("segmenter", "segmenters"))


def protocol(name: str, preset: dict, dataset: dict) -> str:
    """What a results table says of the protocol of ``dataset``, a config entry made from
    the preset ``name`` (both with their defaults filled): the preset's name, and the
    protocol keys the config changed, if any; "merged with preset" for a full entry
    merged with it, "own entry" for one with ``preset: false``. Removes the entry's
    ``preset`` key (:func:`with_presets`' mark, not a setting of any stage)."""
    merged = dataset.pop("preset", None)  # with_presets' mark: read here, not a setting
    if merged is False:
        return f"own entry (preset {name} not applied: preset: false)"
    changed = sorted(
        key
        for key in _flat(preset).keys() | _flat(dataset).keys()
        if key.split(".")[0] not in NOT_PROTOCOL
        and _flat(preset).get(key) != _flat(dataset).get(key)
    )
    # A section whose kind changed is named once: its other keys changed with it.
    replaced = {key.rpartition(".")[0] for key in changed if key.endswith(".kind")}
    changed = sorted({next((r for r in replaced if k.startswith(r + ".")), k) for k in changed})
    said = f"merged with preset {name}" if merged else f"preset {name}"
    return said + (f", changed: {', '.join(changed)}" if changed else "")


def _flat(entry: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in entry.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def unknown_dataset(name: str, config: dict) -> str:
    """Why ``name`` is not among a validated config's datasets: a preset whose folder is
    missing (where to put it, where to get it, the layout it must have), or a name that
    is neither configured nor a preset."""
    preset = presets().get(name)
    if name in RENAMED:
        return f"unknown dataset {name!r}: {RENAMED[name]}"
    if preset is None:
        return (
            f"unknown dataset {name!r}; configured: {sorted(config['datasets'])}; "
            f"presets: {sorted(presets())}"
        )
    folder = Path(config["data_root"]) / preset.dataset["path"]
    if folder.is_dir():
        return (
            f"dataset {name!r} is a vprflow preset ({preset.title}) and {folder} exists, but "
            f"this config does not define {undefined_components(preset.dataset, config)}, "
            f"which it runs: define them, or give `datasets.{name}` methods and defaults "
            "that exist (config/config.yaml defines the preset's)"
        )
    return (
        f"dataset {name!r} is a vprflow preset ({preset.title}), and its folder {folder} "
        f"does not exist. Get it from {preset.dataset['source']}. "
        f"Expected layout (docs/datasets.md):\n{preset.layout}"
    )


def layout_hint(name: str, root: Path, dataset: dict) -> str:
    """What to say when the folder ``root`` of the preset ``name`` exists but lacks the
    reference or query the entry ``dataset`` reads: the layout the preset reads, the
    same layout found one level down, or another published layout of the dataset found
    instead, each with how to convert it. Empty for a dataset that is not the preset's
    layout (another name, or an entry that reads other folders)."""
    preset = presets().get(name)
    wanted = ("reference", "query")
    if preset is None or any(dataset.get(k) != preset.dataset[k] for k in wanted):
        return ""
    lines = [f"The preset {name!r} reads this layout (docs/datasets.md):", preset.layout]

    def has(base: Path, relative: str) -> bool:
        path = base / relative
        return path.is_file() if path.suffix.lower() == ".txt" else path.is_dir()

    found = False
    children = sorted(c for c in root.iterdir() if c.is_dir() and not c.name.startswith("."))
    for child in children:
        if all(has(child, dataset[k]) for k in wanted):
            found = True
            lines.append(
                f"Found it one level down, in {child}: move it up (cd {root} && "
                f"mv {child.name}/* . && rmdir {child.name}), or set "
                f"datasets.{name}.path: {dataset['path']}/{child.name}"
            )
    for other in preset.other_layouts:
        for base in (root, *children):
            if has(base, other["reference"]) and has(base, other["query"]):
                found = True
                lines.append(
                    f"{base} holds {other['name']}, not the layout above. "
                    f"Convert it (in {base}): {other['convert']}"
                )
    if not found:
        names = [p.name + ("/" if p.is_dir() else "") for p in sorted(root.iterdir())]
        others = "; ".join(o["name"] for o in preset.other_layouts)
        lines.append(
            f"{root} holds {', '.join(names[:12]) or 'nothing'}"
            + (", ..." if len(names) > 12 else "")
            + ": neither that layout, nor it one level down"
            + (f", nor {others}" if others else "")
        )
    return "\n" + "\n".join(lines)

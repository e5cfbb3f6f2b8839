"""From a validated config to the content-addressed stages of every experiment.

Each stage instance is identified by a key: a short hash of exactly the parameters
that shape its output, the keys of its inputs and a per-stage format version.
Outputs live at ``results/cache/<stage>/<key>.zarr``. Two experiments that agree on
a stage's parameters and inputs get the same key and share the store; changing a
parameter changes the key of that stage and of everything downstream only.

Every stage is one row of :data:`STAGES` (at the end of this module): its format version,
whether its jobs take ranges of images, and, for a stage an aggregator may need, how it is
planned (the function that runs its jobs is in :data:`vprflow.stages.jobs.RUNNERS`). Bump
a stage's ``version`` whenever the code changes what the stage writes: Snakemake does not
track the library's source, only the key does.
"""

from __future__ import annotations

import copy
import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

from vprflow.aggregation.vocabularies import PUBLISHED as PUBLISHED_VOCABULARIES
from vprflow.core.errors import PlanError
from vprflow.core.masks import PACKED
from vprflow.core.paths import PUBLISHED_VOCABULARY, store_path
from vprflow.data.datasets import listing_truth
from vprflow.data.images import ImageReadError, dataset_orientation, image_size
from vprflow.planning.checkpoints import PlannedCheckpoint, absent, missing_message
from vprflow.planning.config import METHOD_DEFAULT_SECTIONS
from vprflow.planning.fingerprints import (
    dataset_contents,
    file_digest,
    memoised,
    source_fingerprint,
)

if TYPE_CHECKING:
    from vprflow.data.datasets import DatasetFiles
from vprflow.aggregation.aggregators import Aggregator, aggregator, prefixed
from vprflow.evaluation.rerank import RERANKERS
from vprflow.models.kinds import OWN_SIZE, TRAINED_KINDS, TrainedModel, model_kind
from vprflow.search.indexes import SEARCH_INDEXES, search_settings

# Which dataset settings shape which store. A dataset's settings are split between
# what the images are (the `images` store: list, order, content, reader) and what is
# true about them (the `dataset` store: the ground truth), so a ground-truth change
# reruns no model stage. A setting in neither tuple below shapes the images
# store: one the images stage reads (recursive, follow_links, ...) is never left out.
# The truth store's settings (of these, MSLS's `kind` and `city` also pick the images:
# `datasets.listing_truth`).
TRUTH_SETTINGS = ("ground_truth",)
# Settings that shape neither store (later stages read them, or they are for people):
# kept out of both keys, so changing them rebuilds only what uses them.
NOT_DATASET_STAGE = (
    "methods",
    "defaults",
    "recall_at",
    "denominator",
    "resolution",
    "source",
    "download",
    "protocol",
    "rerank",
)

# Settings that change how a stage runs but not what it computes: kept out of keys.
EXECUTION_ONLY = ("batch_size", "cache_dir")


def content_key(record: dict) -> str:
    """16 hex digits of the SHA-256 of ``record`` as canonical JSON."""
    text = json.dumps(record, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# ------------------------------------------------------------------ the plan


@dataclass
class Stage:
    """One stage instance: what it computes from which upstream stores."""

    stage: str
    key: str
    # Exactly what was hashed: the stage, its format versions, its own parameters
    # (``record["params"]``) and its inputs' keys. Stage functions take it whole and
    # store it in their output's attributes.
    record: dict
    inputs: dict[str, tuple[str, str]]  # input name -> (stage, key)
    # Not hashed: device, batch size, whether the stage runs on a GPU when there is one.
    run_params: dict = field(default_factory=dict)
    dataset: str = ""
    # Files the stage reads besides stores (a published vocabulary), by input name: their
    # content is in the record (a pinned hash), the file is fetched by its own rule.
    files: dict[str, str] = field(default_factory=dict)

    @property
    def path(self) -> str:
        return store_path(self.stage, self.key)

    def input_paths(self) -> dict[str, str]:
        return {name: store_path(*ref) for name, ref in self.inputs.items()} | self.files


@dataclass
class MethodRun:
    """One row of a results table: a method on a dataset."""

    method: str
    recall_key: str
    row_params: dict  # flattened parameters for the CSV
    aggregator_name: str
    reranked: bool = False  # a method's retrieval re-ranked: "<method>+<reranker>"

    @property
    def figures(self) -> tuple[str, ...]:
        """The report's figures of this method: its retrievals, and its aggregator's
        explanation when it has one (the retrieval's row shows it, not the re-ranked)."""
        explanation = not self.reranked and aggregator(self.aggregator_name).explanation
        return ("retrievals", explanation) if explanation else ("retrievals",)


@dataclass
class Plan:
    stages: dict[str, dict[str, Stage]] = field(default_factory=dict)
    runs: dict[str, list[MethodRun]] = field(default_factory=dict)  # dataset -> rows
    dataset_keys: dict[str, str] = field(default_factory=dict)  # the truth stores
    images_keys: dict[str, str] = field(default_factory=dict)
    has_ground_truth: dict[str, bool] = field(default_factory=dict)
    # The image lists the dataset keys were made from (absent: not listable), so the
    # workflow does not list 10^5 files a second time for shard ranges.
    dataset_files: dict[str, DatasetFiles] = field(default_factory=dict)
    # Every trained model's checkpoint file the plan reads, by path.
    checkpoints: dict[str, PlannedCheckpoint] = field(default_factory=dict)
    # Set when checkpoints are missing and the plan was built all the same (to fetch
    # them): the stages that read one have no key of their contents, so none is built.
    checkpoint_error: str | None = None

    def add(
        self,
        stage: str,
        params: dict,
        inputs: dict[str, tuple[str, str]],
        dataset: str,
        run_params: dict | None = None,
        files: dict[str, str] | None = None,
    ) -> str:
        record = {
            "stage": stage,
            "version": STAGES[stage].version,
            "store_format": 2,  # 2: crc32c checksums on every chunk
            "params": params,
            "inputs": {name: key for name, (_, key) in sorted(inputs.items())},
        }
        # Keys sorted at every depth: Snakemake's params trigger compares the record's
        # repr, so the order of a config's keys must not rerun a job its key keeps.
        record = json.loads(json.dumps(record, sort_keys=True))
        key = content_key(record)
        self.stages.setdefault(stage, {})[key] = Stage(
            stage, key, record, inputs, run_params or {}, dataset, files or {}
        )
        return key

    def get(self, stage: str, key: str) -> Stage:
        if self.checkpoint_error:
            raise PlanError(self.checkpoint_error)
        try:
            return self.stages[stage][key]
        except KeyError:
            raise PlanError(
                f"no {stage} stage with key {key} in the current config "
                f"(stale target? keys change whenever parameters do)"
            ) from None


def method_run(plan: Plan, dataset: str, method: str) -> MethodRun:
    """The row of ``method`` in ``dataset``'s table; an unknown dataset or method is
    named, with the ones there are."""
    if dataset not in plan.runs:
        raise PlanError(f"no dataset named {dataset!r}; the datasets are: {sorted(plan.runs)}")
    runs = {run.method: run for run in plan.runs[dataset]}
    if method not in runs:
        raise PlanError(f"no method {method!r} on dataset {dataset!r}; its methods: {sorted(runs)}")
    return runs[method]


def method_stores(plan: Plan, dataset: str, method: str) -> dict[str, str]:
    """The stores of one method on one dataset by name: ``images``, ``dataset`` (the
    ground truth), ``features``,
    ``descriptors``, ``recall`` and, as the method has them, ``segments``,
    ``vocabulary``, ``pca``, ``search``."""
    recall = plan.get("recall", method_run(plan, dataset, method).recall_key)
    descriptors = plan.get(*recall.inputs["descriptors"])
    return {**descriptors.input_paths(), **recall.input_paths(), "recall": recall.path}


# ------------------------------------------------------------------ planning

# What a method inherits: its backbone and segmenter entry names, then the sections.
METHOD_SECTIONS = ("features", "segmenter", *METHOD_DEFAULT_SECTIONS)


def resolve_method(config: dict, name: str, dataset: dict | None = None) -> dict:
    """A method's settings: top-level defaults, then the dataset's ``defaults``, then
    the method's own overrides (later wins, dictionaries merge key by key)."""
    if name not in config["methods"]:
        raise PlanError(f"unknown method {name!r}; defined methods: {sorted(config['methods'])}")
    settings = {section: config[section] for section in METHOD_SECTIONS}
    settings = deep_merge(settings, (dataset or {}).get("defaults", {}))
    return deep_merge(settings, config["methods"][name])


def deep_merge(base: dict, override: dict) -> dict:
    merged = copy.deepcopy(base)
    for name, value in override.items():
        if isinstance(value, dict) and isinstance(merged.get(name), dict):
            merged[name] = deep_merge(merged[name], value)
        else:
            merged[name] = copy.deepcopy(value)
    return merged


def build_plan(
    config: dict,
    memo: dict | None = None,
    allow_missing_checkpoints: bool = False,
    configfiles=(),
) -> Plan:
    """Every stage of every (dataset, method) pair in ``config``; shared stages dedupe.

    ``memo`` caches content hashes of local model weights and imported files across
    runs (see :func:`vprflow.planning.fingerprints.source_fingerprint`); pass a dict loaded from
    disk to reuse it. Trained models' checkpoint files that do not exist are one
    PlanError naming them all (:mod:`vprflow.planning.checkpoints`; ``configfiles`` go
    into the fetch command it gives); with ``allow_missing_checkpoints`` the plan is
    built to fetch them, and any stage asked of it raises that error.
    """
    memo = {} if memo is None else memo
    plan = Plan()
    # Native resolutions become sizes here; the caller's config stays as given.
    config = {**config, "datasets": dict(config["datasets"])}
    for dataset_name, dataset in sorted(config["datasets"].items()):
        images_key, dataset_key = _plan_dataset(plan, config, dataset_name, dataset, memo)
        dataset = config["datasets"][dataset_name]
        plan.images_keys[dataset_name] = images_key
        plan.dataset_keys[dataset_name] = dataset_key
        plan.has_ground_truth[dataset_name] = dataset["ground_truth"]["kind"] != "none"
        plan.runs[dataset_name] = []
        for method_name in dataset["methods"]:
            plan.runs[dataset_name] += _plan_method(
                plan, config, memo, dataset_name, (images_key, dataset_key), method_name
            )
        # A preset re-ranks methods a config may drop from its list: only a name that
        # is no method at all is a mistake.
        unknown = sorted(set(dataset["rerank"]) - set(config["methods"]))
        if unknown:
            raise PlanError(
                f"datasets.{dataset_name}.rerank names {unknown}, which are not defined "
                f"under methods: {sorted(config['methods'])}"
            )
    missing = [c for c in plan.checkpoints.values() if absent(c.path)]
    if missing:
        plan.checkpoint_error = missing_message(missing, configfiles)
        if not allow_missing_checkpoints:
            raise PlanError(plan.checkpoint_error)
    return plan


def _plan_dataset(
    plan: Plan, config: dict, name: str, dataset: dict, memo: dict
) -> tuple[str, str]:
    """The keys of a dataset's two stores: ``images`` (what the images are) and
    ``dataset`` (its ground truth, over the images store)."""
    images, truth, files = dataset_contents(config["data_root"], name, dataset, memo)
    if files is not None:
        plan.dataset_files[name] = files
    params = {
        "name": name,
        **{k: v for k, v in dataset.items() if k not in IMAGES_EXCLUDED},
        # What the images hold, not where they are: replaced images rebuild everything,
        # a moved or re-mounted data folder rebuilds nothing.
        "contents": images,
    }
    listing = listing_truth(dataset["ground_truth"])
    if listing:  # MSLS: its published lists pick the images
        params["ground_truth"] = listing
    if dataset["resolution"] == "native" and files is not None:
        # Later stages are keyed by the size itself; the images stage checks that
        # every image has it (the first image stands for all at planning time).
        try:
            first = (files.reference + files.query)[0]
            size = list(image_size(first, dataset_orientation(dataset["exif_orientation"])))
        except ImageReadError:
            size = None  # the images stage decodes every image and names this one
        if size is not None:
            params["native_size"] = size
            config["datasets"][name] = {**dataset, "resolution": size}
    images_key = plan.add("images", params, {}, name)
    truth_params = {
        **{k: dataset[k] for k in TRUTH_SETTINGS},
        # What the ground-truth files hold (the images are the images store's).
        "contents": truth,
    }
    return images_key, plan.add("dataset", truth_params, {"images": ("images", images_key)}, name)


# Kept out of the images store's key: the truth store's settings and those of neither.
IMAGES_EXCLUDED = TRUTH_SETTINGS + NOT_DATASET_STAGE


_StoreRef = tuple[str, str]  # (stage, key)


@dataclass
class _Method:
    """One method on one dataset while its stages are planned: what every stage's
    planner reads, and where it adds its stage."""

    plan: Plan
    config: dict
    memo: dict
    dataset_name: str
    dataset: dict
    images_store: _StoreRef  # what the images are: the model stages' input
    dataset_store: _StoreRef  # the ground truth: recall's input
    name: str
    settings: dict  # resolved: see resolve_method
    aggregator: Aggregator
    options: dict  # the descriptor stage's own settings (Aggregator.options)

    def add(
        self, stage: str, params: dict, inputs: dict[str, _StoreRef], run_params: dict | None = None
    ) -> _StoreRef:
        return (stage, self.plan.add(stage, params, inputs, self.dataset_name, run_params))

    def entry(self, section: str, name: str) -> dict:
        """The ``backbones`` or ``segmenters`` entry ``name`` the method uses."""
        if name not in self.config[section]:
            raise PlanError(
                f"method {self.name!r} uses {name!r}, which is not defined under {section}: "
                f"{sorted(self.config[section])}"
            )
        return self.config[section][name]

    @property
    def execution(self) -> dict:
        """How stages run, not what they compute (not hashed)."""
        return {"device": self.config["device"]}

    def model_run_params(self, stage: str, entry: dict) -> dict:
        """Run settings of a stage that runs a backbone or segmenter ``entry``."""
        return {
            **self.execution,
            "batch_size": entry["batch_size"],
            "uses_gpu": model_kind(stage, entry).uses_gpu,
        }


def _plan_method(
    plan: Plan,
    config: dict,
    memo: dict,
    dataset_name: str,
    keys: tuple[str, str],
    method_name: str,
) -> list[MethodRun]:
    """Plan one method's stages (as its aggregator's entry needs them) and its CSV rows:
    features, the stages its aggregator needs, descriptors, then recall (through the
    segment search for a per-segment method), and a re-ranked row per re-ranker the
    dataset names for it. Each stage's planner returns its store and its CSV columns."""
    dataset = config["datasets"][dataset_name]
    settings = resolve_method(config, method_name, dataset)
    agg = aggregator(settings["aggregator"])
    m = _Method(
        plan,
        config,
        memo,
        dataset_name,
        dataset,
        ("images", keys[0]),
        ("dataset", keys[1]),
        method_name,
        settings,
        agg,
        agg.options(settings),
    )
    features, columns = _plan_features(m)
    row = {"aggregator": agg.name, **columns}
    if "protocol" in dataset:  # a preset's (config.validate_config)
        row["protocol"] = dataset["protocol"]
    inputs = {"images": m.images_store, "features": features}
    for stage in agg.needs:
        spec = STAGES.get(stage)
        if spec is None or spec.needed is None:  # an aggregator the table does not back
            raise PlanError(f"aggregator {agg.name!r} needs unknown stage {stage!r}")
        store, columns = spec.needed(m, inputs)
        if store is not None:
            inputs[stage] = store
        row.update(columns)
    row.update(agg.columns(settings))
    descriptors = m.add("descriptors", {"aggregator": agg.name, **m.options}, inputs)
    retrieval, recall_params, columns = _plan_retrieval(m, descriptors)
    row.update(columns)
    recall_key = m.add("recall", recall_params, {**retrieval, "dataset": m.dataset_store})[1]
    runs = [MethodRun(method_name, recall_key, _flat(row), agg.name)]
    # What a re-ranker re-orders; an approximate search's exact twin is the retrieval row's.
    used = {k: v for k, v in retrieval.items() if k != "exact_search"}
    for reranker in dataset["rerank"].get(method_name, []):
        rerank, columns = _plan_rerank(m, used, recall_params, reranker)
        recall_key = m.add(
            "recall", recall_params, {**used, "dataset": m.dataset_store, "rerank": rerank}
        )[1]
        runs.append(
            MethodRun(
                f"{method_name}+{reranker}",
                recall_key,
                _flat({**row, **columns}),
                agg.name,
                reranked=True,
            )
        )
    return runs


def _plan_features(
    m: _Method, name: str | None = None, reranker: str | None = None
) -> tuple[_StoreRef, dict]:
    """The features store of backbone entry ``name`` (default: the method's), which
    must hold what its reader takes: the method's aggregator, or re-ranker ``reranker``
    (dense features)."""
    name = name or m.settings["features"]
    backbone = m.entry("backbones", name)
    kind = model_kind("features", backbone)
    _check_output(m, name, backbone, reranker)
    if backbone["resize"] == "method":
        # The published pipeline's reader: one backbone entry serves SegVLAD (OpenCV)
        # and SNSM (PIL) faithfully, as two features stores; a trained model's own
        # descriptor, its own pipeline's.
        resize = m.aggregator.resize
        if isinstance(kind.spec, TrainedModel) and backbone["output"] == "descriptor":
            resize = kind.spec.resize
        backbone = {**backbone, "resize": resize}
    if isinstance(kind.spec, TrainedModel):
        weights = _trained_weights(m, name, backbone, kind.spec)
    else:
        weights = source_fingerprint("features", backbone, m.memo, f"backbones.{name}")
    params = {
        **_hashed(backbone),
        **weights,
        "resolution": _resolution(m.dataset, backbone),
        "exif_orientation": _exif_orientation(m),
    }
    params.update(_kind_version(kind))
    patch = backbone.get("patch_size")
    if isinstance(kind.spec, TrainedModel):
        strides = kind.spec.layer_strides
        patch = strides[backbone["layer"]] if strides else kind.spec.patch_size
        patch = patch if backbone["output"] == "features" else None
    sized = isinstance(params["resolution"], list)  # not native, nor each image's own
    if patch and sized and min(params["resolution"]) < patch:
        where = (
            f"datasets.{m.dataset_name}.resolution"
            if backbone["resolution"] == "dataset"
            else f"backbones.{name}.resolution"
        )
        raise PlanError(
            f"config key {where} = {params['resolution']} is smaller than one "
            f"{patch}-pixel patch of backbone {name!r}"
        )
    run_params = m.model_run_params("features", backbone)
    store = m.add("features", params, {"images": m.images_store}, run_params)
    return store, {"features": name, **_prefixed("features", backbone)}


def _output(backbone: dict) -> str:
    """What a backbone entry's features store holds: ``"descriptor"`` (a trained
    model's own, 1 x 1 x D per image) or ``"features"`` (a dense patch grid)."""
    return backbone.get("output", "features")


def _check_output(m: _Method, name: str, backbone: dict, reranker: str | None) -> None:
    """Refuse a backbone entry whose store is not what its reader takes: the ``model``
    aggregator over dense features, or a dense aggregator (or a re-ranker) over a
    trained model's descriptor (``Aggregator.reads``)."""
    reads = "features" if reranker else m.aggregator.reads
    if _output(backbone) == reads:
        return
    kind = backbone["backbone"]
    if reranker:
        reader = f"re-ranker {reranker!r} (rerankers.{reranker}.features, on method {m.name!r})"
    else:
        reader = f"method {m.name!r} (aggregator {m.aggregator.name!r})"
    if reads == "descriptor":
        raise PlanError(
            f"{reader} reads a trained model's own descriptor, but backbone entry {name!r} "
            f"(backbone {kind!r}{', output: features' if 'output' in backbone else ''}) gives "
            f"dense patch features; give the method a backbone entry of a trained kind "
            f"({', '.join(TRAINED_KINDS)}) with output: descriptor, or another aggregator"
        )
    raise PlanError(
        f"{reader} reads dense patch features, but backbone entry {name!r} (backbone "
        f"{kind!r}, output: descriptor) gives one descriptor per image; set "
        f"backbones.{name}.output: features (the map its head reads), or use aggregator "
        "'model' for the model's own descriptor"
    )


def _trained_weights(m: _Method, name: str, backbone: dict, spec: TrainedModel) -> dict:
    """What identifies a trained model's weights: its ``checkpoint`` file's SHA-256.
    An unknown variant, or a checkpoint that is not given or does not exist, is named
    here, at plan time, with the file the variant expects and where to get it."""
    where = f"backbones.{name}"
    variant = backbone["variant"]
    if variant not in spec.variants:
        raise PlanError(
            f"config key {where}.variant = {variant!r}: backbone {backbone['backbone']!r} has "
            f"variants {list(spec.variants)}"
        )
    if backbone["output"] == "descriptor" and not spec.descriptor:
        raise PlanError(
            f"config key {where}.output = 'descriptor': backbone {backbone['backbone']!r} is a "
            f"trunk with no descriptor of its own; it gives output: features ({spec.dense})"
        )
    if spec.layer_strides and backbone["layer"] not in spec.layer_strides:
        raise PlanError(
            f"config key {where}.layer = {backbone['layer']!r}: backbone "
            f"{backbone['backbone']!r} has layers {list(spec.layer_strides)}"
        )
    published = spec.variants[variant]
    hint = (
        f"backbone {backbone['backbone']!r} (variant {variant!r}) expects {published.file} "
        f"({published.repository}), from {published.url}"
    )
    path = backbone["checkpoint"]
    if path is None:
        raise PlanError(f"config key {where}.checkpoint is not set: {hint}")
    m.plan.checkpoints.setdefault(
        path,
        PlannedCheckpoint(path, f"{where}.checkpoint", backbone["backbone"], variant, published),
    )
    if absent(path):  # named with every other missing or empty one, after planning
        return {"checkpoint_sha256": None}
    try:
        return {"checkpoint_sha256": memoised(path, m.memo, file_digest, f"{where}.checkpoint")}
    except PlanError as error:
        raise PlanError(f"{error}; {hint}") from None


def _exif_orientation(m: _Method) -> str:
    """How the method's stages read images: the dataset's ``exif_orientation``, or for
    ``method`` (the default) as the published pipeline's reader does (its aggregator's
    ``Aggregator.exif_orientation``), as ``resize: method`` resizes."""
    orientation = m.dataset["exif_orientation"]
    return m.aggregator.exif_orientation if orientation == "method" else orientation


def _kind_version(kind) -> dict:
    """A model kind's format version for its stores' params: none while it is 1, so that
    those keys stand as they were before kinds had versions."""
    return {"kind_version": kind.version} if kind.version > 1 else {}


def _plan_segments(m: _Method, inputs: dict[str, _StoreRef]) -> tuple[_StoreRef, dict]:
    name = m.settings["segmenter"]
    segmenter = m.entry("segmenters", name)
    if segmenter.get("masks_layout") == PACKED:  # the stores before the option: their keys
        segmenter = {k: v for k, v in segmenter.items() if k != "masks_layout"}
    params = {
        **_hashed(segmenter),
        **source_fingerprint("segments", segmenter, m.memo, f"segmenters.{name}"),
        "resolution": _segment_resolution(m.dataset, segmenter),
        "exif_orientation": _exif_orientation(m),  # as its features: masks on the same pixels
        **_kind_version(model_kind("segments", segmenter)),
    }
    run_params = m.model_run_params("segments", segmenter)
    store = m.add("segments", params, {"images": m.images_store}, run_params)
    return store, {"segmenter": name, **_prefixed("segmenter", segmenter)}


def _plan_vocabulary(m: _Method, inputs: dict[str, _StoreRef]) -> tuple[_StoreRef, dict]:
    vocabulary = m.settings["vocabulary"]
    stores = {"images": m.images_store, "features": inputs["features"]}
    if vocabulary["source"] == "published":
        # The centres are the file's: nothing else of the section shapes them.
        name = vocabulary.get("name")
        if name not in PUBLISHED_VOCABULARIES:
            raise PlanError(
                f"method {m.name!r}: vocabulary source 'published' needs a `name`, one of "
                f"{sorted(PUBLISHED_VOCABULARIES)}"
            )
        params = {
            "source": "published",
            "name": name,
            "sha256": PUBLISHED_VOCABULARIES[name].sha256,
        }
        files = {"centres": PUBLISHED_VOCABULARY.format(name=name)}
        store = (
            "vocabulary",
            m.plan.add("vocabulary", params, stores, m.dataset_name, files=files),
        )
        return store, {"vocabulary.source": "published", "vocabulary.name": name}
    params = {k: v for k, v in vocabulary.items() if k not in ("file", "name")}
    if vocabulary["source"] == "file":
        params.update(
            file=vocabulary["file"],
            sha256=memoised(vocabulary["file"], m.memo, file_digest, "vocabulary.file"),
        )
    # Fitting k-means to a model's wide features is GPU work, as matching them is.
    backbone = m.entry("backbones", m.settings["features"])
    fitted = vocabulary["source"] == "map"
    if fitted and m.aggregator.vocabulary_input is not None:
        # The patches as the aggregator's VLAD sees them (SNSM's baseline: channel-normalised).
        params.update(m.aggregator.vocabulary_input(m.settings))
    run_params = {**m.execution, "uses_gpu": fitted and model_kind("features", backbone).uses_gpu}
    store = m.add("vocabulary", params, stores, run_params)
    return store, _prefixed("vocabulary", {k: v for k, v in vocabulary.items() if k != "name"})


def _plan_pca(m: _Method, inputs: dict[str, _StoreRef]) -> tuple[_StoreRef | None, dict]:
    """The PCA of the method's descriptors, fitted on every input planned so far; none
    when the method disables it."""
    pca = m.settings["pca"]
    if not pca["enabled"]:
        return None, {"pca.enabled": False}
    params = {
        # fit_order is read by the aggregator into fit_on: `method` and the
        # order it resolves to are one PCA.
        **{k: v for k, v in pca.items() if k not in ("enabled", "fit_order")},
        "aggregator": m.aggregator.name,
        # What the PCA is fitted on, as the aggregator says (SegVLAD: one PCA
        # per neighbourhood order).
        "fit_on": m.aggregator.pca_descriptor_options(m.settings, m.options),
    }
    return m.add("pca", params, dict(inputs)), _prefixed("pca", pca)


def _plan_retrieval(m: _Method, descriptors: _StoreRef) -> tuple[dict[str, _StoreRef], dict, dict]:
    """What ranks the references for each query, for recall and re-ranking alike: the
    inputs (descriptors; and the segment search a per-segment method votes over), the
    recall stage's params, and the CSV columns. Recall adds the truth store, a re-ranker
    the images store."""
    inputs = {"descriptors": descriptors}
    params = {
        "recall_at": m.dataset["recall_at"],
        "denominator": m.dataset["denominator"],
        # How deep the ranking goes: its deepest Recall@N, at least 20.
        "depth": max(max(m.dataset["recall_at"]), 20),
    }
    columns: dict = {}
    if m.aggregator.output == "segments":
        searches, columns = _plan_search(m, descriptors)
        inputs.update(searches)
        params["vote_ranking"] = m.settings["voting"]["vote_ranking"]
    return inputs, params, columns


def _plan_rerank(
    m: _Method, retrieval: dict[str, _StoreRef], recall_params: dict, name: str
) -> tuple[_StoreRef, dict]:
    """The ``rerank`` stage of re-ranker entry ``name`` over the method's ``retrieval``
    stores (without an exact twin), and the re-ranked row's extra CSV columns. Its
    ``matches`` store (:func:`_plan_matches`) is every re-ranker's of the method with the
    same features and ``top_k``; the ``rerank`` stage itself only scores them."""
    if name not in m.config["rerankers"]:
        raise PlanError(
            f"datasets.{m.dataset_name}.rerank: {m.name!r} names re-ranker {name!r}, which "
            f"is not defined under rerankers: {sorted(m.config['rerankers'])}"
        )
    entry = m.config["rerankers"][name]
    if entry["features"] not in m.config["backbones"]:
        raise PlanError(
            f"config key rerankers.{name}.features = {entry['features']!r} names no entry "
            f"under backbones: {sorted(m.config['backbones'])} (re-ranker {name!r}, which "
            f"datasets.{m.dataset_name}.rerank applies to method {m.name!r})"
        )
    matches = _plan_matches(m, retrieval, recall_params, entry, name)
    params = {
        "kind": entry["kind"],
        "options": {k: entry[k] for k in RERANKERS[entry["kind"]].options},
    }
    # Scoring stored pairs (counts, sums, RANSAC fits) is CPU work.
    store = m.add("rerank", params, {"matches": matches}, {**m.execution, "uses_gpu": False})
    return store, {"reranker": name, **_prefixed("rerank", entry)}


def _plan_matches(
    m: _Method, retrieval: dict[str, _StoreRef], recall_params: dict, entry: dict, name: str
) -> _StoreRef:
    """The ``matches`` stage of re-ranker entry ``entry`` (named ``name``): exactly what
    decides the candidates and their patch pairs (the retrieval, the features, ``top_k``,
    the depth), not the re-ranker's kind or options, so two re-rankers of one method on
    the same features and ``top_k`` share it."""
    features, _ = _plan_features(m, entry["features"], reranker=name)
    params = {
        "top_k": entry["top_k"],
        # As deep as the recall's ranking: the rest of the retrieval follows the
        # re-ranked top K, so Recall@N beyond top_k is the retrieval's, not truncated.
        "depth": recall_params["depth"],
    }
    if "vote_ranking" in recall_params:
        params["vote_ranking"] = recall_params["vote_ranking"]
    # Matching a model's wide features is GPU work; DAISY's (~100-d) is not worth asking
    # a cluster for a GPU (the stage still uses one when `device` finds it).
    backbone = m.entry("backbones", entry["features"])
    run_params = {**m.execution, "uses_gpu": model_kind("features", backbone).uses_gpu}
    inputs = {**retrieval, "images": m.images_store, "features": features}
    return m.add("matches", params, inputs, run_params)


def _plan_search(m: _Method, descriptors: _StoreRef) -> tuple[dict[str, _StoreRef], dict]:
    """The segment searches a per-segment method's recall votes over, by recall input
    name, and the retrieval and voting CSV columns."""
    # The index's parameter defaults, filled only now: the index and its params may
    # each come from another level of the merge.
    try:
        retrieval = search_settings(m.settings["retrieval"])
    except ValueError as error:
        raise PlanError(f"method {m.name!r}: {error}") from None
    voting = m.settings["voting"]

    def search(settings: dict) -> _StoreRef:
        params = {"top_segments": voting["top_segments"], **settings}
        run_params = {**m.execution, "uses_gpu": SEARCH_INDEXES[settings["index"]].uses_gpu}
        return m.add(
            "search", params, {"images": m.images_store, "descriptors": descriptors}, run_params
        )

    searches = {"search": search(retrieval)}
    if not SEARCH_INDEXES[retrieval["index"]].exact:
        # The table states what the approximation costs: recall of an exact search
        # of the same descriptors, in the same run.
        searches["exact_search"] = search(search_settings({"index": "flat", "params": {}}))
    return searches, {**_prefixed("retrieval", retrieval), **_prefixed("voting", voting)}


def _hashed(params: dict) -> dict:
    return {k: v for k, v in params.items() if k not in EXECUTION_ONLY}


def _resolution(dataset: dict, profile: dict) -> list[int] | str:
    if profile["resolution"] == OWN_SIZE:
        return OWN_SIZE
    if profile["resolution"] != "dataset":
        return list(profile["resolution"])
    if dataset["resolution"] == "native":
        return "native"  # the dataset cannot be listed: its images stage fails first, naming why
    return list(dataset["resolution"])


def _segment_resolution(dataset: dict, segmenter: dict) -> list[int] | str:
    if segmenter.get("resolution") not in (None, "dataset"):
        return list(segmenter["resolution"])
    if dataset["resolution"] == "native":
        return "native"  # as in _resolution
    width, height = dataset["resolution"]
    scale = segmenter["resolution_scale"]
    return [max(1, round(width * scale)), max(1, round(height * scale))]


def _prefixed(prefix: str, section: dict) -> dict:
    return prefixed(prefix, _hashed(section))


def _flat(row: dict) -> dict:
    out: dict = {}
    for name, value in row.items():
        _flatten(name, value, out)
    return out


def _flatten(prefix: str, value, out: dict) -> None:
    if isinstance(value, dict):
        for name in sorted(value):
            _flatten(f"{prefix}.{name}" if prefix else name, value[name], out)
    elif isinstance(value, list):
        out[prefix] = " ".join(str(v) for v in value)
    else:
        out[prefix] = value


# ------------------------------------------------------------------ the stages

# (method, inputs planned so far) -> (its store or None, CSV columns)
_NeededPlanner = Callable[[_Method, dict[str, _StoreRef]], tuple[_StoreRef | None, dict]]


@dataclass(frozen=True)
class StageSpec:
    """One stage of the workflow, as the plan, the rules and their script know it."""

    # The format version, in every key of the stage: bump it when what the stage writes
    # changes (reasons below, by stage).
    version: int
    # Whose ranges the stage's jobs take: "images" (references then queries) or
    # "references"; None: one job. A sharded stage's rule writes shards; its `gather`
    # rule combines them (vprflow.stages.jobs.combine_shards).
    shards: Literal["images", "references"] | None = None
    # The top-level config key that holds a sharded stage's images a job (0: one job).
    shard_size: str | None = None
    # For a stage an aggregator may need (``Aggregator.needs``): how it is planned,
    # between the features and the descriptors.
    needed: _NeededPlanner | None = None


# Every stage, in the order a query's data flows through them (the rerun table's order).
# Each comment says what the stage stores and what its current format version stands
# for; the history of each bump is in git.
STAGES: dict[str, StageSpec] = {
    # What the images are: their list, order, paths, sizes, SHA-256 and how they are
    # read. Its own store, so that no ground-truth setting reaches a model stage's key.
    "images": StageSpec(1),
    # What is true about them: the ground truth over the images store, with its arrays
    # copied; keyed by the images store's key, the ground-truth settings and files.
    "dataset": StageSpec(3),
    # Patch features after the published reader's resize (crop offsets rounded as
    # torchvision, position embeddings interpolated as the authors do).
    "features": StageSpec(3, shards="images", shard_size="shard_size"),
    # Masks after the published (OpenCV INTER_LINEAR) resize; SAM's prompts decoded by
    # models/sam/decoder.py, SAM-HQ's masks upscaled from its transformer's output.
    "segments": StageSpec(3, shards="images", shard_size="shard_size", needed=_plan_segments),
    # VLAD centres (plain cluster means by default) from vprflow's k-means, decided in
    # float64 with a fixed tie order and summed in a fixed order: one result on every CPU.
    "vocabulary": StageSpec(4, needed=_plan_vocabulary),
    # The exact solver by default, capped at the numerical rank, over VLAD whose patches
    # are normalised and assigned as the authors' torch code does (ties go their way).
    "pca": StageSpec(4, needed=_plan_pca),
    # VLAD sums in numpy, one BLAS thread per image, with the input norm and the
    # backbone's crop offsets; patches normalised and assigned to centres in torch on the
    # authors' layout and shapes, so float32 ties go where their code sends them. Jobs of
    # their own size: each imports torch (~1.2 s), ~1 ms of work an image at the shipped
    # settings.
    "descriptors": StageSpec(5, shards="images", shard_size="descriptors_shard_size"),
    # Each query segment's nearest reference segments, a range of reference images per
    # job; the shards' top-k lists are merged, not concatenated.
    "search": StageSpec(1, shards="references", shard_size="search_shard_size"),
    # Each re-ranked candidate's mutual nearest neighbour patch pairs, computed once for
    # all the re-rankers of a method on the same features and top_k.
    "matches": StageSpec(1),
    # A re-ranker's scores from a matches store's pairs: the top K re-ordered, then the
    # rest of the retrieval to the recall's depth.
    "rerank": StageSpec(3),
    # The ranking (the published vote ranking for segments), its scores (a global
    # method's: each ranked pair's distance in float64, the same on every machine),
    # Recall@N, mAP, the precision-recall summary, the cost per query and the queries
    # without a positive; its record names the ranking's depth `depth` (it was `top_k`,
    # which names only a re-ranker's K).
    "recall": StageSpec(8),
}

# The table by column: what the keys hash, and the stages run in shards.
FORMAT_VERSIONS = {name: stage.version for name, stage in STAGES.items()}
SHARDED = tuple(name for name, stage in STAGES.items() if stage.shards)

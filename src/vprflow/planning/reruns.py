"""What a change reruns: for each dataset and method setting, the stages whose keys the
change gives a new value, computed from the plan (no Snakemake, no model).

A stage reruns exactly when the plan after the change holds a key of it that the plan
before did not (``results/cache/<stage>/<key>.zarr`` does not exist yet). The table is
docs/usage.md's "What a change reruns" (``python scripts/write_reruns_doc.py``), and
``tests/planning/test_reruns.py`` checks both the doc and the expected rows: a ground-truth
change reruns the truth store and recall, never a model stage.
"""

from __future__ import annotations

import copy
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from vprflow.planning.config import validate_config
from vprflow.planning.plan import STAGES, build_plan

# The toy's images: references and queries of the same names, so `paired` may pair them.
N_IMAGES = 4
# The stages whose outputs come from a model, a fit or a search over them (hours of GPU
# time on DINOv2-G and SAM-H): every stage but the dataset's two stores and recall, so a
# new stage is one unless it says otherwise. No ground-truth setting may rerun one.
FITTED_STAGES = tuple(s for s in STAGES if s not in ("images", "dataset", "recall"))


def _write_image(path: Path, seed: int) -> None:
    pixels = np.random.default_rng(seed).integers(0, 256, (24, 32, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(path)


def _write_truth(path: Path, radius: int = 0) -> None:
    rows = np.empty((N_IMAGES, 2), dtype=object)
    for q in range(N_IMAGES):
        rows[q] = [q, [r for r in range(N_IMAGES) if abs(r - q) <= radius]]
    np.save(path, rows, allow_pickle=True)


def make_toy(folder: Path) -> Path:
    """``folder/ref/000i.png``, ``folder/query/000i.png`` and a VPR-Bench
    ``ground_truth_new.npy``: the smallest dataset every setting below applies to."""
    for role, offset in (("ref", 0), ("query", 100)):
        (folder / role).mkdir(parents=True, exist_ok=True)
        for i in range(N_IMAGES):
            _write_image(folder / role / f"{i:04d}.png", offset + i)
    _write_truth(folder / "ground_truth_new.npy")
    return folder


def toy_config(shipped: dict, data_root: Path) -> dict:
    """The shipped config with its first dataset's settings and methods (every stage:
    SegVLAD's segments, vocabulary, PCA and segment search; re-rankers) over the toy."""
    config = copy.deepcopy(shipped)
    name = next(iter(config["datasets"]))
    entry = {k: v for k, v in config["datasets"][name].items() if k not in ("download",)}
    entry.update(path="toy", reference="ref", query="query")
    entry["ground_truth"] = {"kind": "vprbench", "file": "ground_truth_new.npy"}
    config.update(data_root=str(data_root), datasets={"toy": entry}, targets=["toy"])
    return config


Edit = Callable[[dict, Path], None]  # (the toy's config entry, its folder) -> None


def _nothing(dataset: dict, folder: Path) -> None:
    pass


@dataclass(frozen=True)
class Change:
    """One row: ``setting`` changed as ``change`` says, by ``edit`` (of the config's
    top level when ``top``, else of the toy's dataset entry; files under its folder),
    from the starting point ``start`` sets (default: the toy as made)."""

    setting: str
    change: str
    edit: Edit
    start: Edit = _nothing
    top: bool = False
    note: str = field(default="", compare=False)


EXECUTION = "how a job runs, not what it computes: nothing reruns"


def _set(*path, value) -> Edit:
    def edit(section: dict, folder: Path) -> None:
        for name in path[:-1]:
            section = section.setdefault(name, {})
        section[path[-1]] = copy.deepcopy(value)

    return edit


def _both(*edits: Edit) -> Edit:
    def edit(section: dict, folder: Path) -> None:
        for one in edits:
            one(section, folder)

    return edit


def _rewrite_truth(dataset: dict, folder: Path) -> None:
    _write_truth(folder / "ground_truth_new.npy", radius=1)


def _replace_image(dataset: dict, folder: Path) -> None:
    _write_image(folder / "query" / "0001.png", 999)


def _move(dataset: dict, folder: Path) -> None:
    pass  # the config's data_root is moved by changed_stages itself


_FRAMES = _set("ground_truth", value={"kind": "frame_window", "radius": 2})
_NONE = _set("ground_truth", value={"kind": "none"})
_PAIRED = _set("paired", value=True)

CHANGES: tuple[Change, ...] = (
    # What is true about the images: the truth store and recall only.
    Change(
        "ground_truth.radius (frame_window)",
        "2 -> 3",
        _set("ground_truth", "radius", value=3),
        _FRAMES,
    ),
    Change("ground_truth.kind", "vprbench -> frame_window", _FRAMES),
    Change(
        "ground_truth.kind (paired: true)",
        "none -> pairs",
        _set("ground_truth", value={"kind": "pairs"}),
        _both(_PAIRED, _NONE),
    ),
    Change("ground_truth.file's content", "rewritten", _rewrite_truth),
    Change(
        "ground_truth.drop_out_of_range",
        "false -> true",
        _set("ground_truth", "drop_out_of_range", value=True),
    ),
    Change("denominator", "with_positives -> all", _set("denominator", value="all")),
    Change(
        "recall_at (within the top 20)", "[1, 5, 10, 20] -> [1, 5]", _set("recall_at", value=[1, 5])
    ),
    Change(
        "recall_at (past 20)",
        "[1, 5, 10, 20] -> [1, 5, 10, 25]",
        _set("recall_at", value=[1, 5, 10, 25]),
    ),
    # What the images are: everything.
    Change("paired", "false -> true", _PAIRED),
    Change("exif_orientation", "method -> ignore", _set("exif_orientation", value="ignore")),
    Change("recursive", "true -> false", _set("recursive", value=False)),
    Change("follow_links", "false -> true", _set("follow_links", value=True)),
    Change("an image's content", "replaced", _replace_image),
    # Read by later stages, or by people only.
    Change("resolution", "[160, 120] -> [128, 96]", _set("resolution", value=[128, 96])),
    Change("source", "changed", _set("source", value="elsewhere")),
    Change("data_root", "moved (the same files)", _move, top=True),
    # Method settings.
    Change(
        "backbones.daisy.radius",
        "12 -> 10",
        _set("backbones", "daisy", "radius", value=10),
        top=True,
    ),
    Change(
        "segmenters.slic.n_segments",
        "40 -> 30",
        _set("segmenters", "slic", "n_segments", value=30),
        top=True,
    ),
    Change(
        "vocabulary.n_clusters", "32 -> 16", _set("vocabulary", "n_clusters", value=16), top=True
    ),
    Change("defaults.pca.dim", "128 -> 64", _set("defaults", "pca", "dim", value=64)),
    Change("voting.top_segments", "50 -> 40", _set("voting", "top_segments", value=40), top=True),
    Change(
        "rerankers.ransac.top_k",
        "100 -> 50",
        _set("rerankers", "ransac", "top_k", value=50),
        top=True,
    ),
    # Scoring alone: the pairs (the matches store) are shared with the other re-rankers.
    Change(
        "rerankers.ransac.threshold",
        "1.5 -> 2.0",
        _set("rerankers", "ransac", "threshold", value=2.0),
        top=True,
    ),
    Change(
        "rerank",
        "mnn_dinov2 added for segvlad",
        _set("rerank", "segvlad", value=["mnn", "ransac", "mnn_dinov2"]),
    ),
    Change(
        "pairs_depth",
        "20 -> 50",
        _set("pairs_depth", value=50),
        top=True,
        note="no key; only the pairs files, which take it, are rewritten",
    ),
    # Execution settings: in no key and in no rule's tracked params, so Snakemake reruns
    # nothing (tests/workflow/test_workflow.py flips each after a finished run).
    Change("device", "auto -> cpu", _set("device", value="cpu"), top=True, note=EXECUTION),
    Change("shard_size", "0 -> 256", _set("shard_size", value=256), top=True, note=EXECUTION),
    Change(
        "descriptors_shard_size",
        "4000 -> 256",
        _set("descriptors_shard_size", value=256),
        top=True,
        note=EXECUTION,
    ),
    Change(
        "search_shard_size",
        "2000 -> 1",
        _set("search_shard_size", value=1),
        top=True,
        note=EXECUTION,
    ),
    Change(
        "backbones.daisy.batch_size",
        "1 -> 4",
        _set("backbones", "daisy", "batch_size", value=4),
        top=True,
        note=EXECUTION,
    ),
)


def _stages(plan) -> dict[str, set[str]]:
    return {stage: set(plan.stages.get(stage, {})) for stage in STAGES}


def changed_stages(change: Change, shipped: dict, schema: Path) -> tuple[str, ...]:
    """The stages (in :data:`vprflow.planning.plan.STAGES` order) that ``change`` reruns on
    the toy: those with a key after it that the plan before it did not have."""
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        make_toy(root / "data" / "toy")
        config = toy_config(shipped, root / "data")
        change.start(config["datasets"]["toy"], root / "data" / "toy")
        before = _stages(build_plan(validate_config(copy.deepcopy(config), schema)))
        if change.edit is _move:
            (root / "data").rename(root / "moved")
            config["data_root"] = str(root / "moved")
        target = config if change.top else config["datasets"]["toy"]
        change.edit(target, Path(config["data_root"]) / "toy")
        after = _stages(build_plan(validate_config(config, schema)))
    return tuple(stage for stage in STAGES if after[stage] - before[stage])


def rerun_table(shipped: dict, schema: Path) -> list[tuple[Change, tuple[str, ...]]]:
    """Every row of :data:`CHANGES` with the stages it reruns."""
    return [(change, changed_stages(change, shipped, schema)) for change in CHANGES]


# Outputs that are no stages (no key): what a rerun stage's store reaches.
READERS = (
    ("recall", "tables, plots, figures, pairs files"),
    ("descriptors", "descriptor exports"),
)
BEGIN = "<!-- rerun table: python scripts/write_reruns_doc.py -->"
END = "<!-- end of the rerun table -->"


def reruns_doc(shipped_config: Path, schema: Path) -> str:
    """The markdown table of docs/usage.md's "What a change reruns" section (between
    :data:`BEGIN` and :data:`END`)."""
    shipped = yaml.safe_load(Path(shipped_config).read_text())
    lines = [
        "| setting | change | stages rerun | and what reads them |",
        "|---|---|---|---|",
    ]
    for change, stages in rerun_table(shipped, schema):
        rerun = ", ".join(f"`{s}`" for s in stages) or "none"
        note = f" ({change.note})" if change.note else ""
        readers = "; ".join(what for stage, what in READERS if stage in stages) or "none"
        lines.append(f"| `{change.setting}` | {change.change} | {rerun}{note} | {readers} |")
    return "\n".join(lines) + "\n"


def with_table(text: str, table: str) -> str:
    """``text`` (docs/usage.md) with the table between :data:`BEGIN` and :data:`END`
    replaced by ``table``."""
    start, end = text.index(BEGIN) + len(BEGIN), text.index(END)
    return text[:start] + "\n" + table + text[end:]

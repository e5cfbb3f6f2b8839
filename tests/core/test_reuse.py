"""Per-image results reused across datasets (vprflow.core.reuse): a dataset sharing
images with one already computed computes only the rest, into stores equal file for
file to a run from scratch, whatever the names, faults or shards."""

from __future__ import annotations

import errno
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from synthetic import make_dataset
from workflow_helpers import toy_config

from vprflow.core import reuse, stores
from vprflow.planning.config import validate_config
from vprflow.planning.plan import build_plan
from vprflow.stages import segments
from vprflow.stages.jobs import Job, combine_shards, run_job
from vprflow.stages.readers import MaskReader, mask_rows, segment_offsets

REPO = Path(__file__).resolve().parents[2]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"
N_PLACES = 4


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    """``base``: 4 places; ``grown``: base plus two new photos, one of base's images
    under a new name (the same bytes) and another of its names holding a new image;
    ``second``: base's references with other queries (a shared database)."""
    root = tmp_path_factory.mktemp("reuse")
    make_dataset(root / "base", n_places=N_PLACES, width=64, height=48)
    make_dataset(root / "other", n_places=3, width=64, height=48, seed=7)
    grown = root / "grown"
    shutil.copytree(root / "base", grown)
    for i in range(2):
        shutil.copy(
            root / "other" / "ref" / f"{i:04d}.png", grown / "ref" / f"{N_PLACES + i:04d}.png"
        )
    shutil.copy(root / "base" / "query" / "0000.jpg", grown / "query" / "0007.jpg")
    shutil.copy(root / "other" / "query" / "0002.jpg", grown / "query" / "0001.jpg")
    shutil.copytree(root / "base" / "ref", root / "second" / "ref")
    shutil.copytree(root / "other" / "query", root / "second" / "query")
    return root


def plan_of(data: Path, *names: str, masks_layout: str | None = None):
    config = toy_config(data, resolution=[64, 48], methods=["segvlad_o0_nopca"])
    if masks_layout is not None:
        config["segmenters"]["slic"]["masks_layout"] = masks_layout
    entry = config["datasets"].pop("toy")
    config["datasets"] = {
        name: {**entry, "path": name, "ground_truth": {"kind": "none"}} for name in names
    }
    config["targets"] = list(names)
    config["segmenters"]["slic"].update(n_segments=6, resolution_scale=1.0)
    return build_plan(validate_config(config, SCHEMA))


def run(plan, stage: str, dataset: str, data: Path, cache: Path, shards=None) -> Path:
    """The ``stage`` store of ``dataset`` built under ``cache`` (its images store too),
    in ``shards`` (image ranges) when given."""
    (key,) = [k for k, s in plan.stages[stage].items() if s.dataset == dataset]
    planned = plan.get(stage, key)
    (images_key,) = [k for k, s in plan.stages["images"].items() if s.dataset == dataset]
    images = cache / "images" / f"{images_key}.zarr"
    if not images.exists():
        run_job(Job(plan.get("images", images_key).record, {}, str(images), data_root=str(data)))
    out = cache / stage / f"{key}.zarr"
    job = Job(planned.record, {"images": str(images)}, str(out), data_root=str(data))
    job = replace(job, run={"device": "cpu", "batch_size": 2})
    if shards is None:
        run_job(job)
        return out
    paths = [f"{out}.shards/{start}-{stop}.zarr" for start, stop in shards]
    for (start, stop), path in zip(shards, paths, strict=True):
        run_job(replace(job, out=path, start=start, stop=stop))
    combine_shards(paths, planned.record, str(out))
    return out


def files_of(store: Path) -> dict[str, bytes]:
    return {
        str(path.relative_to(store)): path.read_bytes()
        for path in sorted(store.rglob("*"))
        if path.is_file() and path.name != ".snakemake_timestamp"
    }


def counts(caplog) -> tuple[int, int]:
    """``(computed, reused)`` of the last job's log line."""
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("images:")]
    computed, reused = re.fullmatch(reuse.IMAGES_PATTERN, lines[-1]).groups()
    return int(computed), int(reused)


@pytest.fixture(scope="module")
def scratch(data, tmp_path_factory):
    """The grown dataset's features and segments stores, each from scratch alone."""
    plan = plan_of(data, "base", "grown")
    cache = tmp_path_factory.mktemp("scratch")
    return {
        stage: run(plan, stage, "grown", data, cache / stage) for stage in ("features", "segments")
    }


@pytest.mark.parametrize("stage", ["features", "segments"])
def test_a_grown_dataset_computes_only_its_new_and_changed_images_into_the_same_store(
    data, scratch, tmp_path, caplog, stage
):
    plan = plan_of(data, "base", "grown")
    caplog.set_level(logging.INFO, logger="vprflow")
    run(plan, stage, "base", data, tmp_path)
    assert counts(caplog) == (2 * N_PLACES, 0)
    grown = run(plan, stage, "grown", data, tmp_path)
    # Two new references, the changed query 0001; the renamed 0007 is base's query 0000.
    assert counts(caplog) == (3, 2 * N_PLACES)
    assert files_of(grown) == files_of(scratch[stage])


def test_reused_features_are_one_file_shared_by_both_stores(data, tmp_path):
    plan = plan_of(data, "base", "grown")
    base = run(plan, "features", "base", data, tmp_path)
    grown = run(plan, "features", "grown", data, tmp_path)
    # Row 6 of grown (its first query) is base's row 4; grown's query 0007 is also it.
    # One file an image, flat in the array's folder (stores.FLAT_CHUNK_KEYS).
    assert os.path.samefile(base / "features/c.4.0.0.0", grown / "features/c.6.0.0.0")
    assert os.path.samefile(base / "features/c.4.0.0.0", grown / "features/c.10.0.0.0")
    assert not os.path.samefile(base / "features/c.5.0.0.0", grown / "features/c.7.0.0.0")


@pytest.mark.parametrize("stage", ["features", "segments"])
def test_a_corrupted_result_is_computed_again_not_used(data, scratch, tmp_path, caplog, stage):
    plan = plan_of(data, "base", "grown")
    base = run(plan, stage, "base", data, tmp_path)
    group = stores.open_store(base)
    chunk = reuse.chunk_file(group["features" if stage == "features" else "masks"].raw, 0)
    damaged = bytearray(chunk.read_bytes())
    damaged[len(damaged) // 2] ^= 0xFF
    chunk.write_bytes(bytes(damaged))
    caplog.set_level(logging.INFO, logger="vprflow")
    grown = run(plan, stage, "grown", data, tmp_path)
    computed, reused = counts(caplog)
    assert computed > 3 and computed + reused == 2 * N_PLACES + 3
    assert files_of(grown) == files_of(scratch[stage])


def test_a_sharded_run_reuses_per_image_and_gathers_the_same_store(data, scratch, tmp_path, caplog):
    plan = plan_of(data, "base", "grown")
    run(plan, "features", "base", data, tmp_path)
    caplog.set_level(logging.INFO, logger="vprflow")
    grown = run(plan, "features", "grown", data, tmp_path, shards=[(0, 4), (4, 8), (8, 11)])
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("images:")]
    assert lines[-3:] == [
        "images: 0 computed, 4 reused",
        "images: 3 computed, 1 reused",
        "images: 0 computed, 3 reused",
    ]
    # The same files as the unsharded store's, but the group's record of its shards.
    gathered, whole = files_of(grown), files_of(scratch["features"])
    assert gathered.keys() == whole.keys()
    assert [k for k in whole if gathered[k] != whole[k]] == ["zarr.json"]
    attrs = stores.open_store(grown).attrs.asdict()
    assert attrs.pop("shards") == [[0, 4], [4, 8], [8, 11]]
    whole_attrs = stores.open_store(scratch["features"]).attrs.asdict()
    assert attrs == {k: v for k, v in whole_attrs.items() if k not in ("start", "stop")}
    assert os.path.samefile(grown / "features/c.10.0.0.0", grown / "features/c.6.0.0.0")


@pytest.mark.parametrize("shards", [None, [(0, 3), (3, 7)], [(0, 7)]])
def test_masks_of_a_shared_database_are_one_file_in_both_stores(
    data, tmp_path, monkeypatch, shards
):
    """A second query set after the same references: each chunk of masks that holds
    references' rows only is the first store's file, unsharded, gathered from shards
    or from one shard; the store is the one a run from scratch writes."""
    monkeypatch.setattr(segments, "CHUNK_ROWS", 4)
    plan = plan_of(data, "base", "second")
    scratch = run(plan, "segments", "second", data, tmp_path / "scratch")
    base = run(plan, "segments", "base", data, tmp_path / "shared")
    second = run(plan, "segments", "second", data, tmp_path / "shared", shards)
    ours, theirs = files_of(second), files_of(scratch)
    assert ours.keys() == theirs.keys()
    # A gathered group's attributes record its shards; nothing else differs.
    assert [k for k in ours if ours[k] != theirs[k]] == ([] if shards is None else ["zarr.json"])
    rows = int(stores.open_store(base)["masks_offsets"][N_PLACES])  # the references'
    shared = [f"masks/c/{c}/0" for c in range(rows // 4)]
    assert len(shared) >= 2
    assert all(os.path.samefile(base / chunk, second / chunk) for chunk in shared)
    after = f"masks/c/{rows // 4 + 1}/0"
    assert (second / after).is_file() and not os.path.samefile(base / after, second / after)


@pytest.mark.parametrize("shards", [None, [(0, 4), (4, 8), (8, 11)]])
def test_per_image_masks_of_every_reused_image_are_its_files_in_both_stores(
    data, scratch, tmp_path, monkeypatch, caplog, shards
):
    """masks_layout per_image: each reused image's chunk files (2 each at 4 masks a file)
    are the base store's, wherever its rows are now, unsharded or gathered; the store is
    the one from scratch, and its masks are the packed store's."""
    monkeypatch.setattr(segments, "IMAGE_CHUNK_ROWS", 4)
    plan = plan_of(data, "base", "grown", masks_layout="per_image")
    alone = run(plan, "segments", "grown", data, tmp_path / "scratch")
    base = run(plan, "segments", "base", data, tmp_path / "shared")
    caplog.set_level(logging.INFO, logger="vprflow")
    grown = run(plan, "segments", "grown", data, tmp_path / "shared", shards)
    if shards is None:
        assert counts(caplog) == (3, 2 * N_PLACES)
    ours, theirs = files_of(grown), files_of(alone)
    assert ours.keys() == theirs.keys()
    assert [k for k in ours if ours[k] != theirs[k]] == ([] if shards is None else ["zarr.json"])
    opened = {store: stores.open_store(store) for store in (base, grown)}
    offsets = {store: mask_rows(group)[0] for store, group in opened.items()}

    def files(store, image: int) -> list[Path]:
        first, stop = offsets[store][image] // 4, offsets[store][image + 1] // 4
        return [reuse.chunk_file(opened[store]["masks"].raw, c) for c in range(first, stop)]

    # grown's references 0-3 are base's 0-3; its queries 0000, 0002, 0003 and 0007 (at
    # 6, 8, 9, 10) base's 4, 6, 7 and 4. Files named c.<i>.0, no folder a chunk.
    assert reuse.chunk_file(opened[base]["masks"].raw, 1).parent == base / "masks"
    for mine, their in [(0, 0), (1, 1), (2, 2), (3, 3), (6, 4), (8, 6), (9, 7), (10, 4)]:
        assert len(files(base, their)) == len(files(grown, mine)) >= 1
        assert all(map(os.path.samefile, files(base, their), files(grown, mine)))
    packed, per_image = stores.open_store(scratch["segments"]), stores.open_store(grown)
    np.testing.assert_array_equal(segment_offsets(packed), segment_offsets(per_image))
    read_packed, read_per_image = MaskReader(packed), MaskReader(per_image)
    for index in range(2 * N_PLACES + 3):
        np.testing.assert_array_equal(read_per_image(index), read_packed(index))


def test_an_unfinished_store_is_never_reused(data, tmp_path, caplog):
    plan = plan_of(data, "base", "grown")
    base = run(plan, "features", "base", data, tmp_path)
    # What a job killed mid-way leaves: its temporary, never renamed into place.
    base.rename(stores.temporary_path(base, "node-1-0badc0de"))
    caplog.set_level(logging.INFO, logger="vprflow")
    run(plan, "features", "grown", data, tmp_path)
    assert counts(caplog) == (2 * N_PLACES + 3, 0)


def test_other_settings_are_not_reused(data, tmp_path, caplog):
    plan = plan_of(data, "base", "grown")
    run(plan, "features", "base", data, tmp_path)
    config = toy_config(data, resolution=[64, 48], methods=["segvlad_o0_nopca"])
    config["datasets"] = {
        "grown": {**config["datasets"]["toy"], "path": "grown", "ground_truth": {"kind": "none"}}
    }
    config["targets"] = ["grown"]
    config["backbones"]["daisy"]["radius"] = 7
    other = build_plan(validate_config(config, SCHEMA))
    caplog.set_level(logging.INFO, logger="vprflow")
    run(other, "features", "grown", data, tmp_path)
    assert counts(caplog) == (2 * N_PLACES + 3, 0)


def test_two_datasets_sharing_images_computed_at_once_each_get_the_scratch_store(
    data, scratch, tmp_path
):
    """Two processes at once: neither finds the other's unfinished store; both stores
    are whole."""
    plan = plan_of(data, "base", "grown")
    script = f"""
import sys
sys.path[:0] = [{str(Path(__file__).parent)!r}, {str(Path(__file__).parents[1])!r}]
from pathlib import Path
from test_reuse import plan_of, run
data = Path({str(data)!r})
run(plan_of(data, "base", "grown"), "features", sys.argv[1], data, Path(sys.argv[2]))
"""
    # Both images stores first, so that neither process builds one the other reads.
    for name in ("base", "grown"):
        (key,) = [k for k, s in plan.stages["images"].items() if s.dataset == name]
        run_job(
            Job(
                plan.get("images", key).record,
                {},
                str(tmp_path / "images" / f"{key}.zarr"),
                data_root=str(data),
            )
        )
    children = [
        subprocess.Popen([sys.executable, "-c", script, name, str(tmp_path)], cwd=REPO)
        for name in ("grown", "base")
    ]
    assert [child.wait(timeout=300) for child in children] == [0, 0]
    (key,) = [k for k, s in plan.stages["features"].items() if s.dataset == "grown"]
    assert files_of(tmp_path / "features" / f"{key}.zarr") == files_of(scratch["features"])
    stores.open_store(tmp_path / "features" / f"{key}.zarr")


def test_skipped_rows_of_a_row_writer_leave_their_chunks_to_the_caller(tmp_path):
    rows = np.arange(5 * 6, dtype=np.float32).reshape(5, 2, 3) + 1
    with stores.atomic_store(tmp_path / "whole.zarr") as group:
        writer = stores.RowWriter(group, "x", (2, 3), np.float32, 1, stores.CHECKSUM_ONLY)
        writer.append(rows)
        writer.close()
    with stores.atomic_store(tmp_path / "gaps.zarr") as group:
        writer = stores.RowWriter(group, "x", (2, 3), np.float32, 1, stores.CHECKSUM_ONLY)
        writer.append(rows[:1])
        writer.skip(2)
        writer.append(rows[3:])
        for index in (1, 2):
            target = reuse.chunk_file(writer.array, index)
            assert reuse.link_chunk(tmp_path / f"whole.zarr/x/c/{index}/0/0", target, 24)
        writer.close()
    assert files_of(tmp_path / "gaps.zarr") == files_of(tmp_path / "whole.zarr")


def test_a_chunk_that_fails_its_checksum_or_size_is_not_linked(tmp_path):
    good = np.arange(6, dtype=np.float32).tobytes()
    import google_crc32c

    source = tmp_path / "chunk"
    source.write_bytes(good + google_crc32c.value(good).to_bytes(4, "little"))
    assert reuse.link_chunk(source, tmp_path / "a" / "linked", 24)
    assert os.path.samefile(source, tmp_path / "a" / "linked")
    assert not reuse.link_chunk(source, tmp_path / "b" / "linked", 28)
    source.write_bytes(good[:-1] + b"\x01" + google_crc32c.value(good).to_bytes(4, "little"))
    assert not reuse.link_chunk(source, tmp_path / "c" / "linked", 24)
    assert not reuse.link_chunk(tmp_path / "absent", tmp_path / "d" / "linked", 24)
    assert not (tmp_path / "b").exists() and not (tmp_path / "c").exists()


# A finished ragged array of 7 images, 4 rows a chunk: rows 0-28, 7 chunks.
LENGTHS = [3, 5, 2, 6, 1, 4, 7]


def ragged_store(path: Path, parts: list[np.ndarray]) -> stores.CheckedGroup:
    """A finished store whose ragged ``masks`` (uint8 rows of 3, 4 rows a chunk) holds
    one image per array of ``parts``."""
    with stores.atomic_store(path) as group:
        writer = stores.RaggedWriter(group, "masks", (3,), np.uint8, 4)
        for part in parts:
            writer.append(part)
        writer.close()
    return stores.open_store(path)


@pytest.mark.parametrize(
    ("position", "first", "last"),
    [(0, 0, 7), (0, 2, 7), (7, 1, 6), (1, 1, 6), (5, 1, 7), (2, 2, 3), (4, 0, 1)],
)
def test_copied_rows_link_whole_chunks_that_land_on_whole_chunks_and_read_the_rest(
    tmp_path, position, first, last
):
    """Images ``first:last`` of a finished ragged array copied after ``position`` rows of
    ours and before another image: the store is the one appending their rows writes,
    and a chunk file of ours is theirs exactly where their rows ``4c:4c + 4`` are ours
    ``4c':4c' + 4``, which needs the two to start equally far from a chunk boundary."""
    rng = np.random.default_rng(position * 100 + first * 10 + last)
    images = [rng.integers(1, 255, (n, 3), dtype=np.uint8) for n in LENGTHS]
    theirs = ragged_store(tmp_path / "theirs.zarr", images)
    head = rng.integers(1, 255, (position, 3), dtype=np.uint8)
    tail = rng.integers(1, 255, (2, 3), dtype=np.uint8)
    expected = ragged_store(tmp_path / "expected.zarr", [head, *images[first:last], tail])
    offsets = np.cumsum([0, *LENGTHS])
    low, high = int(offsets[first]), int(offsets[last])
    with stores.atomic_store(tmp_path / "ours.zarr") as group:
        writer = stores.RaggedWriter(group, "masks", (3,), np.uint8, 4)
        writer.append(head)
        array = stores.array_directory(writer.array)
        alike = reuse.same_chunks(array, theirs.path / "masks")
        pieces = reuse.read_rows(theirs["masks"], low, high, position, alike)
        reuse.append_rows(writer, pieces)
        writer.add_images(np.asarray(LENGTHS[first:last]))
        writer.append(tail)
        writer.close()
    ours = tmp_path / "ours.zarr"
    assert alike and files_of(ours) == files_of(expected.path)
    # Chunks of theirs within low:high that are whole chunks of ours.
    linked = {
        (position + 4 * c - low) // 4: c
        for c in range(-(-low // 4), high // 4)
        if (position - low) % 4 == 0
    }
    for c in range(-(-(position + high - low + 2) // 4)):
        mine = ours / f"masks/c/{c}/0"
        assert mine.stat().st_nlink == (2 if c in linked else 1), c
        if c in linked:
            assert os.path.samefile(mine, theirs.path / f"masks/c/{linked[c]}/0")


def test_copied_rows_that_fail_their_checks_raise_before_anything_is_appended(tmp_path):
    """A damaged chunk among those to link, or among those to read: StoreCorruptError
    from read_rows, which has appended nothing (the caller computes those images)."""
    images = [np.full((n, 3), n, dtype=np.uint8) for n in LENGTHS]
    theirs = ragged_store(tmp_path / "theirs.zarr", images)
    chunk = theirs.path / "masks/c/2/0"
    damaged = bytearray(chunk.read_bytes())
    damaged[0] ^= 0xFF
    chunk.write_bytes(bytes(damaged))
    for position in (0, 1):  # linked, read
        with pytest.raises(stores.StoreCorruptError, match="masks"):
            reuse.read_rows(theirs["masks"], 0, 28, position, link=True)
    assert reuse.read_rows(theirs["masks"], 0, 4, 0, link=True)[1].path.name == "0"


def test_a_grown_maps_reference_masks_are_linked_as_they_are_copied(data, tmp_path, monkeypatch):
    """References at the same rows as the base store's: each whole chunk of theirs is
    hard-linked as the rows are copied (not found afterwards by link_equal_chunks,
    switched off here), and the store is the one from scratch."""
    monkeypatch.setattr(segments, "CHUNK_ROWS", 4)
    monkeypatch.setattr(reuse, "link_equal_chunks", lambda *args: 0)
    plan = plan_of(data, "base", "grown")
    base = run(plan, "segments", "base", data, tmp_path / "shared")
    grown = run(plan, "segments", "grown", data, tmp_path / "shared")
    references = int(stores.open_store(base)["masks_offsets"][N_PLACES])
    assert references >= 8
    for c in range(references // 4):
        assert os.path.samefile(base / f"masks/c/{c}/0", grown / f"masks/c/{c}/0")
    monkeypatch.undo()
    monkeypatch.setattr(segments, "CHUNK_ROWS", 4)
    alone = run(plan, "segments", "grown", data, tmp_path / "scratch")
    assert files_of(grown) == files_of(alone)


@pytest.mark.parametrize("masks_layout", ["packed", "per_image"])
def test_damaged_masks_cost_only_the_images_with_rows_in_them(
    data, tmp_path, caplog, monkeypatch, masks_layout
):
    """A grown map whose base store has a damaged chunk among the references' (linked
    whole) rows, in either layout: the images with rows in it are segmented again, every
    other one is reused, and the store is the one from scratch."""
    monkeypatch.setattr(segments, "CHUNK_ROWS", 4)
    monkeypatch.setattr(segments, "IMAGE_CHUNK_ROWS", 4)
    plan = plan_of(data, "base", "grown", masks_layout=masks_layout)
    scratch = run(plan, "segments", "grown", data, tmp_path / "scratch")
    base = run(plan, "segments", "base", data, tmp_path / "shared")
    group = stores.open_store(base)
    offsets = mask_rows(group)[0]
    chunk = reuse.chunk_file(group["masks"].raw, 1)  # rows 4:8
    damaged = bytearray(chunk.read_bytes())
    damaged[len(damaged) // 2] ^= 0xFF
    chunk.write_bytes(bytes(damaged))
    caplog.set_level(logging.INFO, logger="vprflow")
    grown = run(plan, "segments", "grown", data, tmp_path / "shared")
    # grown's reused images are base's 0-3 (references), 4, 6, 7 and 4 again (queries
    # 0000, 0002, 0003 and 0007); its 3 others are new.
    hit = [j for j in (0, 1, 2, 3, 4, 6, 7, 4) if offsets[j] < 8 and offsets[j + 1] > 4]
    assert 0 < len(hit) < 8
    assert counts(caplog) == (3 + len(hit), 8 - len(hit))
    assert files_of(grown) == files_of(scratch)


def test_chunks_are_linked_only_to_equal_files_of_equal_arrays_and_copied_without_links(
    data, tmp_path, monkeypatch
):
    """link_equal_chunks over a store being written (a copy of a finished one, outside
    the folder): every chunk file equal to a finished twin's is linked; one whose twins
    are gone, an array of another chunk shape or without metadata is no twin; a file
    system refusing hard links keeps the copies, any other refusal is an error."""
    monkeypatch.setattr(segments, "CHUNK_ROWS", 4)
    plan = plan_of(data, "base")
    base = run(plan, "segments", "base", data, tmp_path / "cache")
    folder, record = base.parent, stores.open_store(base).attrs["record"]
    chunks = sorted(p.relative_to(base) for p in (base / "masks" / "c").rglob("*") if p.is_file())
    (folder / "unfinished.zarr").mkdir()  # no record: not a store
    shutil.copytree(base, folder / "other.zarr")
    (folder / "other.zarr" / "masks" / "zarr.json").unlink()  # no metadata: not a twin
    shutil.copytree(base, folder / "wider.zarr")  # another chunk shape: not a twin
    wider = folder / "wider.zarr" / "masks" / "zarr.json"
    metadata = json.loads(wider.read_text())
    metadata["chunk_grid"]["configuration"]["chunk_shape"][0] = 8
    wider.write_text(json.dumps(metadata))

    def written() -> Path:
        target = tmp_path / "written"
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(base, target)
        return target

    target = written()
    (base / chunks[0]).unlink()  # a twin's file deleted meanwhile
    assert reuse.link_equal_chunks(target / "masks", record, folder) == len(chunks) - 1
    assert (target / chunks[0]).stat().st_nlink == 1
    assert all(os.path.samefile(target / c, base / c) for c in chunks[1:])
    assert all(not os.path.samefile(target / c, folder / "wider.zarr" / c) for c in chunks[1:])

    def refuse(code):
        def link(source, target):
            raise OSError(code, os.strerror(code))

        return link

    monkeypatch.setattr(os, "link", refuse(errno.EXDEV))
    target = written()
    assert reuse.link_equal_chunks(target / "masks", record, folder) == 0
    assert all((target / c).stat().st_nlink == 1 for c in chunks[1:])
    monkeypatch.setattr(os, "link", refuse(errno.EACCES))
    with pytest.raises(PermissionError):
        reuse.link_equal_chunks(written() / "masks", record, folder)


def test_the_runs_closing_line_sums_the_images_its_jobs_computed_and_reused(data, tmp_path):
    from vprflow.core.paths import log_pattern
    from vprflow.planning.reports import reuse_line
    from vprflow.stages.runner import run_stage

    plan = plan_of(data, "base", "grown")
    cache = tmp_path / "results" / "cache"
    assert reuse_line(plan, f"{tmp_path}/") is None
    for name in ("base", "grown"):
        (key,) = [k for k, s in plan.stages["features"].items() if s.dataset == name]
        log = tmp_path / log_pattern("features", "0-20").format(key=key)
        log.parent.mkdir(parents=True)
        run_stage(str(log), lambda name=name: run(plan, "features", name, data, cache))
        if name == "base":  # an earlier run's
            os.utime(log, (time.time() - 3600,) * 2)
    started = time.time() - 600
    grown = "vprflow: features and segments: 3 images computed, 8 reused from stores already there"
    assert reuse_line(plan, f"{tmp_path}/", started) == f"{grown} (1 jobs)"
    both = "vprflow: features and segments: 11 images computed, 8 reused from stores already there"
    assert reuse_line(plan, f"{tmp_path}/") == f"{both} (2 jobs)"

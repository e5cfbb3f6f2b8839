"""Atomic Zarr stores, ragged arrays and packed masks (exact round trips)."""

from __future__ import annotations

import errno
import multiprocessing
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from vprflow.core import stores
from vprflow.core.stores import (
    COMPRESSOR,
    COMPRESSORS,
    RaggedWriter,
    StoreCorruptError,
    array_items,
    atomic_store,
    open_store,
    pack_masks,
    read_strings,
    temporary_paths,
    unpack_masks,
    write_array,
)


class Boom(RuntimeError):
    pass


def test_failed_block_leaves_no_store(tmp_path):
    out = tmp_path / "stage" / "key.zarr"
    with pytest.raises(Boom), atomic_store(out, attrs={"stage": "x"}) as group:
        write_array(group, "data", np.arange(10))
        assert temporary_paths(out) and not out.exists()
        raise Boom("interrupted")
    assert not out.exists()
    assert not temporary_paths(out)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        open_store(out)


def test_successful_block_appears_atomically_and_stale_tmp_is_removed(tmp_path):
    out = tmp_path / "key.zarr"
    stale = out.with_name(out.name + ".tmp")  # the name before writer tags
    stale.mkdir()
    (stale / "leftover").write_text("from an interrupted run")
    out.mkdir()  # Snakemake may pre-create a directory output
    (out / "old").write_text("stale")
    with atomic_store(out, attrs={"stage": "x", "n": 3}) as group:
        assert not (stale / "leftover").exists()
        write_array(group, "data", np.arange(10))
        write_array(group, "names", np.array(["a.jpg", "b.jpg"]))
        assert not (out / "data").exists()  # nothing visible before the block ends
    assert not stale.exists()
    assert not (out / "old").exists()
    store = open_store(out)
    assert dict(store.attrs) == {"stage": "x", "n": 3}
    np.testing.assert_array_equal(store["data"][...], np.arange(10))
    assert [str(s) for s in store["names"][...]] == ["a.jpg", "b.jpg"]


@pytest.mark.parametrize("write_bytes", [stores.WRITE_BYTES, 1])  # 1: a write per chunk
@pytest.mark.parametrize("chunk_rows", [1, 4, 7, 1000])
def test_ragged_writer_round_trip_with_many_small_appends(
    tmp_path, monkeypatch, chunk_rows, write_bytes
):
    # With a write per chunk, a write's rows start and end inside appended blocks, often
    # several blocks short of a chunk: the writer splits what it keeps there.
    monkeypatch.setattr(stores, "WRITE_BYTES", write_bytes)
    rng = np.random.default_rng(chunk_rows)
    blocks = [
        rng.standard_normal((int(n), 3, 2)).astype(np.float32) for n in rng.integers(0, 6, 57)
    ]
    blocks[0] = blocks[0][:0]  # first and last images without rows
    blocks[-1] = blocks[-1][:0]
    out = tmp_path / "ragged.zarr"
    with atomic_store(out) as group:
        writer = RaggedWriter(group, "rows", (3, 2), np.float32, chunk_rows)
        for block in blocks:
            writer.append(block)
        offsets = writer.close()
    expected_offsets = [0]
    for block in blocks:
        expected_offsets.append(expected_offsets[-1] + len(block))
    np.testing.assert_array_equal(offsets, expected_offsets)
    store = open_store(out)
    np.testing.assert_array_equal(store["rows_offsets"][...], expected_offsets)
    assert store["rows"].shape == (expected_offsets[-1], 3, 2)
    for i, block in enumerate(blocks):
        np.testing.assert_array_equal(_ragged_rows(store, "rows", i), block)
    np.testing.assert_array_equal(store["rows"][...], np.concatenate(blocks))


def test_split_rows_divides_the_appended_arrays_after_count_rows():
    rng = np.random.default_rng(5)
    for _ in range(200):
        parts = [
            np.arange(n) + 10 * i for i, n in enumerate(rng.integers(0, 5, rng.integers(1, 7)))
        ]
        joined = np.concatenate(parts)
        count = int(rng.integers(0, len(joined) + 1))
        head, tail = stores._split_rows(parts, count)
        assert sum(map(len, head)) == count and all(len(p) for p in head + tail)
        np.testing.assert_array_equal(np.concatenate([*head, *tail, joined[:0]]), joined)
        assert all(any(np.shares_memory(p, q) for q in parts) for p in head + tail)  # views


def test_a_failing_stage_leaves_no_store_behind_its_background_writes(tmp_path):
    out = tmp_path / "d.zarr"
    with pytest.raises(RuntimeError, match="late failure"):
        with atomic_store(out) as group:
            writer = RaggedWriter(group, "rows", (64,), np.float32, chunk_rows=8)
            for _ in range(40):  # several whole chunks, each written in the background
                writer.append(np.ones((3, 64), np.float32))
            raise RuntimeError("late failure")
    assert not out.exists() and not stores.temporary_paths(out)


def test_ragged_writer_casts_to_its_dtype(tmp_path):
    with atomic_store(tmp_path / "r.zarr") as group:
        writer = RaggedWriter(group, "ids", (), np.int64, 3)
        writer.append(np.array([1.0, 2.0]))
        writer.append(np.array([7]))
        writer.close()
    store = open_store(tmp_path / "r.zarr")
    assert store["ids"].dtype == np.int64
    np.testing.assert_array_equal(_ragged_rows(store, "ids", 0), [1, 2])
    np.testing.assert_array_equal(_ragged_rows(store, "ids", 1), [7])


def _chunked_rows(dtype, chunk_rows: int = 4) -> np.ndarray:
    """Rows ``[7 chunks and 2 rows, 3]`` whose chunks zarr must tell apart: chunk 1 all
    zero (zarr stores no file for it), chunk 2 zero but for its last row, chunk 3 -0.0
    where the dtype has it (not zarr's fill value: stored), and a last, partial chunk of
    zeros (not stored)."""
    rng = np.random.default_rng(7)
    rows = (rng.standard_normal((7 * chunk_rows + 2, 3)) * 50).astype(dtype)
    rows[rows == 0] = 1  # only the chunks below hold zeros
    rows[chunk_rows : 2 * chunk_rows] = 0
    rows[2 * chunk_rows : 3 * chunk_rows - 1] = 0
    if np.dtype(dtype).kind == "f":
        rows[3 * chunk_rows : 4 * chunk_rows] = -0.0
    rows[7 * chunk_rows :] = 0
    return rows


def _files(array_dir: Path) -> dict[str, bytes]:
    """An array directory's chunk files, by path, and its zarr.json without attributes
    (atomic_store adds the chunk count)."""
    import json

    found = {}
    for path in sorted(array_dir.rglob("*")):
        if path.is_file():
            data = path.read_bytes()
            if path.name == "zarr.json":
                metadata = json.loads(data)
                metadata.pop("attributes", None)
                data = json.dumps(metadata, sort_keys=True).encode()
            found[str(path.relative_to(array_dir))] = data
    return found


# The codec chains stages write: compressed, compressed fast (descriptors), and the
# checksum alone (features).
CODECS = {
    "zstd+crc32c": stores.COMPRESSORS,
    "zstd-fast+crc32c": stores.FAST_COMPRESSORS,
    "crc32c": stores.CHECKSUM_ONLY,
}


@pytest.mark.parametrize("codecs", CODECS)
@pytest.mark.parametrize("dtype", [np.float32, np.float16, np.int64, np.uint8, bool])
@pytest.mark.parametrize("write_chunks", [1, 3, 100])
def test_row_writer_stores_the_chunk_files_of_zarr_append(
    tmp_path, monkeypatch, dtype, write_chunks, codecs
):
    """RowWriter (several chunks at once, each chunk that cannot be empty encoded and
    written by vprflow, the others by zarr) leaves the files that zarr's own
    Array.append of each chunk leaves, the way RowWriter wrote before; plain zarr reads
    the same bits back."""
    import zarr

    chunk_rows = 4
    rows = _chunked_rows(dtype, chunk_rows)
    row_bytes = rows.dtype.itemsize * rows.shape[1]
    monkeypatch.setattr(stores, "WRITE_BYTES", write_chunks * chunk_rows * row_bytes)
    decided, written = [], []
    real, write_chunk = stores._cannot_be_empty, stores._write_chunk
    monkeypatch.setattr(
        stores, "_cannot_be_empty", lambda *a: decided.append(real(*a)) or decided[-1]
    )
    monkeypatch.setattr(
        stores, "_write_chunk", lambda a, i, r: written.append(i) or write_chunk(a, i, r)
    )
    out = tmp_path / "new.zarr"
    with atomic_store(out) as group:
        writer = stores.RowWriter(group, "rows", (3,), dtype, chunk_rows, CODECS[codecs])
        for first in range(0, len(rows), 3):  # appends that straddle chunks
            writer.append(rows[first : first + 3])
        writer.close()
    reference = zarr.open_group(str(tmp_path / "append.zarr"), mode="w").create_array(
        "rows", shape=(0, 3), chunks=(chunk_rows, 3), dtype=dtype, compressors=CODECS[codecs]
    )
    for first in range(0, len(rows), chunk_rows):
        reference.append(rows[first : first + chunk_rows])

    new, old = _files(out / "rows"), _files(tmp_path / "append.zarr" / "rows")
    assert new.keys() == old.keys()
    # Chunk 1 and the last chunk are zeros: no file, in either.
    assert [name for name in new if name.startswith("c")] == [
        f"c/{i}/0" for i in (0, 2, 3, 4, 5, 6)
    ]
    for name in new:
        assert new[name] == old[name], name
    # zarr's comparison was skipped for every chunk but the two empty ones, whose
    # writes zarr made (and skipped); vprflow wrote the others.
    assert sorted(decided) == [False] * 2 + [True] * 6
    assert sorted(written) == [0, 2, 3, 4, 5, 6]
    stored = zarr.open_group(str(out), mode="r")["rows"][...]
    assert stored.dtype == rows.dtype
    assert stored.tobytes() == rows.tobytes()  # bits: -0.0 stays -0.0


def test_row_writer_records_its_length_once_where_it_writes_every_chunk_file(tmp_path, monkeypatch):
    import zarr

    resizes = []
    resize = zarr.Array.resize
    monkeypatch.setattr(
        zarr.Array, "resize", lambda a, shape: resizes.append(shape) or resize(a, shape)
    )
    monkeypatch.setattr(stores, "WRITE_BYTES", 1)  # a write per chunk
    rows = np.random.default_rng(4).standard_normal((30, 3)).astype(np.float32)
    with atomic_store(tmp_path / "r.zarr") as group:
        writer = stores.RowWriter(group, "rows", (3,), np.float32, 4)
        for first in range(0, len(rows), 5):
            writer.append(rows[first : first + 5])
        writer.close()
    assert resizes == [(30, 3)]
    np.testing.assert_array_equal(open_store(tmp_path / "r.zarr")["rows"][...], rows)


@pytest.mark.parametrize("codecs", CODECS)
def test_a_last_partial_chunk_is_written_padded_as_zarr_pads_it(tmp_path, codecs):
    import zarr

    rows = np.random.default_rng(3).standard_normal((10, 5)).astype(np.float32)
    group = zarr.open_group(str(tmp_path / "g.zarr"), mode="w")
    new, old = (
        group.create_array(
            name, shape=(0, 5), chunks=(4, 5), dtype=np.float32, compressors=CODECS[codecs]
        )
        for name in ("new", "append")
    )
    stores.store_rows(new, rows)
    old.append(rows)
    files = _files(tmp_path / "g.zarr" / "new")
    assert "c/2/0" in files and files == _files(tmp_path / "g.zarr" / "append")
    np.testing.assert_array_equal(zarr.open_group(str(tmp_path / "g.zarr"))["new"][...], rows)


def test_store_rows_appends_at_any_row_as_zarr_append_does(tmp_path):
    """Appends that start and end inside chunks (zarr merges them with the stored part)
    leave zarr's files, empty chunks included; an array chunked along another axis is
    refused by name."""
    import zarr

    rows = _chunked_rows(np.int64)
    group = zarr.open_group(str(tmp_path / "g.zarr"), mode="w")
    arrays = [
        group.create_array(
            name, shape=(0, 3), chunks=(4, 3), dtype=np.int64, compressors=stores.COMPRESSORS
        )
        for name in ("new", "append")
    ]
    first = 0
    for size in (3, 5, 1, 0, 9, 4, 8):
        stores.store_rows(arrays[0], rows[first : first + size])
        arrays[1].append(rows[first : first + size])
        first += size
    assert first == len(rows)
    new, old = _files(tmp_path / "g.zarr" / "new"), _files(tmp_path / "g.zarr" / "append")
    assert "c/1/0" not in new and new == old
    np.testing.assert_array_equal(arrays[0][...], rows)
    wide = group.create_array("wide", shape=(0, 4), chunks=(4, 2), dtype=np.int64)
    with pytest.raises(ValueError, match=r"array file://.*g\.zarr/wide has chunks \(4, 2\)"):
        stores.store_rows(wide, np.ones((4, 4), np.int64))


def test_a_failed_chunk_write_raises_before_the_next_chunk_is_written(tmp_path, monkeypatch):
    """Chunks are written one after another on the caller's thread: when one fails, no
    later one is started, and none is still being written when the failing stage
    deletes its temporary store (atomic_store)."""
    import zarr

    array = zarr.open_group(str(tmp_path / "g.zarr"), mode="w").create_array(
        "x", shape=(0, 3), chunks=(4, 3), dtype=np.float32, compressors=stores.COMPRESSORS
    )
    attempted = []

    def failing_at_two(_array, rows):
        attempted.append(int(rows[0, 0]))
        if rows[0, 0] == 2:
            raise RuntimeError("disk full")
        return True

    monkeypatch.setattr(stores, "_cannot_be_empty", failing_at_two)
    rows = np.repeat(np.arange(4, dtype=np.float32), 4)[:, None].repeat(3, axis=1)
    with pytest.raises(RuntimeError, match="disk full"):
        stores.store_rows(array, rows)
    assert attempted == [0, 1, 2]
    assert sorted(p.name for p in (tmp_path / "g.zarr" / "x" / "c").iterdir()) == ["0", "1"]


@pytest.mark.parametrize(
    "dtype, block, empty",
    [
        (np.float32, np.zeros((4, 3)), True),
        (np.float32, np.full((4, 3), -0.0), False),  # zarr compares floats' bits
        (np.float32, np.r_[np.zeros((3, 3)), [[0, 0, 1e-45]]], False),  # a subnormal
        (np.float64, np.r_[np.zeros((3, 3)), [[0, 0, 5e-324]]], False),
        (np.int64, np.r_[np.zeros((3, 3)), [[0, -1, 0]]], False),
        (np.int64, np.zeros((4, 3)), True),
        (bool, np.zeros((4, 3)), True),
        (bool, np.eye(4, 3), False),
        (np.complex64, np.full((4, 3), -0.0 + 0j), True),  # zarr: -0.0 == 0 for complex
        (np.complex64, np.ones((4, 3)), False),
    ],
)
def test_the_empty_chunk_shortcut_agrees_with_zarrs_comparison(tmp_path, dtype, block, empty):
    """_cannot_be_empty answers True only where zarr's own comparison (NDBuffer.all_equal
    with the fill value) finds the chunk not empty; complex arrays always go to zarr."""
    import zarr
    from zarr.core.buffer.cpu import NDBuffer

    block = np.asarray(block).astype(dtype)
    array = zarr.open_group(str(tmp_path / "g.zarr"), mode="w").create_array(
        "x", shape=(4, 3), chunks=(4, 3), dtype=dtype, compressors=stores.COMPRESSORS
    )
    assert NDBuffer.from_numpy_array(block).all_equal(array.fill_value) is empty
    shortcut = stores._cannot_be_empty(array, block)
    assert shortcut is (not empty and block.dtype.kind != "c")


@pytest.mark.parametrize("shape", [(3, 5, 7), (1, 1, 1), (4, 13, 3), (2, 9, 8), (0, 3, 5)])
def test_pack_unpack_masks_round_trip(shape):
    masks = np.random.default_rng(sum(shape)).random(shape) < 0.4
    packed = pack_masks(masks)
    assert packed.dtype == np.uint8
    assert packed.shape == (shape[0], -(-shape[1] * shape[2] // 8))
    np.testing.assert_array_equal(unpack_masks(packed, shape[1], shape[2]), masks)


def test_packed_masks_survive_a_store(tmp_path):
    masks = np.random.default_rng(0).random((5, 11, 7)) < 0.5
    with atomic_store(tmp_path / "m.zarr") as group:
        write_array(group, "masks", pack_masks(masks))
    stored = open_store(tmp_path / "m.zarr")["masks"][...]
    np.testing.assert_array_equal(unpack_masks(stored, 11, 7), masks)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_values_are_refused_and_nothing_is_stored(tmp_path, bad):
    out = tmp_path / "pca.zarr"
    data = np.ones((4, 3), np.float32)
    data[2, 1] = bad
    with pytest.raises(stores.NonFiniteError, match=r"stage 'pca': array 'components'.*rows \[2\]"):
        with stores.atomic_store(out, {"stage": "pca"}) as group:
            stores.write_array(group, "components", data)
    assert not out.exists() and not stores.temporary_paths(out)


def test_ragged_writer_refuses_non_finite_rows_naming_the_row(tmp_path):
    with pytest.raises(stores.NonFiniteError, match=r"stage 'descriptors'.*rows \[3\]"):
        with stores.atomic_store(tmp_path / "d.zarr", {"stage": "descriptors"}) as group:
            writer = stores.RaggedWriter(group, "descriptors", (2,), np.float32, chunk_rows=4)
            writer.append(np.zeros((3, 2)))
            writer.append(np.array([[np.nan, 0.0]]))


def test_float16_overflow_is_named(tmp_path):
    with pytest.raises(stores.NonFiniteError, match="store_dtype: float32"):
        with stores.atomic_store(tmp_path / "f.zarr", {"stage": "features"}) as group:
            with np.errstate(over="ignore"):
                overflowed = np.array([1e5], np.float32).astype(np.float16)
            stores.check_finite(group, "features", overflowed)


@pytest.mark.parametrize("block_bytes", [1, 24, 1 << 20])
def test_ragged_reader_returns_each_image_in_any_order(tmp_path, block_bytes):
    rng = np.random.default_rng(0)
    counts = [3, 0, 5, 1, 0, 2]
    blocks = [rng.standard_normal((c, 3)).astype(np.float32) for c in counts]
    with stores.atomic_store(tmp_path / "r.zarr") as group:
        writer = stores.RaggedWriter(group, "rows", (3,), np.float32, chunk_rows=4)
        for block in blocks:
            writer.append(block)
        writer.close()
    reader = stores.RaggedReader(stores.open_store(tmp_path / "r.zarr"), "rows", block_bytes)
    for index in [0, 1, 2, 3, 4, 5, 2, 0, 5]:
        np.testing.assert_array_equal(reader(index), blocks[index])


# ------------------------------------------------------------------ corrupted stores


def _sample_store(path, compressors=stores.COMPRESSORS):
    """A store like a stage's: ragged float rows in 4 chunks, strings, integers."""
    rows = np.random.default_rng(0).standard_normal((14, 8)).astype(np.float32)
    with atomic_store(path, attrs={"stage": "descriptors"}) as group:
        if compressors is stores.COMPRESSORS:
            writer = RaggedWriter(group, "descriptors", (8,), np.float32, chunk_rows=4)
            for block in np.split(rows, [3, 7, 12]):
                writer.append(block)
            writer.close()
        else:
            group.create_array("descriptors", data=rows, chunks=(4, 8), compressors=compressors)
        write_array(group, "names", np.array(["ref/a.jpg", "ref/b.jpg", "query/c.jpg"]))
    return rows


def _flip_byte(path, position):
    data = bytearray(path.read_bytes())
    data[position] ^= 0xFF
    path.write_bytes(bytes(data))


def _corrupt_message(path, array=None):
    """What a StoreCorruptError must say: the store, the array, the remedy."""
    named = re.escape(f"store {path}: ") + (f"array '{array}' .*" if array else ".*")
    return named + re.escape(f"rm -r {path}) and run snakemake again")


def test_every_array_carries_a_checksum_and_plain_zarr_reads_the_store_exactly(tmp_path):
    import zarr

    out = tmp_path / "d.zarr"
    rows = _sample_store(out)
    plain = zarr.open_group(str(out), mode="r")
    for name, array in array_items(plain):
        assert type(array.compressors[-1]).__name__ == "Crc32cCodec", name
    np.testing.assert_array_equal(plain["descriptors"][...], rows)
    checked = open_store(out)
    np.testing.assert_array_equal(np.asarray(checked["descriptors"]), rows)
    np.testing.assert_array_equal(checked["descriptors"][5:9], rows[5:9])
    assert read_strings(checked, "names") == ["ref/a.jpg", "ref/b.jpg", "query/c.jpg"]
    assert len(checked["descriptors"]) == 14 and "names" in checked and "x" not in checked
    with pytest.raises(IndexError):  # a selection mistake is not called corruption
        checked["descriptors"][1.5]


@pytest.mark.parametrize("position", [0, 40, -1])
def test_a_flipped_byte_in_a_float_chunk_is_an_error_naming_store_and_array(tmp_path, position):
    out = tmp_path / "d.zarr"
    _sample_store(out)
    chunk = out / "descriptors" / "c" / "1" / "0"
    _flip_byte(chunk, position)
    store = open_store(out)  # the metadata is intact: the chunk fails when read
    assert store["descriptors"][:4].shape == (4, 8)  # the other chunks still read
    with pytest.raises(StoreCorruptError, match=_corrupt_message(out, "descriptors")):
        store["descriptors"][...]
    with pytest.raises(StoreCorruptError, match="checksum"):
        np.asarray(store["descriptors"])


def test_a_flipped_byte_in_a_string_chunk_is_an_error_naming_store_and_array(tmp_path):
    out = tmp_path / "d.zarr"
    _sample_store(out)
    _flip_byte(out / "names" / "c" / "0", 10)
    with pytest.raises(StoreCorruptError, match=_corrupt_message(out, "names")):
        read_strings(open_store(out), "names")


def test_a_truncated_group_zarr_json_is_an_error_naming_the_store(tmp_path):
    out = tmp_path / "d.zarr"
    _sample_store(out)
    metadata = out / "zarr.json"
    metadata.write_text(metadata.read_text()[:30])
    with pytest.raises(StoreCorruptError, match=_corrupt_message(out)) as raised:
        open_store(out)
    assert "group metadata zarr.json cannot be read" in str(raised.value)


def test_a_truncated_array_zarr_json_is_an_error_naming_the_array(tmp_path):
    out = tmp_path / "d.zarr"
    _sample_store(out)
    metadata = out / "descriptors" / "zarr.json"
    metadata.write_text(metadata.read_text()[:30])
    with pytest.raises(StoreCorruptError, match=_corrupt_message(out, "descriptors")) as raised:
        open_store(out)
    assert "descriptors/zarr.json" in str(raised.value)


def test_a_missing_array_zarr_json_is_an_error_not_a_missing_array(tmp_path):
    out = tmp_path / "d.zarr"
    _sample_store(out)
    (out / "names" / "zarr.json").unlink()
    with pytest.raises(StoreCorruptError, match=_corrupt_message(out, "names")) as raised:
        open_store(out)
    assert "names/zarr.json is missing" in str(raised.value)


def test_a_deleted_chunk_file_is_an_error_counting_the_chunks(tmp_path):
    out = tmp_path / "d.zarr"
    _sample_store(out)
    (out / "descriptors" / "c" / "2" / "0").unlink()
    with pytest.raises(StoreCorruptError, match=_corrupt_message(out, "descriptors")) as raised:
        open_store(out)
    assert "array 'descriptors' has 3 chunk files, 4 were written" in str(raised.value)


def test_a_store_with_every_chunk_written_opens_without_listing_its_directories(
    tmp_path, monkeypatch
):
    out = tmp_path / "d.zarr"
    rows = _sample_store(out)
    monkeypatch.setattr(stores, "count_chunk_files", lambda path: pytest.fail(f"listed {path}"))
    np.testing.assert_array_equal(open_store(out)["descriptors"][...], rows)


def test_a_deleted_chunk_file_beside_skipped_empty_chunks_is_an_error(tmp_path):
    out = tmp_path / "z.zarr"
    rows = np.ones((12, 3), np.float32)
    rows[4:8] = 0  # chunk 1 equals the fill value: zarr stores no file for it
    with atomic_store(out) as group:
        writer = stores.RowWriter(group, "rows", (3,), np.float32, chunk_rows=4)
        writer.append(rows)
        writer.close()
    np.testing.assert_array_equal(open_store(out)["rows"][...], rows)
    (out / "rows" / "c" / "2" / "0").unlink()
    with pytest.raises(StoreCorruptError, match="has 1 chunk files, 2 were written"):
        open_store(out)


def test_a_store_without_checksums_is_refused_as_older_than_checksums(tmp_path):
    import zarr

    out = tmp_path / "old.zarr"
    old = zarr.open_group(str(out), mode="w")  # what vprflow wrote before checksums
    old.attrs.update({"stage": "descriptors"})
    old.create_array("descriptors", data=np.ones((4, 2), np.float32), compressors=COMPRESSOR)
    with pytest.raises(StoreCorruptError, match=_corrupt_message(out, "descriptors")) as raised:
        open_store(out)
    assert "predates checksums" in str(raised.value)


def test_an_array_created_without_the_checksum_is_refused_when_the_store_is_finished(tmp_path):
    out = tmp_path / "d.zarr"
    with pytest.raises(ValueError, match="array 'raw' was created without stores.COMPRESSORS"):
        with atomic_store(out) as group:
            group.create_array("raw", data=np.ones(3), compressors=COMPRESSOR)
    assert not out.exists()


def _ragged_rows(group, name: str, index: int) -> np.ndarray:
    """Rows of image ``index`` of a ragged array, read directly from its offsets."""
    start, stop = (int(v) for v in group[f"{name}_offsets"][index : index + 2])
    return np.asarray(group[name][start:stop])


# ------------------------------------------------------------------ reading whole rows

# (shape, chunks): chunks along axis 0 only (1-D, 2-D, 3-D, a partial last chunk, one
# chunk) and along other axes too (partial chunks on every axis).
ROW_LAYOUTS = [
    ((10,), (4,)),
    ((12, 3), (4, 3)),
    ((10, 3), (4, 3)),
    ((7, 2, 3), (3, 2, 3)),
    ((5, 6), (8, 6)),
    ((10, 5), (4, 3)),
    ((9, 4, 5), (2, 3, 2)),
]
# Whole rows: the row reader's. Python ints only (a numpy integer goes to zarr).
ROW_SELECTIONS = [
    ...,
    (),
    slice(None),
    slice(2, 7),
    slice(3, 4),
    slice(-3, None),
    slice(5, 5),
    slice(8, 2),
    slice(0, 100),
    0,
    -1,
    4,
    (slice(1, 6), ...),
    (slice(1, 6), slice(None)),
    (Ellipsis,),
]
# Not whole rows, or not as zarr's row reader would answer: zarr reads them.
OTHER_SELECTIONS = [
    slice(None, None, 2),
    slice(1, 9, 3),
    np.int64(2),
    [0, 3, 1],
    (slice(None), 1),
    (..., 0),
    (2, slice(0, 1)),
    (0, ...),
    (-1,),
]


def _row_store(path, dtype, shape, chunks, zero_chunk=False, **create):
    """A finished store holding one random array ``x``; with ``zero_chunk`` its second
    chunk along axis 0 is all zeros, which zarr does not store (the fill value)."""
    rng = np.random.default_rng(len(shape) * 100 + chunks[0])
    data = (rng.standard_normal(shape) * 40).astype(dtype)
    if zero_chunk:
        data[chunks[0] : 2 * chunks[0]] = 0
    create.setdefault("compressors", stores.COMPRESSORS)
    with atomic_store(path) as group:
        group.create_array("x", shape=shape, chunks=chunks, dtype=dtype, **create)[...] = data
    return data


def _forbid_zarr_reads(monkeypatch):
    """From here on zarr's own reads fail: what is read was read by the row reader."""
    import zarr

    def refuse(self, selection):
        raise AssertionError(f"zarr read {selection!r}: the row reader was not taken")

    monkeypatch.setattr(zarr.Array, "__getitem__", refuse)


def _same(got, expected):
    assert type(got) is type(expected)
    assert got.dtype == expected.dtype and got.shape == expected.shape
    assert np.array_equal(got, expected)


@pytest.mark.parametrize("codecs", CODECS)
@pytest.mark.parametrize("dtype", [np.float32, np.float16, np.int64, np.bool_, np.uint8])
@pytest.mark.parametrize("shape, chunks", ROW_LAYOUTS)
@pytest.mark.parametrize("zero_chunk", [False, True])
def test_whole_rows_are_read_from_the_chunk_files_with_zarrs_values(
    tmp_path, monkeypatch, dtype, shape, chunks, zero_chunk, codecs
):
    import zarr

    out = tmp_path / "rows.zarr"
    data = _row_store(out, dtype, shape, chunks, zero_chunk=zero_chunk, compressors=CODECS[codecs])
    if zero_chunk and shape[0] > chunks[0]:
        assert not (out / "x" / "c" / "1").exists()  # zarr left the chunk out
    plain = zarr.open_group(str(out), mode="r")["x"]
    selections = [s for s in ROW_SELECTIONS if not isinstance(s, tuple) or len(s) <= len(shape)]
    expected = {i: plain[s] for i, s in enumerate(selections)}
    array = open_store(out)["x"]
    _forbid_zarr_reads(monkeypatch)
    for i, selection in enumerate(selections):
        got = array[selection]
        _same(got, expected[i])
        assert np.array_equal(got, data[selection]), selection  # the values written
    _same(np.asarray(array), np.asarray(expected[0]))


@pytest.mark.parametrize(
    "shape, chunks", [((10,), (4,)), ((10, 3), (4, 3)), ((9, 4, 5), (2, 3, 2))]
)
def test_other_selections_are_zarrs(tmp_path, monkeypatch, shape, chunks):
    import zarr

    out = tmp_path / "rows.zarr"
    data = _row_store(out, np.float32, shape, chunks)
    plain = zarr.open_group(str(out), mode="r")["x"]
    array = open_store(out)["x"]
    assert array._rows is not None

    def refuse(*args):
        raise AssertionError("the row reader read a selection it does not take")

    monkeypatch.setattr(stores._RowReader, "read", refuse)
    for selection in OTHER_SELECTIONS:
        if isinstance(selection, tuple) and len(selection) - (... in selection) > len(shape):
            continue  # too many indices: below
        _same(array[selection], plain[selection])
        assert np.array_equal(array[selection], data[selection])
    with pytest.raises(IndexError):  # mistakes are zarr's to name
        array[10]
    with pytest.raises(IndexError):
        array[:, :, :, :]


@pytest.mark.parametrize(
    "other",
    ["gzip", "transpose", "big-endian", "v2-keys", "sharded", "zstd-only"],
)
def test_arrays_with_other_codecs_or_layouts_are_read_by_zarr(tmp_path, other):
    import zarr.codecs

    crc = zarr.codecs.Crc32cCodec()
    create = {
        "gzip": {"compressors": (zarr.codecs.GzipCodec(), crc)},
        "transpose": {"filters": (zarr.codecs.TransposeCodec(order=(1, 0)),)},
        "big-endian": {"serializer": zarr.codecs.BytesCodec(endian="big")},
        "v2-keys": {"chunk_key_encoding": {"name": "v2", "separator": "."}},
        "sharded": {"shards": (8, 3)},
        # A plain zarr array: opened by zarr.open_group, not open_store, so not checked.
        "zstd-only": {"compressors": (stores.COMPRESSOR,)},
    }[other]
    out = tmp_path / "other.zarr"
    data = (np.random.default_rng(1).standard_normal((16, 3)) * 40).astype(np.float32)
    if other == "zstd-only":
        zarr.open_group(str(out), mode="w").create_array("x", data=data, chunks=(4, 3), **create)
        array = stores.CheckedArray(zarr.open_group(str(out), mode="r")["x"], out, "x")
    else:
        data = _row_store(out, np.float32, (16, 3), (4, 3), **create)
        array = open_store(out)["x"]
    assert array._rows is None
    _same(array[2:9], data[2:9])
    _same(np.asarray(array), data)


@pytest.mark.parametrize(
    "create",
    [
        {"chunk_key_encoding": {"name": "default", "separator": "."}},
        {"compressors": (stores.COMPRESSOR.__class__(level=5, checksum=True), COMPRESSORS[-1])},
    ],
    ids=["dot-separated-keys", "zstd-level-5-with-its-checksum"],
)
def test_vprflows_codecs_with_other_settings_are_still_read_from_the_files(
    tmp_path, monkeypatch, create
):
    out = tmp_path / "rows.zarr"
    data = _row_store(out, np.float32, (10, 3), (4, 3), **create)
    array = open_store(out)["x"]
    _forbid_zarr_reads(monkeypatch)
    _same(array[1:9], data[1:9])


def _damage(path, how):
    data = path.read_bytes()
    if how == "flipped first byte":
        path.write_bytes(bytes([data[0] ^ 0xFF]) + data[1:])
    elif how == "flipped middle byte":
        middle = len(data) // 2
        path.write_bytes(data[:middle] + bytes([data[middle] ^ 0xFF]) + data[middle + 1 :])
    elif how == "flipped checksum byte":
        path.write_bytes(data[:-1] + bytes([data[-1] ^ 0xFF]))
    elif how == "truncated":
        path.write_bytes(data[: len(data) - 7])
    elif how == "two bytes":
        path.write_bytes(data[:2])
    elif how == "empty":
        path.write_bytes(b"")


@pytest.mark.parametrize(
    "how",
    [
        "flipped first byte",
        "flipped middle byte",
        "flipped checksum byte",
        "truncated",
        "two bytes",
        "empty",
    ],
)
@pytest.mark.parametrize("codecs", CODECS)
def test_a_damaged_chunk_file_read_as_rows_is_an_error_naming_it(
    tmp_path, monkeypatch, how, codecs
):
    out = tmp_path / "d.zarr"
    rows = _sample_store(out, CODECS[codecs])
    _damage(out / "descriptors" / "c" / "1" / "0", how)
    array = open_store(out)["descriptors"]
    _forbid_zarr_reads(monkeypatch)
    np.testing.assert_array_equal(array[:4], rows[:4])  # the other chunks still read
    np.testing.assert_array_equal(array[8:], rows[8:])
    for selection in [..., slice(2, 6), 5]:
        with pytest.raises(StoreCorruptError, match=_corrupt_message(out, "descriptors")) as raised:
            array[selection]
        assert "chunk file descriptors/c/1/0 " in str(raised.value)
        assert ("checksum" if how != "two bytes" and how != "empty" else "bytes") in str(
            raised.value
        )


@pytest.mark.parametrize("rows", [3, 5])
def test_a_chunk_of_the_wrong_size_with_a_good_checksum_is_an_error_naming_it(
    tmp_path, monkeypatch, rows
):
    import google_crc32c
    import numcodecs.zstd

    out = tmp_path / "d.zarr"
    _sample_store(out)
    # What a 4-row chunk of another array, or a bug, would leave: a valid file, other size.
    frame = numcodecs.zstd.compress(np.ones((rows, 8), np.float32).tobytes(), 1)
    crc = np.uint32(google_crc32c.value(frame)).tobytes()  # little-endian, as zarr's
    (out / "descriptors" / "c" / "1" / "0").write_bytes(frame + crc)
    array = open_store(out)["descriptors"]
    _forbid_zarr_reads(monkeypatch)
    with pytest.raises(StoreCorruptError, match=_corrupt_message(out, "descriptors")) as raised:
        array[...]
    assert f"chunk file descriptors/c/1/0 decompresses to {rows * 32} bytes, not 128" in str(
        raised.value
    )


@pytest.mark.parametrize("rows", [3, 5])
def test_an_uncompressed_chunk_of_the_wrong_size_with_a_good_checksum_is_an_error_naming_it(
    tmp_path, monkeypatch, rows
):
    import google_crc32c

    out = tmp_path / "d.zarr"
    _sample_store(out, stores.CHECKSUM_ONLY)
    plain = np.ones((rows, 8), np.float32).tobytes()
    crc = np.uint32(google_crc32c.value(plain)).tobytes()
    (out / "descriptors" / "c" / "1" / "0").write_bytes(plain + crc)
    array = open_store(out)["descriptors"]
    _forbid_zarr_reads(monkeypatch)
    with pytest.raises(StoreCorruptError, match=_corrupt_message(out, "descriptors")) as raised:
        array[...]
    assert f"chunk file descriptors/c/1/0 holds {rows * 32} bytes, not 128" in str(raised.value)


def test_zstd_frame_content_size_is_read_for_every_header_width():
    import numcodecs.zstd

    for size in [0, 1, 255, 256, 300, 65535 + 256, 65536 + 256, 1 << 20]:
        frame = numcodecs.zstd.compress(bytes(size), 1)
        assert stores._content_size(frame) == size, size
    assert stores._content_size(b"not a zstd frame") is None


# ------------------------------------------------------------------ concurrent writers


def _dead_pid() -> int:
    """The id of a process that has exited (and was reaped)."""
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def _write_keyed_store(out, record, value, barrier=None):
    """A stage's write of ``out``: ``record`` is what its key hashes. With ``barrier``,
    the writer waits for the other one before finishing, so both rename at once."""
    with atomic_store(out, attrs={"stage": "x", "record": record}) as group:
        write_array(group, "data", np.full(1000, value, np.float32))
        if barrier is not None:
            barrier.wait(timeout=120)


def test_two_interleaved_writers_of_one_keyed_store_both_finish_and_one_store_remains(
    tmp_path, caplog
):
    out = tmp_path / "stage" / "key.zarr"
    record = {"stage": "x", "params": {"k": 1}}
    first = atomic_store(out, attrs={"stage": "x", "record": record})
    second = atomic_store(out, attrs={"stage": "x", "record": record})
    group_a = first.__enter__()
    group_b = second.__enter__()  # before: removed the first writer's <out>.tmp
    assert len(temporary_paths(out)) == 2
    write_array(group_a, "data", np.arange(10))
    write_array(group_b, "data", np.arange(10))
    first.__exit__(None, None, None)
    assert out.exists()
    with caplog.at_level("INFO", logger="vprflow"):
        second.__exit__(None, None, None)  # before: OSError: Directory not empty
    assert "finished by another run meanwhile" in caplog.text
    store = open_store(out)
    assert store.attrs["record"] == record
    np.testing.assert_array_equal(store["data"][...], np.arange(10))
    assert not temporary_paths(out)
    assert sorted(p.name for p in out.parent.iterdir()) == ["key.zarr"]


def test_two_processes_racing_to_write_one_keyed_store_both_succeed(tmp_path):
    out = tmp_path / "stage" / "key.zarr"
    record = {"stage": "x", "params": {"k": 2}}
    context = multiprocessing.get_context("spawn")
    barrier = context.Barrier(2)
    writers = [
        context.Process(target=_write_keyed_store, args=(out, record, 7.0, barrier))
        for _ in range(2)
    ]
    for writer in writers:
        writer.start()
    for writer in writers:
        writer.join(timeout=120)
    assert [w.exitcode for w in writers] == [0, 0]
    store = open_store(out)
    assert store.attrs["record"] == record
    np.testing.assert_array_equal(store["data"][...], np.full(1000, 7.0, np.float32))
    assert sorted(p.name for p in out.parent.iterdir()) == ["key.zarr"]


def test_a_store_with_another_record_at_the_output_is_replaced(tmp_path):
    out = tmp_path / "key.zarr"
    _write_keyed_store(out, {"params": {"k": 1}}, 1.0)
    _write_keyed_store(out, {"params": {"k": 2}}, 2.0)
    store = open_store(out)
    assert store.attrs["record"] == {"params": {"k": 2}}
    np.testing.assert_array_equal(store["data"][...], np.full(1000, 2.0, np.float32))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["key.zarr"]


def test_a_damaged_store_with_the_same_record_is_replaced_not_kept(tmp_path):
    out = tmp_path / "key.zarr"
    record = {"params": {"k": 1}}
    _write_keyed_store(out, record, 1.0)
    chunk = next(p for p in (out / "data").rglob("*") if p.is_file() and p.name != "zarr.json")
    chunk.unlink()  # a lost chunk: open_store refuses the store
    _write_keyed_store(out, record, 1.0)
    np.testing.assert_array_equal(open_store(out)["data"][...], np.full(1000, 1.0, np.float32))


def test_only_temporaries_without_a_live_writer_are_removed_at_job_start(tmp_path, caplog):
    from vprflow.core.files import host_name

    out = tmp_path / "key.zarr"
    host = host_name()
    live = out.with_name(f"key.{host}-{os.getppid()}-0123abcd.zarr.tmp")
    dead = out.with_name(f"key.{host}-{_dead_pid()}-0123abcd.zarr.tmp")
    dead_aside = out.with_name(f"key.{host}-{_dead_pid()}-4567cdef.zarr.old")
    elsewhere_fresh = out.with_name("key.other-node-17-89abcdef.zarr.tmp")
    elsewhere_old = out.with_name("key.other-node-18-89abcdef.zarr.tmp")
    unrelated = out.with_name("key2.other-node-18-89abcdef.zarr.tmp")
    for path in (live, dead, dead_aside, elsewhere_fresh, elsewhere_old, unrelated):
        (path / "data").mkdir(parents=True)
    two_days_ago = time.time() - 2 * 24 * 3600
    for path in (elsewhere_old / "data", elsewhere_old):
        os.utime(path, (two_days_ago, two_days_ago))
    with caplog.at_level("INFO", logger="vprflow"):
        _write_keyed_store(out, {"params": {}}, 0.0)
    assert live.exists() and elsewhere_fresh.exists() and unrelated.exists()
    assert not dead.exists() and not dead_aside.exists() and not elsewhere_old.exists()
    said = f"another run is writing {out} (pid {os.getppid()} on {host}, in {live.name})"
    assert said in caplog.text and "--nolock bypasses it" in caplog.text
    assert open_store(out).attrs["record"] == {"params": {}}


def test_a_missing_store_while_two_runs_of_the_folder_go_on_names_both_and_nolock(
    tmp_path, monkeypatch
):
    """Another run's Snakemake deleted the store before its job began writing it: no
    temporary names a writer, the two runs' markers do."""
    from vprflow.core.files import host_name
    from vprflow.core.runs import RUNS

    monkeypatch.chdir(tmp_path)
    (tmp_path / RUNS).mkdir(parents=True)
    for pid in (os.getppid(), os.getpid()):
        (tmp_path / RUNS / f"{host_name()}-{pid}-0123abcd.json").write_text("{}")
    with pytest.raises(FileNotFoundError) as raised:
        open_store("results/cache/x/key.zarr")
    message = str(raised.value)
    assert message.startswith("store results/cache/x/key.zarr does not exist: 2 runs of this")
    assert f"pid {os.getppid()} on {host_name()}" in message and "--nolock bypasses it" in message


def test_a_missing_store_that_another_run_is_writing_names_its_process_and_nolock(tmp_path):
    from vprflow.core.files import host_name

    out = tmp_path / "key.zarr"
    with pytest.raises(FileNotFoundError, match=r"has its stage run\?"):
        open_store(out)
    live = out.with_name(f"key.{host_name()}-{os.getppid()}-0123abcd.zarr.tmp")
    live.mkdir()
    with pytest.raises(FileNotFoundError) as raised:
        open_store(out)
    assert str(raised.value) == (
        f"store {out} does not exist: another run is writing it (pid {os.getppid()} on "
        f"{host_name()}). Two runs of one folder delete each other's stores; Snakemake's "
        "lock prevents this, --nolock bypasses it"
    )


def test_a_store_replaced_under_every_rename_names_concurrent_runs_and_nolock(
    tmp_path, monkeypatch
):
    out = tmp_path / "key.zarr"
    _write_keyed_store(out, {"params": {"k": 1}}, 1.0)
    real_replace = os.replace

    def contested(source, target):
        if Path(target) == out:  # another run always renames its store in first
            raise OSError(errno.ENOTEMPTY, "Directory not empty", str(target))
        if Path(source) == out:  # ... and moves it away before we can
            raise FileNotFoundError(source)
        real_replace(source, target)

    monkeypatch.setattr(stores.os, "replace", contested)
    with pytest.raises(stores.ConcurrentWriteError, match="do not use --nolock for concurrent"):
        _write_keyed_store(out, {"params": {"k": 2}}, 2.0)
    monkeypatch.undo()
    assert not temporary_paths(out)


@pytest.mark.parametrize("node", ["group", "array"])
def test_set_attrs_leaves_the_zarr_json_of_attrs_update_in_one_write(tmp_path, monkeypatch, node):
    import zarr

    def made(name: str):
        group = zarr.open_group(str(tmp_path / name), mode="w", attributes={"stage": "x"})
        if node == "group":
            return group, tmp_path / name / "zarr.json"
        array = group.create_array("a", shape=(2,), dtype=np.float32, attributes={"n": 1})
        return array, tmp_path / name / "a" / "zarr.json"

    values = {"grid": [15, 20], "stage": "y", "dim": 104}
    reference, reference_json = made("update.zarr")
    reference.attrs.update(values)
    writes = []
    update = type(reference).update_attributes
    monkeypatch.setattr(
        type(reference), "update_attributes", lambda n, a: writes.append(a) or update(n, a)
    )
    target, target_json = made("set.zarr")
    stores.set_attrs(target, **values)
    assert len(writes) == 1
    assert target_json.read_text() == reference_json.read_text()
    assert dict(target.attrs) == dict(reference.attrs)

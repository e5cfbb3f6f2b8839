"""Atomic Zarr stores, ragged arrays and packed masks (exact round trips)."""

from __future__ import annotations

import numpy as np
import pytest

from vprflow import stores
from vprflow.stores import (
    RaggedWriter,
    atomic_store,
    open_store,
    pack_masks,
    read_ragged,
    temporary_path,
    unpack_masks,
    write_array,
)


class Boom(RuntimeError):
    pass


def test_failed_block_leaves_no_store(tmp_path):
    out = tmp_path / "stage" / "key.zarr"
    with pytest.raises(Boom), atomic_store(out, attrs={"stage": "x"}) as group:
        write_array(group, "data", np.arange(10))
        assert temporary_path(out).exists() and not out.exists()
        raise Boom("interrupted")
    assert not out.exists()
    assert not temporary_path(out).exists()
    with pytest.raises(FileNotFoundError, match="does not exist"):
        open_store(out)


def test_successful_block_appears_atomically_and_stale_tmp_is_removed(tmp_path):
    out = tmp_path / "key.zarr"
    stale = temporary_path(out)
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


@pytest.mark.parametrize("chunk_rows", [1, 4, 7, 1000])
def test_ragged_writer_round_trip_with_many_small_appends(tmp_path, chunk_rows):
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
        np.testing.assert_array_equal(read_ragged(store, "rows", i), block)
    np.testing.assert_array_equal(store["rows"][...], np.concatenate(blocks))


def test_a_failing_stage_leaves_no_store_behind_its_background_writes(tmp_path):
    out = tmp_path / "d.zarr"
    with pytest.raises(RuntimeError, match="late failure"):
        with atomic_store(out) as group:
            writer = RaggedWriter(group, "rows", (64,), np.float32, chunk_rows=8)
            for _ in range(40):  # several whole chunks, each written in the background
                writer.append(np.ones((3, 64), np.float32))
            raise RuntimeError("late failure")
    assert not out.exists() and not stores.temporary_path(out).exists()


def test_ragged_writer_casts_to_its_dtype(tmp_path):
    with atomic_store(tmp_path / "r.zarr") as group:
        writer = RaggedWriter(group, "ids", (), np.int64, 3)
        writer.append(np.array([1.0, 2.0]))
        writer.append(np.array([7]))
        writer.close()
    store = open_store(tmp_path / "r.zarr")
    assert store["ids"].dtype == np.int64
    np.testing.assert_array_equal(read_ragged(store, "ids", 0), [1, 2])
    np.testing.assert_array_equal(read_ragged(store, "ids", 1), [7])


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
    assert not out.exists() and not stores.temporary_path(out).exists()


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

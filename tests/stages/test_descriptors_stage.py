"""The descriptors stage (vprflow.stages.descriptors) against direct computations: per-
segment and global descriptors, their dtype, threads and compression."""

from __future__ import annotations

import numpy as np
import pytest
from toy_pipeline import N_PLACES, stage_path

from vprflow.core import stores
from vprflow.stages.descriptors import compute_descriptors
from vprflow.stages.jobs import Job
from vprflow.stages.readers import read_centres, read_features, read_masks, read_pca


def test_segvlad_descriptors_are_the_projected_segment_vlads(pipeline):
    """The descriptors stage equals image_segvlad + the PCA projection, per image."""
    from vprflow.aggregation.aggregators import vlad_input
    from vprflow.aggregation.segvlad import image_segvlad

    features = stores.open_store(stage_path(pipeline, "features"))
    segments = stores.open_store(stage_path(pipeline, "segments"))
    centres = read_centres(stage_path(pipeline, "vocabulary"))
    pca = read_pca(stage_path(pipeline, "pca"))
    group = stores.open_store(stage_path(pipeline, "descriptors"))
    offsets = np.asarray(group["descriptors_offsets"][...])
    for index in (1, 2 * N_PLACES - 1):
        vectors = image_segvlad(
            vlad_input(read_features(features, index), {"normalize_descriptors": True}),
            read_masks(segments, index),
            centres,
            (48, 64),
            8,
            1,
        )
        stored = np.asarray(group["descriptors"][offsets[index] : offsets[index + 1]])
        np.testing.assert_allclose(stored, pca.transform(vectors), rtol=1e-5, atol=1e-5)


def test_segment_gem_descriptors_are_each_segments_gem_projected(pipeline):
    """A second per-segment aggregator on SegVLAD's segment path: its descriptors equal a
    float64 GeM over each segment's patches (channel-normalised tokens), L2-normalised,
    then its own PCA, per image; its recall comes from the segment search and voting."""
    from vprflow.aggregation.segvlad import mask_patch_membership

    features = stores.open_store(stage_path(pipeline, "features", "segment_gem"))
    segments = stores.open_store(stage_path(pipeline, "segments", "segment_gem"))
    pca = read_pca(stage_path(pipeline, "pca", "segment_gem"))
    group = stores.open_store(stage_path(pipeline, "descriptors", "segment_gem"))
    offsets = np.asarray(group["descriptors_offsets"][...])
    for index in (0, 2 * N_PLACES - 2):
        grid = read_features(features, index).astype(np.float64)
        tokens = (grid / (np.linalg.norm(grid, axis=(0, 1)) + 1e-10)).reshape(-1, grid.shape[2])
        members = mask_patch_membership(read_masks(segments, index), (48, 64), (6, 8), 8)
        expected = []
        for member in members:
            mean = (tokens[member] ** 3).mean(axis=0)
            pooled = np.sign(mean) * np.abs(mean) ** (1 / 3)
            expected.append(pooled / np.linalg.norm(pooled))
        stored = np.asarray(group["descriptors"][offsets[index] : offsets[index + 1]])
        np.testing.assert_allclose(stored, pca.transform(np.array(expected)), atol=2e-5)
    recall = stores.open_store(stage_path(pipeline, "recall", "segment_gem"))
    assert "search" in dict(recall.attrs["record"]["inputs"])


def test_float16_segment_descriptors_are_the_float32_ones_rounded(pipeline, tmp_path):
    plan, runner, _, _ = pipeline
    (stage,) = [
        s
        for s in plan.stages["descriptors"].values()
        if s.record["params"]["aggregator"] == "segvlad"
    ]
    inputs = {name: runner.path(*ref) for name, ref in stage.inputs.items()}
    params = {**stage.record, "params": {**stage.record["params"], "store_dtype": "float16"}}
    out = str(tmp_path / "half.zarr")
    compute_descriptors(Job(params, inputs, out))
    half = stores.open_store(out)["descriptors"]
    full = stores.open_store(stage_path(pipeline, "descriptors"))["descriptors"]
    assert half.dtype == np.float16
    np.testing.assert_array_equal(np.asarray(half[...]), np.asarray(full[...]).astype(np.float16))


@pytest.mark.parametrize("way", ["as probed", "on the pool", "on the calling thread"])
@pytest.mark.parametrize("method", ["segvlad", "anyloc_vlad"])
def test_descriptors_are_the_same_bits_with_more_threads(
    pipeline, tmp_path, monkeypatch, method, way
):
    """Images computed with three threads, on a pool of them or on the calling thread
    (whichever the probes find faster), store what the sharded one-thread runs stored."""
    from vprflow.stages import descriptors

    forced = {
        "on the pool": descriptors.in_order,
        "on the calling thread": lambda pool, function, items, workers: map(function, items),
    }
    if way in forced:
        monkeypatch.setattr(descriptors, "fastest_in_order", forced[way])
    plan, runner, _, _ = pipeline
    (stage,) = [
        s for s in plan.stages["descriptors"].values() if s.record["params"]["aggregator"] == method
    ]
    inputs = {name: runner.path(*ref) for name, ref in stage.inputs.items()}
    out = str(tmp_path / "threads.zarr")
    compute_descriptors(Job(stage.record, inputs, out, threads=3))
    threaded = stores.open_store(out)
    stored = stores.open_store(stage_path(pipeline, "descriptors", method))
    for name, array in stores.array_items(stored):
        np.testing.assert_array_equal(np.asarray(threaded[name]), np.asarray(array), err_msg=name)


def test_descriptor_stores_are_compressed_fast_and_read_back_as_zarr_reads_them(pipeline):
    """Every descriptors store (global, per segment, projected) uses FAST_COMPRESSORS;
    vprflow's row reader returns the bits zarr's own read does."""
    for method in ("segvlad", "anyloc_vlad", "segment_gem", "gem", "snsm"):
        group = stores.open_store(stage_path(pipeline, "descriptors", method))
        assert tuple(group["descriptors"].raw.compressors) == stores.FAST_COMPRESSORS, method
        rows = np.asarray(group["descriptors"][...])
        assert rows.tobytes() == np.asarray(group["descriptors"].raw[...]).tobytes(), method


class Ticks:
    """A clock that advances only when told: an item computed on the ``slow`` way (the
    pool's threads or the caller's) costs ``cost`` ticks, on the other 1."""

    def __init__(self, slow: str, cost: float = 10):
        import threading

        self.now, self.slow, self.cost, self.lock = 0, slow, cost, threading.Lock()

    def __call__(self) -> float:
        return self.now

    def compute(self, item: int) -> tuple[int, str]:
        import threading

        on_pool = threading.current_thread().name.startswith("probe-pool")
        with self.lock:
            self.now += self.cost if on_pool == (self.slow == "pool") else 1
        return item * item, "pool" if on_pool else "caller"


@pytest.mark.parametrize("slow", ["pool", "caller"])
@pytest.mark.parametrize(("cost", "rounds_run"), [(10, 1), (1.2, 3)])
@pytest.mark.parametrize("n_items", [0, 1, 5, 30, 200])
def test_fastest_in_order_yields_every_result_in_order_computed_the_faster_way(
    slow, cost, rounds_run, n_items
):
    """One way 10 times slower is clear after one round of probes; 1.2 times slower
    takes all three."""
    from concurrent.futures import ThreadPoolExecutor

    from vprflow.stages.descriptors import fastest_in_order

    ticks = Ticks(slow, cost)
    probe, rounds = 4, 3
    with ThreadPoolExecutor(2, thread_name_prefix="probe-pool") as pool:
        got = list(fastest_in_order(pool, ticks.compute, range(n_items), 2, probe, rounds, ticks))
    assert [value for value, _ in got] == [i * i for i in range(n_items)]
    ways = [way for _, way in got]
    # The first item alone on the calling thread, then the probes in turn, then the
    # faster way for the rest.
    expected = ["caller"] + (["caller"] * probe + ["pool"] * probe) * rounds_run
    faster = "caller" if slow == "pool" else "pool"
    expected += [faster] * max(0, n_items - len(expected))
    assert ways == expected[:n_items]

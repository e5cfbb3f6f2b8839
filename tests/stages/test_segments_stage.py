"""The segments stage (vprflow.stages.segments): SLIC's masks partition every image, in
image order, and either masks layout gives every later stage the same values."""

from __future__ import annotations

import numpy as np
from toy_pipeline import N_PLACES, Runner, pipeline_config, stage_path

from vprflow.core import stores
from vprflow.planning.plan import build_plan
from vprflow.stages.readers import read_masks


def test_slic_segments_partition_every_image(pipeline):
    group = stores.open_store(stage_path(pipeline, "segments"))
    assert int(group["masks_offsets"][-1]) == group["masks"].shape[0]
    for index in range(2 * N_PLACES):
        masks = read_masks(group, index)
        assert masks.shape[1:] == (48, 64)
        np.testing.assert_array_equal(masks.sum(axis=0), 1)  # SLIC labels every pixel once


def test_segments_come_in_image_order_with_the_next_batch_read_while_one_is_segmented():
    import threading

    from vprflow.stages.segments import _segmented

    second_read = threading.Event()

    def read(indices):
        if indices[0] == 2:
            second_read.set()
        return [np.full((index + 1, 2, 2), True) for index in indices]

    def segment(images):
        if len(images[0]) == 1:  # the first batch waits until the second is being read
            assert second_read.wait(timeout=60), "the next batch was not read ahead"
        return images

    out = list(_segmented(read, segment, [0, 1, 2, 3, 4], batch_size=2))
    assert [index for index, _ in out] == [0, 1, 2, 3, 4]
    assert [len(masks) for _, masks in out] == [1, 2, 3, 4, 5]


def test_masks_laid_out_per_image_give_every_later_store_the_packed_ones_values(pipeline, tmp_path):
    """The toy pipeline again with masks_layout per_image (its stores of other keys
    taken from the packed run): new segments, PCA, descriptors, search and recall
    stores, sharded as before, whose every array equals the packed run's."""
    plan, runner, _, root = pipeline
    per_image = build_plan(pipeline_config(root / "data", masks_layout="per_image"))
    again = Runner(per_image, root / "data", tmp_path)
    again.done.update(runner.done)
    compared = set()
    for packed_run, run in zip(plan.runs["toy"], per_image.runs["toy"], strict=True):
        stack = [(("recall", packed_run.recall_key), ("recall", run.recall_key))]
        while stack:
            (stage, packed_key), (_, key) = stack.pop()
            if packed_key == key or (stage, key) in compared:
                continue
            compared.add((stage, key))
            ours = stores.open_store(again.path(stage, key))
            theirs = stores.open_store(runner.path(stage, packed_key))
            for name, array in theirs.arrays():
                if stage == "segments" and name.startswith("masks"):
                    continue  # another layout: its masks are compared below
                np.testing.assert_array_equal(np.asarray(ours[name]), np.asarray(array))
            packed_inputs = plan.get(stage, packed_key).inputs
            for name, ref in per_image.get(stage, key).inputs.items():
                stack.append((packed_inputs[name], ref))
    assert {stage for stage, _ in compared} >= {"segments", "descriptors", "recall"}
    segments = [key for stage, key in compared if stage == "segments"]
    ours = stores.open_store(again.path("segments", segments[0]))
    assert "masks_counts" in ours
    theirs = stores.open_store(stage_path(pipeline, "segments"))
    for index in range(2 * N_PLACES):
        np.testing.assert_array_equal(read_masks(ours, index), read_masks(theirs, index))

"""The segments stage (vprflow.stages.segments): SLIC's masks partition every image, in
image order."""

from __future__ import annotations

import numpy as np
from toy_pipeline import N_PLACES, stage_path

from vprflow.core import stores
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

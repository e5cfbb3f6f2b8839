"""The stores' read side (vprflow.stages.readers) on the toy pipeline's stores."""

from __future__ import annotations

import numpy as np
import pytest
from toy_pipeline import stage_path

from vprflow.core import stores
from vprflow.stages.readers import read_features


def test_the_feature_reader_gives_each_images_features_read_only(pipeline):
    from vprflow.stages.readers import FeatureReader

    group = stores.open_store(stage_path(pipeline, "features", "anyloc_vlad"))
    per_image = 4 * int(np.prod(group["features"].shape[1:]))
    for block_bytes in (0, 3 * per_image, 64 << 20):  # one image, 3, all of them a read
        reader = FeatureReader(group, block_bytes)
        for index in [0, 1, 5, 4, 11, 2]:  # forwards, back, across blocks
            grid = reader(index)
            np.testing.assert_array_equal(grid, read_features(group, index))
            assert grid.dtype == np.float32 and not grid.flags.writeable
            with pytest.raises(ValueError, match="read-only"):
                grid += 1

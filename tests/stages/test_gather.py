"""The gather of a stage's shards (vprflow.stages.gather)."""

from __future__ import annotations

import numpy as np

from vprflow.core import stores
from vprflow.stages.gather import gather


def test_gather_of_one_shard_renames_it_with_the_gathered_attributes(tmp_path):
    shard = tmp_path / "x.shards" / "0-3.zarr"
    rows = np.arange(12, dtype=np.float32).reshape(6, 2)
    with stores.atomic_store(shard, {"stage": "descriptors", "start": 0, "stop": 3}) as group:
        writer = stores.RaggedWriter(group, "descriptors", (2,), np.float32, chunk_rows=4)
        for block in (rows[:1], rows[1:1], rows[1:]):
            writer.append(block)
        writer.close()
    out = tmp_path / "x.zarr"
    gather([str(shard)], {"stage": "descriptors", "key": "x"}, str(out))
    assert not shard.exists()
    group = stores.open_store(out)
    assert dict(group.attrs) == {
        "stage": "descriptors",
        "record": {"stage": "descriptors", "key": "x"},
        "shards": [[0, 3]],
    }
    np.testing.assert_array_equal(group["descriptors"][...], rows)
    np.testing.assert_array_equal(group["descriptors_offsets"][...], [0, 1, 1, 6])

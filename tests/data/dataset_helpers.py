"""Small dataset folders and exact ground-truth comparison, shared by test_datasets.py,
test_ground_truth.py and test_positions.py."""

from __future__ import annotations

import numpy as np
from workflow_helpers import dataset_spec

SPEC = dataset_spec(path="ds", reference="ref", query="query", paired=False)


def assert_truth_equal(truth, expected):
    assert len(truth) == len(expected)
    for q, (got, want) in enumerate(zip(truth, expected, strict=True)):
        assert got.dtype == np.int64, q
        np.testing.assert_array_equal(got, np.asarray(sorted(want), dtype=np.int64), err_msg=q)


def touch_images(folder, names):
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        (folder / name).write_bytes(b"")


def utm_name(easting, northing, stem):
    return f"@{easting:010.2f}@{northing:.2f}@17@T@{stem}.jpg"

"""Ground-truth kinds (vprflow.data.ground_truth) against direct formulas: exact integer
index sets, the safe VPR-Bench loader against live malicious pickles, errors that name
the file, row or folder at fault, and the table of kinds against the schema.

Tests marked ``data`` read the real files under ``$VPRFLOW_DATA`` (the ``data_root``
fixture of conftest.py): skipped when it is unset or not a folder, but failed under
``CI=true`` (CI must not lose them).
"""

from __future__ import annotations

import os
import pickle
import shlex
from pathlib import Path

import numpy as np
import pytest
from dataset_helpers import SPEC, assert_truth_equal, touch_images, utm_name
from workflow_helpers import SCHEMA, dataset_spec, truth_spec

from vprflow.core.errors import DatasetError
from vprflow.data.datasets import DatasetFiles, list_dataset
from vprflow.data.ground_truth import (
    KINDS,
    frame_window_ground_truth,
    ground_truth,
    ground_truth_files,
    ground_truth_rule,
    load_object_npy,
    pairs_ground_truth,
    vprbench_ground_truth,
)

# ------------------------------------------------------------------ vprbench


def write_vprbench(path, rows):
    """A VPR-Bench style object array ``[[q, [refs]], ...]`` saved with pickles."""
    table = np.empty((len(rows), 2), dtype=object)
    for i, (q, refs) in enumerate(rows):
        table[i, 0] = q
        table[i, 1] = refs
    np.save(path, table, allow_pickle=True)
    return path


def test_vprbench_ground_truth_matches_file_rows(tmp_path):
    rng = np.random.default_rng(0)
    n_query, n_ref = 12, 15
    rows = []
    for q in rng.permutation(n_query):  # rows need not be in query order
        refs = [int(r) for r in rng.choice(n_ref, rng.integers(0, 5), replace=False)]
        rows.append((int(q), refs))
    rows[0] = (rows[0][0], [np.int64(3), np.int64(3), np.int64(1)])  # numpy ints, duplicate
    # Other legitimate forms: integral floats, a tuple, 1-D arrays, a single index, none.
    rows[1] = (float(rows[1][0]), (np.float64(4.0), 2.0, np.uint8(7)))
    rows[2] = (np.int32(rows[2][0]), np.array([5, 6], dtype=np.int16))
    rows[3] = (np.float32(rows[3][0]), np.array([8.0, 9.0]))
    rows[4] = (rows[4][0], np.int64(11))
    rows[5] = (rows[5][0], [])
    path = write_vprbench(tmp_path / "gt.npy", rows)
    expected = [None] * n_query
    for q, refs in rows:
        expected[int(q)] = {int(r) for r in np.reshape(refs, -1)}
    assert_truth_equal(vprbench_ground_truth(path, n_query, n_ref), expected)


def test_vprbench_row_count_must_match_queries(tmp_path):
    path = write_vprbench(tmp_path / "gt.npy", [(0, [0]), (1, [1]), (2, [2])])
    with pytest.raises(DatasetError, match="3 ground-truth rows but the dataset has 4 query"):
        vprbench_ground_truth(path, 4, 4)


def test_vprbench_out_of_range_references(tmp_path, caplog):
    # The published 17places file lists references 406 and 407 of a 406-image set.
    path = write_vprbench(tmp_path / "gt.npy", [(0, [0, 1]), (1, [2, 4, 5]), (2, [3])])
    with pytest.raises(DatasetError, match=r"row 1: query 1 lists reference indices \[4, 5\]"):
        vprbench_ground_truth(path, 3, 4)
    with caplog.at_level("WARNING", logger="vprflow"):
        truth = vprbench_ground_truth(path, 3, 4, drop_out_of_range=True)
    assert_truth_equal(truth, [{0, 1}, {2}, {3}])
    assert "dropped 2 reference index(es) past the last of the 4 references" in caplog.text
    assert "row 1: 4, row 1: 5" in caplog.text


@pytest.mark.parametrize("drop", [False, True])
def test_a_negative_reference_index_is_refused_naming_file_row_and_value_even_when_dropping(
    tmp_path, drop
):
    # drop_out_of_range used to drop -1 silently: the query lost a positive unnoticed.
    path = write_vprbench(tmp_path / "gt.npy", [(0, [0, 1]), (1, [2]), (2, [-1, 3])])
    message = r"gt.npy row 2: query 2 lists negative reference indices \[-1\]"
    with pytest.raises(DatasetError, match=message):
        vprbench_ground_truth(path, 3, 4, drop_out_of_range=drop)


@pytest.mark.parametrize("index", [10**6, 1e30])
def test_drop_out_of_range_refuses_an_index_far_past_the_last_reference(tmp_path, index):
    # Not a sequence that ran on past the end (17places: 406 and 407 of 406) but a file
    # for another reference set, or a damaged one: dropping it hid the damage.
    path = write_vprbench(tmp_path / "gt.npy", [(0, [0, 1]), (1, [2, index]), (2, [3])])
    with pytest.raises(DatasetError, match=r"gt.npy row 1: query 1 lists reference indices \[1"):
        vprbench_ground_truth(path, 3, 4, drop_out_of_range=True)
    with pytest.raises(DatasetError, match="longest list of positives"):
        vprbench_ground_truth(path, 3, 4, drop_out_of_range=True)


def test_vprbench_bad_query_index_and_missing_file(tmp_path):
    path = write_vprbench(tmp_path / "gt.npy", [(0, [0]), (5, [1])])
    with pytest.raises(DatasetError, match="row 1 has query index 5, outside"):
        vprbench_ground_truth(path, 2, 2)
    with pytest.raises(DatasetError, match="does not exist"):
        vprbench_ground_truth(tmp_path / "missing.npy", 2, 2)
    (tmp_path / "junk.npy").write_bytes(b"not a numpy file at all")
    with pytest.raises(DatasetError, match="junk.npy"):
        vprbench_ground_truth(tmp_path / "junk.npy", 2, 2)


def ragged(*lists):
    """A 1-D object array of lists (what ``np.array`` makes of rows of unequal length)."""
    array = np.empty(len(lists), dtype=object)
    for i, item in enumerate(lists):
        array[i] = item
    return array


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ((1, [0, 2.5]), r"reference index 2\.5 is not an integer"),
        ((1, [np.float64(2.5)]), r"reference index np\.float64\(2\.5\) is not an integer"),
        ((1, [0, float("nan")]), r"reference index nan is not an integer"),
        ((1, np.array([0.0, np.inf])), r"reference index np\.float64\(inf\) is not an integer"),
        ((1, [0, True]), r"reference index True is a boolean"),
        ((1, np.array([False, True])), r"reference index np\.False_ is a boolean"),
        ((1, True), r"reference index True is a boolean"),
        ((1.5, [0]), r"query index 1\.5 is not an integer"),
        ((True, [0]), r"query index True is a boolean"),
    ],
)
def test_vprbench_fractional_nan_or_boolean_indices_are_refused_naming_row_and_value(
    tmp_path, row, message
):
    # Today 2.5 is truncated to 2 (every positive off by one) and True read as 1.
    path = write_vprbench(tmp_path / "gt.npy", [(0, [1]), row])
    with pytest.raises(DatasetError, match=rf"gt\.npy row 1: {message}"):
        vprbench_ground_truth(path, 2, 5)


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ((None, [0]), r"query index None is not an integer"),
        (("1", [0]), r"query index '1' is not an integer"),
        ((1, None), r"positives None: expected a list of reference indices"),
        ((1, "0 1"), r"positives '0 1': expected a list"),
        ((1, b"01"), r"positives b'01': expected a list"),
        ((1, {0: 1}), r"positives \{0: 1\}: expected a list"),
        ((1, ["0"]), r"reference index '0' is not an integer"),
        ((1, [0, [1, 2]]), r"reference index \[1, 2\] is not an integer"),
        ((1, ragged([1, 2], [3])), r"reference index \[1, 2\] is not an integer"),
        ((1, np.array([[0, 1]])), r"positives are a 2-D array of shape \(1, 2\)"),
    ],
)
def test_vprbench_values_that_are_not_indices_are_refused_naming_row_field_and_value(
    tmp_path, row, message
):
    path = write_vprbench(tmp_path / "gt.npy", [(0, [1]), row])
    with pytest.raises(DatasetError, match=rf"gt\.npy row 1: {message}"):
        vprbench_ground_truth(path, 2, 5)


def test_vprbench_duplicate_query_rows_are_rejected_with_rows_and_gaps(tmp_path):
    # Query 0 twice, query 9 absent: today's "last row wins" would lose query 0's
    # first positives and silently evaluate 9 queries.
    rows = [(q, [q]) for q in range(9)] + [(0, [5])]
    path = write_vprbench(tmp_path / "gt.npy", rows)
    with pytest.raises(DatasetError, match=r"query 0 in rows \[0, 9\].*no row: \[9\]"):
        vprbench_ground_truth(path, 10, 10)


def test_ground_truth_without_any_positive_names_the_file(tmp_path):
    write_vprbench(tmp_path / "gt.npy", [(0, []), (1, [2])])  # 2 is past the end: dropped
    files = DatasetFiles(reference=[Path("a.jpg"), Path("b.jpg")], query=[Path("c"), Path("d")])
    spec = truth_spec(kind="vprbench", file="gt.npy", drop_out_of_range=True)
    with pytest.raises(DatasetError, match=r"gt\.npy: no query has a positive"):
        ground_truth(files, spec, tmp_path)


def test_plain_numeric_npy_loads_without_pickle(tmp_path):
    np.save(tmp_path / "a.npy", np.arange(6).reshape(3, 2))
    np.testing.assert_array_equal(load_object_npy(tmp_path / "a.npy"), np.arange(6).reshape(3, 2))


class _RunsCommand:
    """Unpickling this object runs a shell command (the classic malicious pickle)."""

    def __init__(self, command):
        self.command = command

    def __reduce__(self):
        return (os.system, (self.command,))


def malicious_files(tmp_path, marker):
    command = f"touch {shlex.quote(str(marker))}"
    header = {"descr": "|O", "fortran_order": False, "shape": (1, 2)}
    whole = tmp_path / "whole.npy"  # the entire payload is the malicious object
    with open(whole, "wb") as f:
        np.lib.format.write_array_header_1_0(f, header)
        pickle.dump(_RunsCommand(command), f, protocol=3)
    nested = tmp_path / "nested.npy"  # a genuine object array with one bad element
    table = np.empty((1, 2), dtype=object)
    table[0, 0] = 0
    table[0, 1] = _RunsCommand(command)
    np.save(nested, table, allow_pickle=True)
    return [whole, nested]


def test_safe_loader_refuses_malicious_pickles(tmp_path):
    marker = tmp_path / "pwned"
    files = malicious_files(tmp_path, marker)
    # The payloads are live: numpy's own pickle loading runs the command.
    np.load(files[0], allow_pickle=True)
    assert marker.exists()
    marker.unlink()
    for path in files:
        with pytest.raises(DatasetError, match="refusing to load"):
            load_object_npy(path)
        with pytest.raises(DatasetError):
            vprbench_ground_truth(path, 1, 1)
        assert not marker.exists()


# ------------------------------------------------------------------ other kinds


@pytest.mark.parametrize(("n_query", "n_ref", "radius"), [(20, 20, 2), (9, 14, 3), (14, 9, 0)])
def test_frame_window_matches_direct_formula(n_query, n_ref, radius):
    expected = [{j for j in range(n_ref) if abs(i - j) <= radius} for i in range(n_query)]
    assert_truth_equal(frame_window_ground_truth(n_query, n_ref, radius), expected)


def test_pairs_ground_truth():
    assert_truth_equal(pairs_ground_truth(5, 5), [{i} for i in range(5)])
    with pytest.raises(DatasetError, match="has 5 query images and 4 reference images"):
        pairs_ground_truth(5, 4)


def test_ground_truth_dispatch(tmp_path):
    files = DatasetFiles(
        reference=[tmp_path / utm_name(0, 0, "r0"), tmp_path / utm_name(30, 0, "r1")],
        query=[tmp_path / utm_name(1, 0, "q0"), tmp_path / utm_name(29, 0, "q1")],
    )
    write_vprbench(tmp_path / "gt.npy", [(0, [1]), (1, [0, 1])])
    cases = {
        "vprbench": (truth_spec(kind="vprbench", file="gt.npy"), [{1}, {0, 1}]),
        "frame_window": (truth_spec(kind="frame_window", radius=0), [{0}, {1}]),
        "utm": (truth_spec(kind="utm", radius=5), [{0}, {1}]),
        "pairs": (truth_spec(kind="pairs"), [{0}, {1}]),
    }
    for spec, expected in cases.values():
        assert_truth_equal(ground_truth(files, spec, tmp_path), expected)
    with pytest.raises(DatasetError, match="unknown ground-truth kind"):
        ground_truth(files, {"kind": "gps"}, tmp_path)


@pytest.mark.parametrize(
    ("spec", "missing"),
    [
        ({"kind": "utm"}, "radius"),
        ({"kind": "vprbench", "file": "gt.npy"}, "drop_out_of_range"),
    ],
)
def test_a_ground_truth_setting_left_unfilled_fails_with_key_error_not_a_restated_default(
    tmp_path, spec, missing
):
    # The schema fills these before any stage runs; a spec that skipped it is a bug.
    files = DatasetFiles(reference=[tmp_path / utm_name(0, 0, "r")], query=[tmp_path / "q"])
    write_vprbench(tmp_path / "gt.npy", [(0, [0])])
    with pytest.raises(KeyError, match=missing):
        ground_truth(files, spec, tmp_path)


@pytest.mark.parametrize("radius", [0.9, 2.5, True])
def test_a_fractional_frame_window_is_refused_naming_key_and_value(tmp_path, radius):
    # int(0.9) ran as +-0 while the table said +-0.9.
    files = DatasetFiles([tmp_path / f"r{i}" for i in range(4)], [tmp_path / "q"])
    spec = truth_spec(kind="frame_window", radius=radius)
    message = rf"ground_truth.radius: {radius!r} is not a whole number of frames"
    for compute in (
        lambda: ground_truth(files, spec, tmp_path),
        lambda: ground_truth_rule(spec),
        lambda: ground_truth_files(tmp_path, {"path": ".", "ground_truth": spec}),
    ):
        with pytest.raises(DatasetError, match=message):
            compute()


def test_the_rule_states_the_frame_window_as_applied():
    # 2.0 frames is applied as 2 and so named; the truth equals the integer rule's.
    files = DatasetFiles([Path(f"r{i}") for i in range(6)], [Path(f"q{i}") for i in range(6)])
    spec = truth_spec(kind="frame_window", radius=2.0)
    assert ground_truth_rule(spec) == "frame_window:+-2"
    expected = [set(t.tolist()) for t in frame_window_ground_truth(6, 6, 2)]
    assert_truth_equal(ground_truth(files, spec, Path(".")), expected)


def test_rows_given_as_integral_floats_are_read_and_fractional_ones_refused(tmp_path):
    # YAML reads 1.0 as a float, which the schema's integer admits; slicing with it failed
    # with numpy's "slice indices must be integers", naming nothing.
    write_vprbench(tmp_path / "gt.npy", [(q, [q]) for q in range(4)])
    files = DatasetFiles([tmp_path / f"r{i}" for i in range(4)], [tmp_path / "q0", tmp_path / "q1"])
    spec = truth_spec(kind="vprbench", file="gt.npy", rows=[1.0, 3.0], query_index="position")
    assert_truth_equal(ground_truth(files, spec, tmp_path), [{1}, {2}])
    spec["rows"] = [1, 2.5]
    with pytest.raises(DatasetError, match=r"ground_truth.rows: 2.5 is not a whole number"):
        ground_truth(files, spec, tmp_path)


def test_a_heading_limit_on_exif_positions_is_refused_naming_the_key(tmp_path):
    # EXIF gives no heading: the limit was named in the table and then failed unnamed.
    spec = {"kind": "coordinates", "source": "exif", "radius_m": 15, "max_heading_diff": 30}
    with pytest.raises(DatasetError, match=r"ground_truth.max_heading_diff: 30 is set but source"):
        ground_truth_rule(spec)


def test_every_kinds_rule_names_the_values_its_truth_applies():
    # The numbers in a rule are the ones the truth computes with, as numbers.
    rules = {
        "frame_window:+-3": truth_spec(kind="frame_window", radius=3.0),
        "utm:25m": truth_spec(kind="utm"),
        "utm:7.5m": truth_spec(kind="utm", radius=7.5),
        "coordinates:c.csv:25m,heading<=40deg": truth_spec(
            kind="coordinates", file="c.csv", radius_m=25.0, max_heading_diff=40
        ),
        "positions:ref_gt:10": truth_spec(
            kind="positions", reference_positions="ref_gt", query_positions="q_gt", radius=10.0
        ),
    }
    for rule, spec in rules.items():
        assert ground_truth_rule(spec) == rule


def test_the_utm_radius_default_comes_from_the_schema():
    assert truth_spec(kind="utm")["radius"] == 25
    assert truth_spec(kind="utm", radius=7)["radius"] == 7
    # frame_window requires its radius: the utm default never reaches it.
    assert "radius" not in truth_spec(kind="frame_window")


def test_no_ground_truth_gives_empty_lists_and_its_rule():
    files = DatasetFiles([Path("r0.jpg"), Path("r1.jpg")], [Path("q.jpg")])
    truth = ground_truth(files, {"kind": "none"}, Path("."))
    assert [t.tolist() for t in truth] == [[]]
    assert ground_truth_rule({"kind": "none"}) == "none"


def test_the_schema_admits_exactly_the_table_of_kinds():
    # The enum is filled from KINDS (config.load_schema): a kind the schema admits is
    # one ground_truth() computes, and the other way round.
    from vprflow.planning.config import load_schema

    dataset = load_schema(SCHEMA)["definitions"]["dataset"]["properties"]
    assert dataset["ground_truth"]["properties"]["kind"]["enum"] == list(KINDS)


# ------------------------------------------------------------------ images by folder in errors


SUBFOLDERS = "; images in subfolders are found too unless the dataset sets recursive: false"


def test_vprbench_row_count_mismatch_names_the_subfolder_holding_the_extra_queries(tmp_path):
    # The recursive search also finds query/extra/: the count alone does not say where.
    touch_images(tmp_path / "ds/ref", ["1.jpg", "2.jpg", "3.jpg"])
    touch_images(tmp_path / "ds/query", ["1.jpg", "2.jpg", "3.jpg"])
    touch_images(tmp_path / "ds/query/extra", ["1.jpg", "2.jpg"])
    write_vprbench(tmp_path / "ds/gt.npy", [(q, [q]) for q in range(3)])
    files = list_dataset(tmp_path, "toy", SPEC)
    with pytest.raises(DatasetError) as error:
        ground_truth(files, truth_spec(kind="vprbench", file="gt.npy"), tmp_path / "ds")
    assert str(error.value).endswith(
        f"gt.npy has 3 ground-truth rows but the dataset has 5 query images "
        f"(query/: 3, query/extra/: 2{SUBFOLDERS})"
    )


def test_vprbench_reference_out_of_range_names_the_folders_of_the_references(tmp_path):
    touch_images(tmp_path / "ds/ref/a", ["1.jpg", "2.jpg"])
    touch_images(tmp_path / "ds/ref/b", ["1.jpg"])
    touch_images(tmp_path / "ds/query", ["1.jpg", "2.jpg"])
    write_vprbench(tmp_path / "ds/gt.npy", [(0, [0]), (1, [3])])
    files = list_dataset(tmp_path, "toy", SPEC)
    # Side by side, neither folder inside the other: no word about subfolders.
    message = r"query 1 lists reference indices \[3\] but the dataset has 3 reference images "
    with pytest.raises(DatasetError, match=message + r"\(ref/a/: 2, ref/b/: 1\) \(set"):
        ground_truth(files, truth_spec(kind="vprbench", file="gt.npy"), tmp_path / "ds")


def test_pairs_count_mismatch_names_the_subfolder_holding_the_extra_images(tmp_path):
    # Not `paired` (which would refuse ir/old/a.png for want of a partner): the `pairs`
    # ground truth alone sees only the counts.
    spec = dict(SPEC, reference="vi", query="ir")
    touch_images(tmp_path / "ds/vi", ["a.png", "b.png"])
    touch_images(tmp_path / "ds/ir", ["a.png", "b.png"])
    touch_images(tmp_path / "ds/ir/old", ["a.png"])
    files = list_dataset(tmp_path, "toy", spec)
    with pytest.raises(DatasetError) as error:
        ground_truth(files, {"kind": "pairs"}, tmp_path / "ds")
    assert str(error.value).endswith(
        f"has 3 query images (ir/: 2, ir/old/: 1{SUBFOLDERS}) and 2 reference images"
    )


# ------------------------------------------------------------------ real data


@pytest.mark.data
def test_real_corridor_ground_truth(data_root):
    spec = dataset_spec(path="corridor", reference="ref", query="query", paired=False)
    files = list_dataset(data_root, "corridor", spec)
    assert len(files.reference) == len(files.query) == 111
    truth = ground_truth(
        files, truth_spec(kind="vprbench", file="ground_truth_new.npy"), data_root / "corridor"
    )
    assert len(truth) == 111
    # The corridor file is the +-2 frame rule.
    assert_truth_equal(truth, [set(t.tolist()) for t in frame_window_ground_truth(111, 111, 2)])


@pytest.mark.data
def test_real_17places_needs_drop_out_of_range(data_root):
    path = data_root / "17places" / "ground_truth_new.npy"
    raw = load_object_npy(path)
    assert sorted({int(r) for refs in raw[:, 1] for r in refs if int(r) >= 406}) == [406, 407]
    with pytest.raises(DatasetError, match="drop_out_of_range"):
        vprbench_ground_truth(path, 406, 406)
    truth = vprbench_ground_truth(path, 406, 406, drop_out_of_range=True)
    assert len(truth) == 406 and max(int(t.max()) for t in truth) == 405
    assert_truth_equal(truth, [set(t.tolist()) for t in frame_window_ground_truth(406, 406, 2)])

"""Dataset layouts, ground-truth kinds and image reading against direct formulas.

Ground truth is exact (integer index sets). Images: 8-bit values must equal v / 255
and 16-bit values v / 65535 within 1e-7 (float32 rounding); resizing a linear ramp
must reproduce the ramp at the output pixel centres within 1e-5.

Tests marked ``data`` read the real files under ``$VPRFLOW_DATA`` (the ``data_root``
fixture of conftest.py): skipped when it is unset or not a folder, but failed under
``CI=true`` (CI must not lose them).
"""

from __future__ import annotations

import math
import os
import pickle
import shlex
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from workflow_helpers import dataset_spec, truth_spec

from vprflow.datasets import DatasetError, DatasetFiles, list_dataset
from vprflow.ground_truth import (
    frame_window_ground_truth,
    ground_truth,
    load_object_npy,
    pairs_ground_truth,
    vprbench_ground_truth,
)
from vprflow.images import ImageReadError, list_images, read_image, resize_image
from vprflow.positions import utm_from_name, utm_ground_truth


def assert_truth_equal(truth, expected):
    assert len(truth) == len(expected)
    for q, (got, want) in enumerate(zip(truth, expected, strict=True)):
        assert got.dtype == np.int64, q
        np.testing.assert_array_equal(got, np.asarray(sorted(want), dtype=np.int64), err_msg=q)


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


def test_vprbench_out_of_range_references(tmp_path):
    # The published 17places file lists references 406 and 407 of a 406-image set.
    path = write_vprbench(tmp_path / "gt.npy", [(0, [0, 1]), (1, [2, 4, 5]), (2, [-1, 3])])
    with pytest.raises(DatasetError, match=r"query 1 lists reference indices \[4, 5\]"):
        vprbench_ground_truth(path, 3, 4)
    truth = vprbench_ground_truth(path, 3, 4, drop_out_of_range=True)
    assert_truth_equal(truth, [{0, 1}, {2}, {3}])


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
    write_vprbench(tmp_path / "gt.npy", [(0, []), (1, [7])])
    files = DatasetFiles(reference=[Path("a.jpg"), Path("b.jpg")], query=[Path("c"), Path("d")])
    spec = {"kind": "vprbench", "file": "gt.npy", "drop_out_of_range": True}
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


def utm_name(easting, northing, stem):
    return f"@{easting:010.2f}@{northing:.2f}@17@T@{stem}.jpg"


def test_utm_ground_truth_matches_pairwise_distance_loop(tmp_path):
    rng = np.random.default_rng(0)
    ref_xy = rng.uniform(0, 120, (60, 2)) + [585300.0, 4477300.0]
    query_xy = rng.uniform(0, 120, (25, 2)) + [585300.0, 4477300.0]
    reference = [tmp_path / utm_name(e, n, f"r{i}") for i, (e, n) in enumerate(ref_xy)]
    query = [tmp_path / utm_name(e, n, f"q{i}") for i, (e, n) in enumerate(query_xy)]
    # The names are rounded to centimetres: the direct loop reads them back the same way.
    ref_xy = [(float(p.name.split("@")[1]), float(p.name.split("@")[2])) for p in reference]
    query_xy = [(float(p.name.split("@")[1]), float(p.name.split("@")[2])) for p in query]
    for radius in (10.0, 25.0):
        expected = [
            {r for r, (re, rn) in enumerate(ref_xy) if math.hypot(qe - re, qn - rn) <= radius}
            for qe, qn in query_xy
        ]
        assert any(expected) and not all(expected)
        assert_truth_equal(utm_ground_truth(reference, query, radius), expected)


def test_utm_from_name():
    assert utm_from_name("db/@0585313.93@4477305.41@17@T@037.0@x.jpg") == (585313.93, 4477305.41)
    with pytest.raises(DatasetError, match="no '@easting@northing@'"):
        utm_from_name("db/000123.jpg")


@pytest.mark.parametrize(("easting", "northing"), [("nan", "4.1e6"), ("585313.9", "inf")])
def test_utm_name_with_nan_or_infinity_is_refused_naming_the_file_and_value(
    tmp_path, easting, northing
):
    # Today scipy's KD-tree fails with "'x' must be finite", naming no file.
    name = f"@{easting}@{northing}@17@T@x.jpg"
    reference = [tmp_path / utm_name(585313.9, 4.1e6, "r0"), tmp_path / name]
    query = [tmp_path / utm_name(585313.9, 4.1e6, "q0")]
    bad = easting if easting == "nan" else northing
    with pytest.raises(DatasetError, match=rf"{name}: UTM \w+ '{bad}' in the file name is not"):
        utm_ground_truth(reference, query, 25.0)


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


def test_listing_a_dataset_whose_defaults_were_not_filled_fails_with_key_error(tmp_path):
    touch_images(tmp_path / "ds/ref", ["1.jpg"])
    touch_images(tmp_path / "ds/query", ["2.jpg"])
    unfilled = {"path": "ds", "reference": "ref", "query": "query"}
    with pytest.raises(KeyError, match="recursive"):
        list_dataset(tmp_path, "toy", unfilled)


def test_the_utm_radius_default_comes_from_the_schema():
    assert truth_spec(kind="utm")["radius"] == 25
    assert truth_spec(kind="utm", radius=7)["radius"] == 7
    # frame_window requires its radius: the utm default never reaches it.
    assert "radius" not in truth_spec(kind="frame_window")


# ------------------------------------------------------------------ folders

SPEC = dataset_spec(path="ds", reference="ref", query="query", paired=False)


def touch_images(folder, names):
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        (folder / name).write_bytes(b"")


def test_list_dataset_natural_order(tmp_path):
    touch_images(tmp_path / "ds/ref", ["10.jpg", "2.jpg", "1.jpg", "notes.txt", "img10.PNG"])
    touch_images(tmp_path / "ds/query", ["frame_10.png", "frame_2.png", "frame_9.png"])
    files = list_dataset(tmp_path, "toy", SPEC)
    assert [p.name for p in files.reference] == ["1.jpg", "2.jpg", "10.jpg", "img10.PNG"]
    assert [p.name for p in files.query] == ["frame_2.png", "frame_9.png", "frame_10.png"]
    assert list_images(tmp_path / "ds/query") == files.query


def test_list_dataset_missing_and_empty_folders(tmp_path):
    spec = dict(SPEC, source="https://example.org/toy")
    with pytest.raises(DatasetError, match=r"folder .*ds does not exist.*example\.org"):
        list_dataset(tmp_path, "toy", spec)
    touch_images(tmp_path / "ds/ref", ["1.jpg"])
    with pytest.raises(DatasetError, match=r"query folder .*query does not exist"):
        list_dataset(tmp_path, "toy", spec)
    touch_images(tmp_path / "ds/query", ["readme.txt"])
    with pytest.raises(DatasetError, match=r"query folder .*query contains no images"):
        list_dataset(tmp_path, "toy", spec)


def test_broken_link_or_folder_with_an_image_name_is_an_error_naming_it(tmp_path):
    # Skipping it would shift every later reference index against the ground truth.
    touch_images(tmp_path / "ds/ref", ["1.jpg", "3.jpg"])
    touch_images(tmp_path / "ds/query", ["1.jpg"])
    (tmp_path / "ds/ref/2.jpg").symlink_to(tmp_path / "gone.jpg")
    with pytest.raises(ImageReadError, match=r"ref/2\.jpg") as error:
        list_dataset(tmp_path, "toy", SPEC)
    assert "broken link" in str(error.value)
    (tmp_path / "ds/ref/2.jpg").unlink()
    (tmp_path / "ds/ref/2.jpg").mkdir()
    with pytest.raises(ImageReadError, match=r"ref/2\.jpg"):
        list_dataset(tmp_path, "toy", SPEC)


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


def test_paired_dataset_names_unpaired_files(tmp_path):
    spec = dict(SPEC, reference="vi", query="ir", paired=True)
    touch_images(tmp_path / "ds/vi", ["a.png", "b.png", "c.png"])
    touch_images(tmp_path / "ds/ir", ["a.png", "c.jpg", "d.png"])  # suffix may differ
    with pytest.raises(DatasetError) as error:
        list_dataset(tmp_path, "toy", spec)
    message = str(error.value)
    assert "2 file(s)" in message
    assert str(tmp_path / "ds/vi/b.png") in message and str(tmp_path / "ds/ir/d.png") in message
    (tmp_path / "ds/vi/b.png").unlink()
    (tmp_path / "ds/ir/d.png").unlink()
    files = list_dataset(tmp_path, "toy", spec)
    assert [p.stem for p in files.reference] == [p.stem for p in files.query] == ["a", "c"]


# ------------------------------------------------------------------ images


def test_read_8bit_rgb(tmp_path):
    pixels = np.random.default_rng(0).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    Image.fromarray(pixels, "RGB").save(tmp_path / "rgb.png")
    image = read_image(tmp_path / "rgb.png")
    assert image.shape == (5, 7, 3) and image.dtype == np.float32
    np.testing.assert_allclose(image, pixels / 255.0, rtol=0, atol=1e-7)


@pytest.mark.parametrize(("low", "high"), [(0.0, 255.0), (-0.5, 0.5)])
def test_float_image_outside_unit_range_is_refused_naming_file_and_range(tmp_path, low, high):
    # A 0-255 float TIFF used to be clipped to [0, 1]: 98% white, no error.
    pixels = np.linspace(low, high, 20, dtype=np.float32).reshape(4, 5)
    Image.fromarray(pixels, "F").save(tmp_path / "float.tif")
    with pytest.raises(ImageReadError, match=rf"float\.tif.*\[{low:g}, {high:g}\]"):
        read_image(tmp_path / "float.tif")


def test_float_image_in_unit_range_is_read_as_is(tmp_path):
    pixels = np.random.default_rng(3).uniform(0, 1, (4, 5)).astype(np.float32)
    Image.fromarray(pixels, "F").save(tmp_path / "float.tif")
    np.testing.assert_array_equal(read_image(tmp_path / "float.tif")[:, :, 1], pixels)


def test_read_grayscale_is_repeated(tmp_path):
    pixels = np.random.default_rng(1).integers(0, 256, (4, 6), dtype=np.uint8)
    Image.fromarray(pixels, "L").save(tmp_path / "grey.png")
    image = read_image(tmp_path / "grey.png")
    assert image.shape == (4, 6, 3)
    for c in range(3):
        np.testing.assert_allclose(image[:, :, c], pixels / 255.0, rtol=0, atol=1e-7)


def test_read_16bit_grayscale(tmp_path):
    pixels = np.random.default_rng(2).integers(0, 65536, (6, 5), dtype=np.uint16)
    pixels[0, 0], pixels[0, 1] = 0, 65535
    Image.fromarray(pixels).save(tmp_path / "thermal.png")
    assert Image.open(tmp_path / "thermal.png").mode.startswith("I")
    image = read_image(tmp_path / "thermal.png")
    assert image.shape == (6, 5, 3)
    for c in range(3):
        np.testing.assert_allclose(image[:, :, c], pixels / 65535.0, rtol=0, atol=1e-7)
    # 16-bit precision survives: neighbouring levels stay distinct (8-bit would merge them).
    assert image[0, 1, 0] == 1.0 and image[0, 0, 0] == 0.0


def test_read_rgba_drops_alpha(tmp_path):
    pixels = np.random.default_rng(3).integers(0, 256, (3, 4, 4), dtype=np.uint8)
    pixels[..., 3] = 0  # fully transparent: colours must still come through unchanged
    Image.fromarray(pixels, "RGBA").save(tmp_path / "rgba.png")
    np.testing.assert_allclose(
        read_image(tmp_path / "rgba.png"), pixels[..., :3] / 255.0, rtol=0, atol=1e-7
    )


def test_read_palette_image(tmp_path):
    palette = np.array([[255, 0, 0], [0, 128, 255], [10, 20, 30]], dtype=np.uint8)
    index = np.random.default_rng(4).integers(0, 3, (5, 6), dtype=np.uint8)
    image = Image.fromarray(index, "P")
    image.putpalette(palette.ravel().tolist())
    image.save(tmp_path / "palette.png")
    np.testing.assert_allclose(
        read_image(tmp_path / "palette.png"), palette[index] / 255.0, rtol=0, atol=1e-7
    )


def test_read_corrupt_image_names_the_file(tmp_path):
    garbage = tmp_path / "broken.jpg"
    garbage.write_bytes(b"\xff\xd8 definitely not a jpeg")
    with pytest.raises(ImageReadError, match="broken.jpg"):
        read_image(garbage)
    Image.fromarray(np.zeros((64, 64, 3), np.uint8) + 7).save(tmp_path / "whole.png")
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes((tmp_path / "whole.png").read_bytes()[:60])
    with pytest.raises(ImageReadError, match="truncated.png"):
        read_image(truncated)
    with pytest.raises(ImageReadError, match="missing.png"):
        read_image(tmp_path / "missing.png")


def test_resize_image_reproduces_a_linear_ramp():
    height, width = 6, 40
    ramp = np.tile(np.linspace(0.1, 0.9, width, dtype=np.float32), (height, 1))
    image = np.stack([ramp, 1 - ramp, np.full_like(ramp, 0.25)], axis=2)
    step = 0.8 / (width - 1)

    def value_at(x):  # the ramp at input column coordinate x (pixel centres at integers)
        return 0.1 + step * x

    for new_width in (20, 13, 80):
        out = resize_image(image, new_width, height)
        assert out.shape == (height, new_width, 3) and out.dtype == np.float32
        scale = width / new_width
        centres = (np.arange(new_width) + 0.5) * scale - 0.5
        # Away from the borders (where the filter is truncated) a linear ramp stays exact.
        margin = int(math.ceil(2 * max(scale, 1.0)))
        inner = slice(margin, new_width - margin)
        expected = np.broadcast_to(value_at(centres[inner]), (height, len(centres[inner])))
        np.testing.assert_allclose(out[:, inner, 0], expected, rtol=0, atol=1e-5)
        np.testing.assert_allclose(out[:, inner, 1], 1 - expected, rtol=0, atol=1e-5)
        np.testing.assert_allclose(out[:, :, 2], 0.25, atol=1e-6)  # constants stay constant
        assert out.min() >= 0.0 and out.max() <= 1.0
    same = resize_image(image, width, height)
    np.testing.assert_array_equal(same, image)


def test_resize_keeps_16bit_precision():
    image = np.full((8, 8, 3), 1000 / 65535, dtype=np.float32)
    image[:, 4:] = 1001 / 65535
    out = resize_image(image, 4, 4)
    assert out[0, 0, 0] == pytest.approx(1000 / 65535, abs=1e-8)
    assert out[0, 3, 0] == pytest.approx(1001 / 65535, abs=1e-8)


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


# ------------------------------------------------------------------ roles and pairs


def write_pngs(folder, names):
    for name in names:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(folder / name)


def test_references_and_queries_that_are_the_same_files_are_refused(tmp_path):
    write_pngs(tmp_path / "ds/ref", ["1.png", "2.png"])
    same_folder = {**SPEC, "query": "ref"}
    with pytest.raises(DatasetError, match=r"2 query image\(s\) are also reference images"):
        list_dataset(tmp_path, "toy", same_folder)
    (tmp_path / "ds/query").mkdir()
    (tmp_path / "ds/query/9.png").symlink_to(tmp_path / "ds/ref/2.png")
    with pytest.raises(DatasetError, match=r"query/9\.png = .*ref/2\.png"):
        list_dataset(tmp_path, "toy", {**SPEC, "follow_links": True})


def test_pairs_are_matched_by_relative_path_not_by_sort_order(tmp_path):
    # The suffixes make the visible and thermal names sort in different orders.
    write_pngs(tmp_path / "ds/vi", ["a.png", "a.m.png"])  # a.m.png sorts first
    write_pngs(tmp_path / "ds/ir", ["a.jpg", "a.m.jpg"])  # a.jpg sorts first
    spec = {**SPEC, "reference": "vi", "query": "ir", "paired": True}
    files = list_dataset(tmp_path, "toy", spec)
    pairs = [(r.name, q.name) for r, q in zip(files.reference, files.query, strict=True)]
    assert pairs == [("a.m.png", "a.m.jpg"), ("a.png", "a.jpg")]


def test_pairs_in_subfolders_need_partners_in_the_same_subfolders(tmp_path):
    write_pngs(tmp_path / "ds/vi", ["day/1.png", "night/1.png"])
    write_pngs(tmp_path / "ds/ir", ["1.png", "2.png"])  # same stems, flat: not partners
    spec = {**SPEC, "reference": "vi", "query": "ir", "paired": True}
    with pytest.raises(DatasetError, match=r"no partner of the same relative path.*day/1\.png"):
        list_dataset(tmp_path, "toy", spec)


def test_a_name_with_two_suffixes_makes_pairs_ambiguous(tmp_path):
    write_pngs(tmp_path / "ds/vi", ["1.png", "1.jpg", "2.png"])
    write_pngs(tmp_path / "ds/ir", ["1.png", "2.png", "3.png"])
    spec = {**SPEC, "reference": "vi", "query": "ir", "paired": True}
    with pytest.raises(DatasetError, match=r"two suffixes.*vi/1\.jpg and .*vi/1\.png"):
        list_dataset(tmp_path, "toy", spec)

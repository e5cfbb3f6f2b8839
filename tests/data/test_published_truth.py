"""The papers' own ground-truth files, checked against the published rules written out
directly: Baidu Mall camera files, InsideOut position pickles, MSLS validation lists."""

from __future__ import annotations

import pickle
import re
from collections import OrderedDict
from pathlib import Path

import numpy as np
import pytest

from vprflow.core.errors import DatasetError
from vprflow.data.datasets import DatasetFiles
from vprflow.data.ground_truth import ground_truth, ground_truth_rule
from vprflow.data.published_truth import (
    MSLS_FILES,
    camera_centres,
    load_object_npy,
    msls_ground_truth,
    msls_listed_images,
    published_order,
    read_msls_lists,
    read_position_array,
)


def test_published_order_is_natsorts_default_digits_as_numbers_case_kept():
    names = ["img10.jpg", "img2.jpg", "img1.jpg", "Img3.jpg", "a.jpg", "img02.jpg", "1.jpg"]
    ordered = [names[i] for i in published_order(names)]
    # natsort.natsorted(names) as the authors' code calls it (a leading number first;
    # 'I' < 'a' < 'i' by code point; 2 and 02 are equal numbers, then by name).
    assert ordered == [
        "1.jpg",
        "Img3.jpg",
        "a.jpg",
        "img1.jpg",
        "img02.jpg",
        "img2.jpg",
        "img10.jpg",
    ]


def test_published_order_is_natsorts_on_adversarial_names():
    natsort = pytest.importorskip("natsort")
    from test_images import ADVERSARIAL_NAMES

    names = list(reversed(ADVERSARIAL_NAMES))
    ordered = [names[i] for i in published_order(names)]
    assert ordered == natsort.natsorted(sorted(names))


def write_camera(path: Path, centre) -> None:
    """A Baidu Mall .camera file as the authors' loader reads it: rotation rows on lines
    5-7, the camera centre on the second-to-last line."""
    lines = ["# camera", "640 480", "500 500 320 240", "0 0 0 0"]
    lines += [" ".join(f"{v:.6f}" for v in row) for row in np.eye(3)]
    lines += ["0 0 0", " ".join(f"{v:.6f}" for v in centre), "end"]
    path.write_text("\n".join(lines) + "\n")


def positions_dataset(tmp_path, rng, n_ref=12, n_query=7):
    """A miniature Baidu Mall: images and one .camera file per image."""
    root = tmp_path / "baidu_mall"
    centres = {}
    for role, folder, gt, n in (
        ("reference", "training_images_undistort", "training_gt", n_ref),
        ("query", "query_images_undistort", "query_gt", n_query),
    ):
        (root / folder).mkdir(parents=True)
        (root / gt).mkdir()
        xyz = rng.uniform(0, 30, size=(n, 3))
        paths = []
        for i in range(n):
            image = root / folder / f"{role}_{i:04d}.jpg"
            image.write_bytes(b"")
            write_camera(root / gt / f"{image.stem}.camera", xyz[i])
            paths.append(image)
        centres[role] = (paths, np.round(xyz, 6))
    return root, centres


def test_baidu_positions_are_references_within_the_radius_of_each_query_camera(tmp_path):
    rng = np.random.default_rng(0)
    root, centres = positions_dataset(tmp_path, rng)
    (refs, ref_xyz), (queries, query_xyz) = centres["reference"], centres["query"]
    entry = {
        "kind": "positions",
        "reference_positions": "training_gt",
        "query_positions": "query_gt",
        "radius": 10,
    }
    truth = ground_truth(DatasetFiles(refs, queries), entry, root)
    # Direct: 3-D Euclidean distance between camera centres, <= radius (sklearn).
    for q in range(len(queries)):
        expected = [
            r for r in range(len(refs)) if np.sqrt(((query_xyz[q] - ref_xyz[r]) ** 2).sum()) <= 10
        ]
        assert truth[q].tolist() == expected
    assert ground_truth_rule(entry) == "positions:training_gt:10"


def test_a_missing_camera_file_is_named(tmp_path):
    rng = np.random.default_rng(1)
    root, centres = positions_dataset(tmp_path, rng)
    refs = centres["reference"][0]
    (root / "training_gt" / f"{refs[3].stem}.camera").unlink()
    with pytest.raises(DatasetError, match=f"{refs[3].stem}.camera"):
        camera_centres(root / "training_gt", refs, "ground_truth.reference_positions")


def test_a_camera_file_without_a_centre_line_is_an_error_naming_it(tmp_path):
    path = tmp_path / "x.camera"
    path.write_text("only\n")
    image = tmp_path / "x.jpg"
    with pytest.raises(DatasetError, match="x.camera"):
        camera_centres(tmp_path, [image], "ground_truth.reference_positions")
    path.write_text("a\n1 2 nan\nend\n")
    with pytest.raises(DatasetError, match="three finite numbers"):
        camera_centres(tmp_path, [image], "ground_truth.reference_positions")


def test_position_pickles_are_read_in_the_authors_file_order_not_vprflows(tmp_path):
    # vprflow orders names case-folded (a < B); natsorted keeps case (B < a): the pickle's
    # rows follow natsorted, so query row 0 belongs to B2.jpg.
    root = tmp_path / "insideout"
    for folder in ("ref_images", "query_images"):
        (root / folder).mkdir(parents=True)
    refs = [root / "ref_images" / n for n in ("a1.jpg", "b1.jpg", "c1.jpg")]
    queries = [root / "query_images" / n for n in ("a2.jpg", "B2.jpg")]
    ref_rows = [(0.0, 0.0), (100.0, 0.0), (200.0, 0.0)]  # natsorted: a1, b1, c1
    query_rows = [(100.0, 0.0), (0.0, 0.0)]  # natsorted: B2, a2
    with open(root / "gps_db_correct.pkl", "wb") as f:
        pickle.dump(ref_rows, f)
    with open(root / "gps_q_new.pkl", "wb") as f:
        pickle.dump(np.array(query_rows), f)
    entry = {
        "kind": "positions",
        "reference_positions": "gps_db_correct.pkl",
        "query_positions": "gps_q_new.pkl",
        "radius": 50,
    }
    truth = ground_truth(DatasetFiles(refs, queries), entry, root)
    # a2 is at x=99 (natsorted row 1), near a1 at x=100 (row 1, vprflow index 0);
    # B2 at x=1 is near B1 at x=0 (vprflow index 1).
    assert [t.tolist() for t in truth] == [[0], [1]]


@pytest.mark.parametrize(
    "content, message",
    [
        (OrderedDict(a=1), "refusing to load"),
        ([(1.0, 2.0, 3.0, 4.0)] * 3, "expected numbers"),
        ([(1.0, 2.0)] * 2, "2 positions for 3 images"),
        ([(1.0, float("nan"))] * 3, "not finite"),
        (["x", "y", "z"], "expected numbers"),
    ],
)
def test_position_files_that_are_not_plain_numbers_per_image_are_refused(
    tmp_path, content, message
):
    path = tmp_path / "gps.pkl"
    with open(path, "wb") as f:
        pickle.dump(content, f)
    with pytest.raises(DatasetError, match=message):
        read_position_array(path, 3, "ground_truth.reference_positions")


def write_msls_lists(folder: Path, rng) -> dict:
    """Published MSLS validation lists: query paths (some dropped by qIdx), per kept query
    its positives as indices into dbImages; CPH first, then SF, as shipped."""
    db = [f"train_val/cph/database/images/c{i:03d}.jpg" for i in range(8)]
    db += [f"train_val/sf/database/images/s{i:03d}.jpg" for i in range(6)]
    queries = [f"train_val/cph/query/images/cq{i}.jpg" for i in range(4)]
    queries += [f"train_val/sf/query/images/sq{i}.jpg" for i in range(4)]
    kept = np.array([0, 1, 3, 4, 5, 7], dtype=np.int64)  # cq2 and sq2 dropped
    positives = np.empty(len(kept), dtype=object)
    for row, q in enumerate(kept):
        pool = range(8) if "cph" in queries[q] else range(8, 14)
        chosen = rng.choice(list(pool), size=rng.integers(1, 4), replace=False)
        # One cross-city positive: the published split keeps same-city ones only.
        positives[row] = np.array([*chosen, 13 if "cph" in queries[q] else 0], dtype=np.int64)
    np.save(folder / MSLS_FILES["dbImages"], np.array(db))
    np.save(folder / MSLS_FILES["qImages"], np.array(queries))
    np.save(folder / MSLS_FILES["qIdx"], kept)
    np.save(folder / MSLS_FILES["pIdx"], positives, allow_pickle=True)
    return {"db": db, "queries": queries, "kept": kept, "positives": positives}


@pytest.mark.parametrize("city", ["sf", "cph"])
def test_msls_positives_follow_the_published_lists_of_one_city(tmp_path, city):
    lists = write_msls_lists(tmp_path, np.random.default_rng(2))
    # The city's folders as the authors' clean-up script lays them out: basenames.
    refs = [tmp_path / "database" / Path(p).name for p in lists["db"] if f"/{city}/" in p]
    kept = [lists["queries"][q] for q in lists["kept"]]
    queries = [tmp_path / "query" / Path(p).name for p in kept if f"/{city}/" in p][::-1]
    truth = msls_ground_truth(tmp_path, city, refs, queries)
    # Direct: a query's positives are its pIdx entries in its own city, by name.
    for q, positives in zip(queries, truth, strict=True):
        row = next(i for i, p in enumerate(kept) if Path(p).name == q.name)
        names = {
            Path(lists["db"][p]).name
            for p in lists["positives"][row]
            if f"/{city}/" in lists["db"][p]
        }
        assert sorted(refs[i].name for i in positives) == sorted(names)


def test_an_msls_query_outside_the_kept_list_is_refused(tmp_path):
    lists = write_msls_lists(tmp_path, np.random.default_rng(3))
    refs = [tmp_path / "database" / Path(p).name for p in lists["db"] if "/sf/" in p]
    queries = [tmp_path / "query" / "sq2.jpg"]  # dropped by qIdx
    with pytest.raises(DatasetError, match="sq2.jpg"):
        msls_ground_truth(tmp_path, "sf", refs, queries)


def test_an_msls_positive_missing_from_the_reference_folder_is_refused(tmp_path):
    lists = write_msls_lists(tmp_path, np.random.default_rng(4))
    absent = Path(lists["db"][lists["positives"][0][0]]).name  # cq0's first positive
    refs = [
        tmp_path / "database" / Path(p).name
        for p in lists["db"]
        if "/cph/" in p and Path(p).name != absent
    ]
    with pytest.raises(DatasetError, match=f"missing from the reference folder.*{absent}"):
        msls_ground_truth(tmp_path, "cph", refs, [tmp_path / "query" / "cq0.jpg"])


def test_rows_and_leading_columns_of_one_pose_list_give_each_roles_positions(tmp_path):
    poses = np.arange(40, dtype=np.float64).reshape(10, 4)  # x, y, z, yaw
    np.save(tmp_path / "poses.npy", poses.astype(object), allow_pickle=True)
    table = read_position_array(tmp_path / "poses.npy", 3, "q", rows=[6, 9], dims=2)
    np.testing.assert_array_equal(table, poses[6:9, :2])
    with pytest.raises(DatasetError, match=r"rows \[6, 11\] of .*which has 10 rows"):
        read_position_array(tmp_path / "poses.npy", 5, "q", rows=[6, 11], dims=2)
    with pytest.raises(DatasetError, match="expected numbers"):  # 4 columns, no dims
        read_position_array(tmp_path / "poses.npy", 3, "q", rows=[6, 9])


def test_a_matches_table_gives_row_is_positives_and_names_a_bad_index(tmp_path):
    from vprflow.data.published_truth import matches_csv_ground_truth

    path = tmp_path / "gt_matches.csv"
    path.write_text("query_ind,top_2_ref_ind,top_1_ref_ind\n7,3,1\n9,0,0\n")
    truth = matches_csv_ground_truth(path, 2, 4)
    assert [t.tolist() for t in truth] == [[1, 3], [0]]  # by row, query_ind not read
    path.write_text("query_ind,top_1_ref_ind\n0,2.5\n")
    with pytest.raises(DatasetError, match=r"row 2: top_1_ref_ind = '2.5' is not a reference"):
        matches_csv_ground_truth(path, 1, 4)
    path.write_text("query_ind,top_1_ref_ind\n0,4\n")
    with pytest.raises(DatasetError, match="is not a reference index"):
        matches_csv_ground_truth(path, 1, 4)


def test_a_vprbench_file_read_by_position_ignores_the_first_field_and_keeps_rows(tmp_path):
    from vprflow.data.ground_truth import vprbench_ground_truth

    rows = np.empty((4, 2), dtype=object)
    for i, (q, refs) in enumerate([(0, [0]), (1, [1]), (11, [2]), (12, [0, 2])]):
        rows[i, 0], rows[i, 1] = q, refs
    np.save(tmp_path / "gt.npy", rows, allow_pickle=True)
    truth = vprbench_ground_truth(tmp_path / "gt.npy", 2, 3, rows=[2, 4], query_index="position")
    assert [t.tolist() for t in truth] == [[2], [0, 2]]
    with pytest.raises(DatasetError, match="query index 11, outside 0..1"):
        vprbench_ground_truth(tmp_path / "gt.npy", 2, 3, rows=[2, 4], query_index="column")


# ------------------------------------------------ MSLS lists: values of the wrong kind


def _resave(folder: Path, key: str, values) -> Path:
    """Overwrite one published list with ``values`` (an object array, as pickled lists
    are), returning its path."""
    path = folder / MSLS_FILES[key]
    array = np.empty(len(values), dtype=object)
    array[:] = values
    np.save(path, array, allow_pickle=True)
    return path


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (-1, "query index -1 is outside 0..7"),  # numpy would read the last query
        (1.7, "query index 1.7 is not an integer"),  # int64 would truncate it to 1
        (True, "query index True is a boolean"),
        ("3", "query index '3' is not an integer"),
        (8, "query index 8 is outside 0..7"),  # used to be a bare IndexError
    ],
)
def test_an_msls_query_index_of_the_wrong_kind_is_refused_naming_file_row_and_value(
    tmp_path, value, message
):
    lists = write_msls_lists(tmp_path, np.random.default_rng(5))
    path = _resave(tmp_path, "qIdx", [*lists["kept"][:2], value, *lists["kept"][3:]])
    refs = [tmp_path / "database" / Path(p).name for p in lists["db"] if "/sf/" in p]
    with pytest.raises(DatasetError, match=f"{re.escape(str(path))} row 2: {re.escape(message)}"):
        msls_ground_truth(tmp_path, "sf", refs, [tmp_path / "query" / "sq0.jpg"])


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (-1, "reference index -1 is outside 0..13"),  # numpy would read the last image
        (2.5, "reference index 2.5 is not an integer"),
        (False, "reference index False is a boolean"),
        ("0", "reference index '0' is not an integer"),
        (14, "reference index 14 is outside 0..13"),
    ],
)
def test_an_msls_positive_of_the_wrong_kind_is_refused_naming_file_row_and_value(
    tmp_path, value, message
):
    lists = write_msls_lists(tmp_path, np.random.default_rng(6))
    rows = [list(p) for p in lists["positives"]]
    rows[1] = [*rows[1], value]
    path = _resave(tmp_path, "pIdx", rows)
    refs = [tmp_path / "database" / Path(p).name for p in lists["db"] if "/cph/" in p]
    with pytest.raises(DatasetError, match=f"{re.escape(str(path))} row 1: {re.escape(message)}"):
        msls_ground_truth(tmp_path, "cph", refs, [tmp_path / "query" / "cq0.jpg"])


def test_an_msls_query_kept_twice_is_refused_naming_both_rows(tmp_path):
    lists = write_msls_lists(tmp_path, np.random.default_rng(7))
    kept = lists["kept"].copy()
    kept[4] = kept[3]  # sq0 twice: the later row's positives used to win silently
    np.save(tmp_path / MSLS_FILES["qIdx"], kept)
    refs = [tmp_path / "database" / Path(p).name for p in lists["db"] if "/sf/" in p]
    with pytest.raises(DatasetError, match=r"qIdx\.npy rows 3 and 4: query index 4 .*twice"):
        msls_ground_truth(tmp_path, "sf", refs, [tmp_path / "query" / "sq0.jpg"])


def test_integral_float_msls_indices_are_read_as_the_integers_they_are(tmp_path):
    lists = write_msls_lists(tmp_path, np.random.default_rng(8))
    refs = [tmp_path / "database" / Path(p).name for p in lists["db"] if "/cph/" in p]
    queries = [tmp_path / "query" / "cq0.jpg", tmp_path / "query" / "cq3.jpg"]
    expected = msls_ground_truth(tmp_path, "cph", refs, queries)
    np.save(tmp_path / MSLS_FILES["qIdx"], lists["kept"].astype(np.float64))
    _resave(tmp_path, "pIdx", [np.asarray(p, dtype=np.float64) for p in lists["positives"]])
    truth = msls_ground_truth(tmp_path, "cph", refs, queries)
    assert [t.tolist() for t in truth] == [t.tolist() for t in expected]


# ------------------------------------------------ MSLS: the images the lists name


def test_msls_images_the_lists_leave_out_are_left_out_and_counted(tmp_path, caplog):
    lists = write_msls_lists(tmp_path, np.random.default_rng(9))
    # The raw Copenhagen folders: every listed image, one database image the lists leave
    # out (12,601 raw, 12,556 listed) and the query that qIdx drops.
    listed = [tmp_path / "database" / Path(p).name for p in lists["db"] if "/cph/" in p]
    reference = sorted([*listed, tmp_path / "database" / "unlisted.jpg"])
    query = [tmp_path / "query" / f"cq{i}.jpg" for i in range(4)]
    with caplog.at_level("WARNING", logger="vprflow"):
        kept_refs, kept_queries = msls_listed_images(tmp_path, "cph", reference, query)
    assert kept_refs == [p for p in reference if p.name != "unlisted.jpg"]
    assert [q.name for q in kept_queries] == ["cq0.jpg", "cq1.jpg", "cq3.jpg"]
    assert "1 of the 9 reference images are not in msls_val_dbImages.npy" in caplog.text
    assert "1 of the 4 query images are not in msls_val_qIdx.npy" in caplog.text
    assert "unlisted.jpg" in caplog.text and "cq2.jpg" in caplog.text
    # Read unlisted, the extra image is a distractor that no published number ranks.
    with pytest.raises(DatasetError, match=r"1 reference image\(s\) are not .*unlisted\.jpg"):
        msls_ground_truth(tmp_path, "cph", reference, kept_queries)


def test_a_listed_msls_image_missing_from_the_folder_is_refused_naming_it(tmp_path):
    lists = write_msls_lists(tmp_path, np.random.default_rng(10))
    reference = [tmp_path / "database" / Path(p).name for p in lists["db"] if "/sf/" in p]
    query = [tmp_path / "query" / f"sq{i}.jpg" for i in (0, 1, 3)]
    with pytest.raises(DatasetError, match=r"1 reference image\(s\) listed in .*s002\.jpg"):
        msls_listed_images(tmp_path, "sf", [p for p in reference if p.name != "s002.jpg"], query)
    with pytest.raises(DatasetError, match=r"1 query image\(s\) listed in .*sq3\.jpg"):
        msls_listed_images(tmp_path, "sf", reference, query[:2])


def test_an_msls_preset_lists_only_the_images_of_the_published_lists(tmp_path):
    from vprflow.data.datasets import list_dataset

    lists = write_msls_lists(tmp_path, np.random.default_rng(11))
    for path in lists["db"][:8] + ["unlisted.jpg"]:
        (tmp_path / "database").mkdir(exist_ok=True)
        (tmp_path / "database" / Path(path).name).write_bytes(b"")
    for name in ("cq0.jpg", "cq1.jpg", "cq2.jpg", "cq3.jpg"):
        (tmp_path / "query").mkdir(exist_ok=True)
        (tmp_path / "query" / name).write_bytes(b"")
    entry = {
        "path": tmp_path.name,
        "reference": "database",
        "query": "query",
        "paired": False,
        "recursive": True,
        "follow_links": False,
        "ground_truth": {"kind": "msls", "city": "cph"},
    }
    files = list_dataset(tmp_path.parent, "msls_cph", entry)
    assert [p.name for p in files.reference] == [f"c{i:03d}.jpg" for i in range(8)]
    assert [p.name for p in files.query] == ["cq0.jpg", "cq1.jpg", "cq3.jpg"]


# ------------------------------------------------ the restricted unpickler's sizes


class _Huge:
    """A pickle that asks numpy for 2**40 elements in one of the ways its own arrays
    are pickled: ``_reconstruct``'s shape, or the shape of ``__setstate__``'s state."""

    def __init__(self, how: str):
        self.how = how

    def __reduce__(self):
        from numpy._core.multiarray import _reconstruct

        if self.how == "reconstruct":
            return (_reconstruct, (np.ndarray, (2**40,), b"b"))
        state = (1, (2**40,), np.dtype(object), False, [1, 2])
        return (_reconstruct, (np.ndarray, (0,), b"b"), state)


@pytest.mark.parametrize("how", ["reconstruct", "setstate"])
def test_a_pickle_asking_for_a_2_to_the_40_element_array_is_refused_naming_the_file(tmp_path, how):
    path = tmp_path / "gt.npy"
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": "|O", "fortran_order": False, "shape": (2,)}
        )
        pickle.dump(_Huge(how), f, protocol=3)
    # It used to end in a MemoryError naming no file.
    with pytest.raises(DatasetError, match=rf"{re.escape(str(path))}: .*\(1099511627776,\)"):
        load_object_npy(path)
    pkl = tmp_path / "gps.pkl"
    with open(pkl, "wb") as f:
        pickle.dump(_Huge(how), f, protocol=3)
    with pytest.raises(DatasetError, match=rf"{re.escape(str(pkl))} .*more than the whole file"):
        read_position_array(pkl, 2, "ground_truth.reference_positions")


def test_a_npy_header_declaring_more_data_than_the_file_holds_is_refused_naming_it(tmp_path):
    path = tmp_path / "gt.npy"
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": "<f8", "fortran_order": False, "shape": (2**40,)}
        )
        f.write(b"\0" * 64)
    with pytest.raises(DatasetError, match=rf"{re.escape(str(path))}: its header declares"):
        load_object_npy(path)


def test_a_pickle_calling_the_array_class_itself_is_refused(tmp_path):
    class CallsNdarray:
        def __reduce__(self):
            return (np.ndarray, ((2**40,), "u1"))

    path = tmp_path / "gps.pkl"
    with open(path, "wb") as f:
        pickle.dump(CallsNdarray(), f, protocol=3)
    with pytest.raises(DatasetError, match=f"{re.escape(str(path))}.*refusing to call numpy"):
        read_position_array(path, 2, "ground_truth.reference_positions")


@pytest.mark.parametrize("name", ["msls_sf", "msls_cph"])
def test_the_msls_city_presets_leave_out_a_query_whose_positives_lie_in_the_other_city(
    tmp_path, caplog, name
):
    from vprflow.data.presets import presets
    from vprflow.evaluation.recall import recall_at

    # Revisit-Anything's segregate_data_by_city keeps a query's same-city positives
    # only, and calc_recall / get_recall skip a query whose gt is then empty (and do not
    # count it): cq0 below, listed with one San Francisco positive, is not evaluated.
    lists = write_msls_lists(tmp_path, np.random.default_rng(12))
    rows = [list(p) for p in lists["positives"]]
    rows[0] = [13]  # cq0: its one positive is San Francisco's s005
    _resave(tmp_path, "pIdx", rows)
    refs = [tmp_path / "database" / Path(p).name for p in lists["db"] if "/cph/" in p]
    queries = [tmp_path / "query" / f"cq{i}.jpg" for i in (0, 1, 3)]
    with caplog.at_level("WARNING", logger="vprflow"):
        truth = msls_ground_truth(tmp_path, "cph", refs, queries)
    assert len(truth[0]) == 0 and all(len(t) for t in truth[1:])
    assert (
        "1 of the 3 kept cph queries have their listed positives (msls_val_pIdx.npy) only "
        "in the other city, so none after the city filter (e.g. cq0.jpg)" in caplog.text
    )
    ranking = np.array([[t[0] if len(t) else 0] for t in truth])  # the others hit at 1
    denominator = presets()[name].dataset["denominator"]
    assert recall_at(ranking, truth, [1], denominator) == {1: 2 / 2}


def test_msls_val_divides_recall_by_every_kept_query_as_salad(tmp_path, caplog):
    from vprflow.data.presets import presets
    from vprflow.evaluation.recall import recall_at

    # SALAD's get_validation_recalls divides the hits by len(predictions): every kept
    # query, whether or not its pIdx row lists a positive; no city filter drops one.
    lists = write_msls_lists(tmp_path, np.random.default_rng(12))
    rows = [list(p) for p in lists["positives"]]
    rows[0] = []  # cq0 keeps no positive
    _resave(tmp_path, "pIdx", rows)
    refs = [tmp_path / "database" / Path(p).name for p in lists["db"]]
    queries = [tmp_path / "query" / Path(lists["queries"][q]).name for q in lists["kept"]]
    with caplog.at_level("WARNING", logger="vprflow"):
        truth = msls_ground_truth(tmp_path, "all", refs, queries)
    assert "other city" not in caplog.text
    ranking = np.array([[t[0] if len(t) else 0] for t in truth])  # the others hit at 1
    denominator = presets()["msls_val"].dataset["denominator"]
    assert recall_at(ranking, truth, [1], denominator) == {1: 5 / 6}


def test_two_listed_msls_paths_of_one_file_name_are_refused_naming_both_rows(tmp_path):
    lists = write_msls_lists(tmp_path, np.random.default_rng(13))
    db = list(lists["db"])
    db[9] = "train_val/sf/database/images/c001.jpg"  # the name of Copenhagen's row 1
    np.save(tmp_path / MSLS_FILES["dbImages"], np.array(db))
    reference = list(dict.fromkeys(tmp_path / "database" / Path(p).name for p in db))
    query = [tmp_path / "query" / f"{c}q{i}.jpg" for c in "cs" for i in (0, 1, 3)]
    # Matched by name, either file could stand for both rows: refused, not guessed.
    with pytest.raises(DatasetError, match=r"dbImages\.npy rows 1 and 9 .* one file name"):
        msls_listed_images(tmp_path, "all", reference, query)
    # One city's images are matched among that city's rows only.
    kept_refs, _ = msls_listed_images(tmp_path, "cph", reference, query)
    assert len(kept_refs) == 8


def test_a_positives_list_that_is_not_one_row_per_kept_query_is_refused_naming_it(tmp_path):
    write_msls_lists(tmp_path, np.random.default_rng(14))
    np.save(tmp_path / MSLS_FILES["pIdx"], np.int64(3))
    with pytest.raises(DatasetError, match=r"pIdx\.npy: 0 rows for 6 kept queries"):
        read_msls_lists(tmp_path)

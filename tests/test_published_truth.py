"""The papers' own ground-truth files, checked against the published rules written out
directly: Baidu Mall camera files, InsideOut position pickles, MSLS validation lists."""

from __future__ import annotations

import pickle
from collections import OrderedDict
from pathlib import Path

import numpy as np
import pytest

from vprflow.datasets import DatasetError, DatasetFiles
from vprflow.ground_truth import ground_truth, ground_truth_rule
from vprflow.published_truth import (
    MSLS_FILES,
    camera_centres,
    msls_ground_truth,
    published_order,
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
    from vprflow.published_truth import matches_csv_ground_truth

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
    from vprflow.ground_truth import vprbench_ground_truth

    rows = np.empty((4, 2), dtype=object)
    for i, (q, refs) in enumerate([(0, [0]), (1, [1]), (11, [2]), (12, [0, 2])]):
        rows[i, 0], rows[i, 1] = q, refs
    np.save(tmp_path / "gt.npy", rows, allow_pickle=True)
    truth = vprbench_ground_truth(tmp_path / "gt.npy", 2, 3, rows=[2, 4], query_index="position")
    assert [t.tolist() for t in truth] == [[2], [0, 2]]
    with pytest.raises(DatasetError, match="query index 11, outside 0..1"):
        vprbench_ground_truth(tmp_path / "gt.npy", 2, 3, rows=[2, 4], query_index="column")

"""Miniature copies of the presets' published layouts: a handful of tiny images with the
real file naming and folder structure, and ground-truth files written the way the
published code reads them. Each builder returns, per query file name, the reference
file names the published rule makes positive, computed directly from what it wrote."""

from __future__ import annotations

import pickle
from collections.abc import Callable
from pathlib import Path

import numpy as np
from PIL import Image
from synthetic import place_image, write_vprbench_ground_truth

from vprflow.data.published_truth import MSLS_FILES, published_order

SIZE = (40, 30)  # stored image size; the test backbone resizes to its own


def write_image(path: Path, rng: np.random.Generator) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    pixels = (place_image(rng, *SIZE) * 255).astype(np.uint8)
    Image.fromarray(pixels).save(path)


def _within(points_q: dict, points_r: dict, radius: float) -> dict[str, set[str]]:
    """Per query name, the reference names within ``radius`` (Euclidean, <=)."""
    return {
        q: {r for r, pr in points_r.items() if np.linalg.norm(np.subtract(pq, pr)) <= radius}
        for q, pq in points_q.items()
    }


def _index_window(root: Path, rng, radius: int, n: int = 8) -> dict[str, set[str]]:
    """Frames ``Image000.jpg`` ... in ref/ and query/ (written once: the two 17places
    presets share a folder); query i's positives are references within ``radius``."""
    names = [f"Image{i:03d}.jpg" for i in range(n)]  # VPR-Bench's 17places naming
    for name in names:
        for role in ("ref", "query"):
            if not (root / role / name).exists():
                write_image(root / role / name, rng)
    return {q: {names[j] for j in range(n) if abs(i - j) <= radius} for i, q in enumerate(names)}


def seventeen_places(root: Path, rng) -> dict[str, set[str]]:
    """Revisit-Anything's rule: +-15 frames (gt.py), no file read."""
    return _index_window(root, rng, 15, 8)


def seventeen_places_anyloc(root: Path, rng) -> dict[str, set[str]]:
    """VPR-Bench file of +-2 frames, listing references past the end (dropped)."""
    n = 8
    expected = _index_window(root, rng, 2, n)
    write_vprbench_ground_truth(root / "ground_truth_new.npy", n, n + 2, radius=2)
    return expected


def utm_names(root: Path, rng, database: str, queries: str, n_ref=8, n_query=4):
    """Downloader names ``@easting@northing@zone@band@lat@lon@...@.jpg``, references
    along a street every 10 m, queries near some of them."""
    refs, qs = {}, {}
    for i in range(n_ref):
        e, n = 584000.0 + 10 * i, 4477000.0 + 3 * i
        name = f"@{e:.2f}@{n:.2f}@17@T@40.44@-79.99@ref{i:03d}@@@@@@@@.jpg"
        refs[name] = (e, n)
        write_image(root / database / name, rng)
    for i in range(n_query):
        e, n = 584000.0 + 20 * i + rng.uniform(-6, 6), 4477000.0 + rng.uniform(-6, 6)
        name = f"@{e:.2f}@{n:.2f}@17@T@40.44@-79.99@q{i:03d}@@@@@@@@.jpg"
        qs[name] = (float(name.split("@")[1]), float(name.split("@")[2]))
        write_image(root / queries / name, rng)
    refs = {k: (float(k.split("@")[1]), float(k.split("@")[2])) for k in refs}
    return refs, qs


def pitts30k(root: Path, rng) -> dict[str, set[str]]:
    refs, qs = utm_names(root, rng, "images/test/database", "images/test/queries")
    return _within(qs, refs, 25)


def _utm_preset(database: str, queries: str) -> Callable:
    def build(root: Path, rng) -> dict[str, set[str]]:
        refs, qs = utm_names(root, rng, database, queries)
        return _within(qs, refs, 25)

    return build


def nordland(root: Path, rng) -> dict[str, set[str]]:
    """The downloader's names: fake northing of 25/10.5 m per frame, rounded to 0.1 m,
    so 25 m is +-10 frames (the published convention, checked here as frames)."""

    def name(frame: int) -> str:
        return f"@0@{round(frame * 25 / 10.5, 1)}@@@@@{frame:05d}@@@@@@@@.jpg"

    frames = range(0, 24)
    for frame in frames:
        write_image(root / "images/test/database" / name(frame), rng)
    queries = (0, 5, 11, 23)
    for frame in queries:
        write_image(root / "images/test/queries" / name(frame), rng)
    return {name(q): {name(f) for f in frames if abs(f - q) <= 10} for q in queries}


def vp_air(root: Path, rng) -> dict[str, set[str]]:
    """vpair_gt.npy as released: an object array of [query index, [reference indices]]
    rows; a distractors/ folder beside, which Revisit-Anything's protocol does not read.
    Written once (vp_air_anyloc shares the folder)."""
    refs = [f"{i:05d}.png" for i in range(1, 9)]
    queries = [f"{i:05d}.png" for i in range(1, 6)]
    gt = root / "vpair_gt.npy"
    if not gt.exists():
        for name in refs:
            write_image(root / "reference_views" / name, rng)
        for name in queries:
            write_image(root / "queries" / name, rng)
        for i in range(1, 4):
            write_image(root / "distractors" / f"{i:05d}.png", rng)
        rows = np.empty((len(queries), 2), dtype=object)
        for q in range(len(queries)):
            positives = sorted(rng.choice(len(refs), size=2, replace=False).tolist())
            rows[q, 0], rows[q, 1] = q + 1, positives  # read by position: the field is ignored
        np.save(gt, rows, allow_pickle=True)
    rows = np.load(gt, allow_pickle=True)
    return {name: {refs[i] for i in rows[q, 1]} for q, name in enumerate(queries)}


def vp_air_anyloc(root: Path, rng) -> dict[str, set[str]]:
    """The same folder with the database list the preset's layout says to write
    (reference views, then distractors: AnyLoc's order); the positives index the
    reference views, so no distractor is one."""
    expected = vp_air(root, rng)
    listed = [f"reference_views/{p.name}" for p in sorted((root / "reference_views").iterdir())]
    listed += [f"distractors/{p.name}" for p in sorted((root / "distractors").iterdir())]
    (root / "database_with_distractors.txt").write_text("\n".join(listed) + "\n")
    return expected


def _snsm(name: str) -> Callable:
    """SNSM's lists: RGB paths in <name>_rgb.txt, thermal partners line by line in
    <name>_thr.txt, in the lists' own (not sorted) order; names differ between the two."""

    def build(root: Path, rng) -> dict[str, set[str]]:
        frames = ["0010", "0002", "0007", "0001", "0003"]
        rgb = [f"Vis/{f}_rgb.png" for f in frames]
        thermal = [f"Ir/{f}_ir.png" for f in frames]
        for path in rgb + thermal:
            write_image(root / path, rng)
        (root / f"{name}_rgb.txt").write_text("\n".join(rgb) + "\n")
        (root / f"{name}_thr.txt").write_text("\n".join(thermal) + "\n")
        return {Path(t).name: {Path(r).name} for r, t in zip(rgb, thermal, strict=True)}

    return build


def _pose_list(n_db: int, query_rows: tuple[int, int]) -> Callable:
    """AnyLoc's pose_topic_list.npy: one object array of poses (x, y, z, yaw) for both
    roles, the database in rows 0..n_db, the queries in ``query_rows``, other rows
    unused; images named so that natsorted order is not vprflow's (``img10`` vs
    ``Img9``)."""

    def build(root: Path, rng) -> dict[str, set[str]]:
        start, stop = query_rows
        poses = np.empty((stop, 4), dtype=object)
        poses[:] = rng.uniform(0, 60, (stop, 4)).round(3).tolist()
        names = {"db_images": [f"{'I' if i % 7 == 0 else 'i'}mg{i}.png" for i in range(n_db)]}
        names["q_images"] = [f"{'Q' if i % 5 == 0 else 'q'}{i}.png" for i in range(stop - start)]
        points = {}
        for folder, first in (("db_images", 0), ("q_images", start)):
            order = published_order(names[folder])
            for row, i in enumerate(order):
                write_image(root / folder / names[folder][i], rng)
                points.setdefault(folder, {})[names[folder][i]] = tuple(
                    float(v) for v in poses[first + row, :2]
                )
        np.save(root / "pose_topic_list.npy", poses, allow_pickle=True)
        return _within(points["q_images"], points["db_images"], 8)

    return build


def mid_atlantic_ridge(root: Path, rng) -> dict[str, set[str]]:
    """eiffel_gt.npy: 202 rows of [index, positives], the queries' from row 101 on."""
    refs = [f"db_{i}.png" for i in range(6)]
    queries = [f"q_{i}.png" for i in range(101)]
    for name in refs:
        write_image(root / "db_images" / name, rng)
    for name in queries:
        write_image(root / "q_images" / name, rng)
    rows = np.empty((202, 2), dtype=object)
    expected = {}
    for row in range(202):
        positives = sorted(rng.choice(6, size=2, replace=False).tolist())
        rows[row, 0], rows[row, 1] = row, positives
        if row >= 101:
            expected[queries[row - 101]] = {refs[i] for i in positives}
    np.save(root / "eiffel_gt.npy", rows, allow_pickle=True)
    return expected


def nardo_air(root: Path, rng) -> dict[str, set[str]]:
    """gt_matches.csv: per query row, its five top reference indices."""
    refs = [f"ref_{i:03d}.png" for i in range(9)]
    queries = [f"query_{i:03d}.png" for i in range(4)]
    for name in refs:
        write_image(root / "reference_images" / name, rng)
    for name in queries:
        write_image(root / "query_images" / name, rng)
    lines = ["query_ind,top_1_ref_ind,top_2_ref_ind,top_3_ref_ind,top_4_ref_ind,top_5_ref_ind"]
    expected = {}
    for q, name in enumerate(queries):
        top = rng.choice(9, size=5, replace=False).tolist()
        lines.append(",".join(str(v) for v in [q, *top]))
        expected[name] = {refs[i] for i in top}
    (root / "gt_matches.csv").write_text("\n".join(lines) + "\n")
    return expected


def baidu_mall(root: Path, rng) -> dict[str, set[str]]:
    """Images and one .camera file each (centre on the second-to-last line)."""
    centres = {}
    for folder, gt, prefix, n in (
        ("training_images_undistort", "training_gt", "ref", 8),
        ("query_images_undistort", "query_gt", "q", 4),
    ):
        points = {}
        for i in range(n):
            name = f"{prefix}_{i:05d}.jpg"
            write_image(root / folder / name, rng)
            xyz = np.round(rng.uniform(0, 25, 3), 4)
            lines = ["CAMERA", "640 480", "525.0 525.0 320.0 240.0", "0 0 0 0 0"]
            lines += [" ".join(f"{v:.6f}" for v in row) for row in np.eye(3)]
            # The centre is the second-to-last line (the authors' lines[-2]).
            lines += ["0 0 0", " ".join(f"{v:.4f}" for v in xyz), "0"]
            (root / gt).mkdir(parents=True, exist_ok=True)
            (root / gt / f"{Path(name).stem}.camera").write_text("\n".join(lines) + "\n")
            points[name] = xyz
        centres[prefix] = points
    return _within(centres["q"], centres["ref"], 10)


def insideout(root: Path, rng) -> dict[str, set[str]]:
    """Position pickles in natsorted (case-kept) name order, which differs from
    vprflow's case-folded order for these names."""
    points = {}
    for folder, pickle_name, names in (
        ("ref_images", "gps_db_correct.pkl", ["b2.jpg", "A10.jpg", "a3.jpg", "C1.jpg", "c4.jpg"]),
        ("query_images", "gps_q_new.pkl", ["q2.jpg", "Q1.jpg", "q10.jpg"]),
    ):
        xy = {name: tuple(np.round(rng.uniform(0, 150, 2), 3)) for name in names}
        for name in names:
            write_image(root / folder / name, rng)
        rows = [list(xy[names[i]]) for i in published_order(names)]
        with open(root / pickle_name, "wb") as f:
            pickle.dump(rows, f)
        points[folder] = xy
    return _within(points["query_images"], points["ref_images"], 50)


def _msls(city: str) -> Callable:
    def build(root: Path, rng) -> dict[str, set[str]]:
        db = [f"train_val/cph/database/images/cphdb{i}.jpg" for i in range(6)]
        db += [f"train_val/sf/database/images/sfdb{i}.jpg" for i in range(6)]
        queries = [
            f"train_val/{c}/query/images/{c}q{i}.jpg" for c in ("cph", "sf") for i in range(4)
        ]
        kept = np.array([0, 2, 3, 4, 6, 7], dtype=np.int64)  # cphq1, sfq1 dropped: qIdx drops 7
        positives = np.empty(len(kept), dtype=object)
        expected = {}
        for row, q in enumerate(kept):
            own = [i for i, p in enumerate(db) if f"/{queries[q].split('/')[1]}/" in p]
            # cphq3 and sfq3: their one listed positive lies in the other city, so the
            # city split leaves them none.
            only_cross = queries[q].endswith("q3.jpg")
            chosen = [] if only_cross else rng.choice(own, size=2, replace=False).tolist()
            cross = [i for i, p in enumerate(db) if i not in own][:1]
            positives[row] = np.array(chosen + cross, dtype=np.int64)
            if city == "all":
                expected[Path(queries[q]).name] = {Path(db[i]).name for i in chosen + cross}
            elif f"/{city}/" in queries[q]:
                expected[Path(queries[q]).name] = {Path(db[i]).name for i in chosen}
        root.mkdir(parents=True, exist_ok=True)
        np.save(root / MSLS_FILES["dbImages"], np.array(db))
        np.save(root / MSLS_FILES["qImages"], np.array(queries))
        np.save(root / MSLS_FILES["qIdx"], kept)
        np.save(root / MSLS_FILES["pIdx"], positives, allow_pickle=True)
        # The raw folders: besides the listed images, a database image the lists leave
        # out (as 45 of Copenhagen's 12,601) and the queries qIdx drops; both left out.
        for p in db:
            if city == "all" or f"/{city}/" in p:
                write_image(root / "database" / Path(p).name, rng)
        write_image(root / "database" / "unlisted.jpg", rng)
        for p in queries:
            if city == "all" or f"/{city}/" in p:
                write_image(root / "query" / Path(p).name, rng)
        return expected

    return build


def amstertime(root: Path, rng) -> dict[str, set[str]]:
    """Pairs named alike in new/ (png) and old/ (jpg), as the published release."""
    names = [f"{i:04d}" for i in (0, 1, 2, 10, 11)]
    for name in names:
        write_image(root / "new" / f"{name}.png", rng)
        write_image(root / "old" / f"{name}.jpg", rng)
    return {f"{n}.jpg": {f"{n}.png"} for n in names}


MINIATURES: dict[str, Callable[[Path, np.random.Generator], dict[str, set[str]]]] = {
    "17places": seventeen_places,
    "17places_anyloc": seventeen_places_anyloc,
    "pitts30k": pitts30k,
    "baidu_mall": baidu_mall,
    "insideout": insideout,
    "msls_sf": _msls("sf"),
    "msls_cph": _msls("cph"),
    "amstertime": amstertime,
    "pitts250k": _utm_preset("images/test/database", "images/test/queries"),
    "tokyo247": _utm_preset("images/test/database", "images/test/queries"),
    "st_lucia": _utm_preset("images/test/database", "images/test/queries"),
    "nordland": nordland,
    "sf_xl_val": _utm_preset("database", "queries"),
    "sf_xl_test": _utm_preset("database", "queries_v1"),
    "msls_val": _msls("all"),
    "vp_air": vp_air,
    "vp_air_anyloc": vp_air_anyloc,
    **{name: _snsm(name) for name in ("m3fd", "boson", "flir", "ino", "llvip", "vot", "vtuav")},
    "hawkins": _pose_list(127, (127, 245)),
    "laurel_caverns": _pose_list(141, (229, 341)),
    "mid_atlantic_ridge": mid_atlantic_ridge,
    "nardo_air": nardo_air,
    "nardo_air_r": nardo_air,
}

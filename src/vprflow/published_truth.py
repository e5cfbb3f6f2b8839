"""Ground-truth files as the papers' code ships them (docs/datasets.md), read without
running arbitrary pickles, each matched to the images by name rather than by position.

- Baidu Mall: one plain-text ``.camera`` file per image (AnyLoc/Revisit-Anything
  ``dataloaders/baidu_dataloader.py``): the camera centre is the second-to-last line.
- Position arrays (InsideOut's ``gps_db_correct.pkl`` / ``gps_q_new.pkl``): ``[N, 2]``
  metric coordinates in the authors' image order, ``natsorted`` file names.
- MSLS validation lists (``msls_val_{qImages,qIdx,pIdx,dbImages}.npy``, shipped by
  serizba/salad and Revisit-Anything): positives as database indices per kept query.
"""

from __future__ import annotations

import pickle
import re
from pathlib import Path

import numpy as np

from vprflow.datasets import DatasetError
from vprflow.images import natural_key


def published_order(names: list[str]) -> list[int]:
    """Indices that put ``names`` in ``natsort.natsorted`` order (its default ``ns.INT``),
    the order in which the authors' code lists images and writes per-image arrays: the
    order vprflow lists images in (:func:`vprflow.images.natural_key`)."""
    return sorted(range(len(names)), key=lambda i: natural_key(names[i]))


class _PlainUnpickler(pickle.Unpickler):
    """Lists, tuples, numbers and numpy arrays of them: any other class is refused."""

    ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }

    def find_class(self, module, name):
        if (module, name) in self.ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} from a ground-truth file")


def load_object_npy(path: str | Path) -> np.ndarray:
    """Load a ``.npy`` file, including object arrays, without running arbitrary pickles."""
    path = Path(path)
    with open(path, "rb") as f:
        try:
            version = np.lib.format.read_magic(f)
            read_header = {
                (1, 0): np.lib.format.read_array_header_1_0,
                (2, 0): np.lib.format.read_array_header_2_0,
            }.get(version)
            if read_header is None:
                raise ValueError(f"unsupported .npy version {version}")
            _shape, _fortran, dtype = read_header(f)
        except ValueError as error:
            raise DatasetError(f"{path} is not a .npy file: {error}") from error
        if dtype.hasobject:
            try:
                array = _PlainUnpickler(f).load()
            except (pickle.UnpicklingError, EOFError, AttributeError) as error:
                raise DatasetError(f"{path}: unreadable object array: {error}") from error
            return np.asarray(array)
        f.seek(0)
    return np.load(path, allow_pickle=False)


def read_position_array(
    path: Path, n: int, what: str, rows: list[int] | None = None, dims: int | None = None
) -> np.ndarray:
    """``[n, 2]`` or ``[n, 3]`` float64 coordinates from a ``.npy`` or a pickle of plain
    numbers (``what`` names the config key in errors): rows ``rows = [start, stop]`` of
    the file (AnyLoc's Hawkins and Laurel Caverns keep both roles in one pose list) and
    its first ``dims`` columns (the rest of a pose: orientation), or all of either."""
    if not path.is_file():
        raise DatasetError(f"{what}: {path} does not exist")
    try:
        if path.suffix == ".npy":  # may be an object array (AnyLoc saves with pickle)
            raw = load_object_npy(path)
        else:
            with open(path, "rb") as f:
                raw = _PlainUnpickler(f).load()
        table = np.asarray(raw)
    except (pickle.UnpicklingError, ValueError, EOFError, OSError) as error:
        raise DatasetError(
            f"{what}: cannot read {path} as an array of numbers without running code ({error})"
        ) from error
    if table.dtype == object:  # numbers held as Python objects: plain floats or nothing
        try:
            table = np.asarray(table.tolist(), dtype=np.float64)
        except (TypeError, ValueError):
            pass  # refused below, naming the dtype
    if rows is not None:
        n_rows = len(table) if table.ndim else 0
        if not rows[0] < rows[1] <= n_rows:
            raise DatasetError(f"{what}: rows {rows} of {path}, which has {n_rows} rows")
        table = table[rows[0] : rows[1]]
    if dims is not None and table.ndim == 2:
        table = table[:, :dims]
    if table.ndim != 2 or table.shape[1] not in (2, 3) or table.dtype.kind not in "iuf":
        raise DatasetError(
            f"{what}: {path} holds {table.dtype} {table.shape}; expected numbers [N, 2] or "
            "[N, 3] (one position per image)"
        )
    if len(table) != n:
        raise DatasetError(f"{what}: {path} has {len(table)} positions for {n} images")
    table = table.astype(np.float64)
    bad = np.flatnonzero(~np.isfinite(table).all(axis=1))
    if len(bad):
        raise DatasetError(f"{what}: {path} row {bad[0]} is not finite: {table[bad[0]]}")
    return table


def in_published_order(table: np.ndarray, images: list[Path]) -> np.ndarray:
    """Rows of a per-image array written in the authors' order, put in ``images``' order."""
    order = published_order([p.name for p in images])
    out = np.empty_like(table)
    out[order] = table
    return out


def read_camera_centre(path: Path) -> np.ndarray:
    """The camera centre ``[x, y, z]`` of a Baidu Mall ``.camera`` file: its
    second-to-last line (``get_cop_pose`` in the authors' loader)."""
    lines = [line for line in path.read_text().splitlines()]
    try:
        centre = np.array([float(v) for v in lines[-2].split()], dtype=np.float64)
    except (IndexError, ValueError) as error:
        raise DatasetError(
            f"{path}: expected a camera file whose second-to-last line is the camera "
            f"centre 'x y z' ({error})"
        ) from error
    if centre.shape != (3,) or not np.isfinite(centre).all():
        raise DatasetError(f"{path}: camera centre {lines[-2]!r} is not three finite numbers")
    return centre


def camera_centres(folder: Path, images: list[Path], what: str) -> np.ndarray:
    """``[n, 3]`` camera centres of ``images`` from ``<folder>/<image stem>.camera``."""
    if not folder.is_dir():
        raise DatasetError(f"{what}: pose folder {folder} does not exist")
    paths = [folder / f"{image.stem}.camera" for image in images]
    missing = [p.name for p in paths if not p.is_file()]
    if missing:
        raise DatasetError(
            f"{what}: {len(missing)} image(s) have no pose file in {folder} (e.g. "
            f"{', '.join(missing[:5])}); each image X.jpg needs X.camera"
        )
    return np.stack([read_camera_centre(p) for p in paths])


def radius_ground_truth(
    reference: np.ndarray, query: np.ndarray, radius: float
) -> list[np.ndarray]:
    """References within ``radius`` (Euclidean, ``<=``, as sklearn's
    ``radius_neighbors``) of each query: ``reference [R, d]``, ``query [Q, d]``."""
    from scipy.spatial import cKDTree

    tree = cKDTree(reference)
    return [np.array(sorted(h), dtype=np.int64) for h in tree.query_ball_point(query, radius)]


MSLS_FILES = {
    "qImages": "msls_val_qImages.npy",
    "qIdx": "msls_val_qIdx.npy",
    "pIdx": "msls_val_pIdx.npy",
    "dbImages": "msls_val_dbImages.npy",
}


def msls_city(path: str) -> str | None:
    """The city of an MSLS list path as the authors' ``segregate_data_by_city`` decides
    it: ``cph`` when the path contains it (checked first), else ``sf``, else none."""
    if "cph" in path:
        return "cph"
    if "sf" in path:
        return "sf"
    return None


def msls_ground_truth(
    folder: Path, city: str, reference: list[Path], query: list[Path]
) -> list[np.ndarray]:
    """Positives of one MSLS validation city from the published lists: the kept queries
    ``qImages[qIdx]``, their positives ``pIdx`` (indices into ``dbImages``), both
    restricted to ``city`` (Revisit-Anything's mslsSF / mslsCPH) or, with ``"all"``, as
    they stand (the 740-query MSLS-val of MixVPR and SALAD); images are matched by file
    name. A listed positive or a
    query that is missing from the folders is an error (it would change the recall)."""
    arrays = {}
    for key, name in MSLS_FILES.items():
        path = folder / name
        if not path.is_file():
            raise DatasetError(
                f"ground_truth (msls): {path} does not exist; copy the four msls_val_*.npy "
                "files (serizba/salad datasets/msls_val/) into the dataset folder"
            )
        arrays[key] = load_object_npy(path)
    kept = [str(arrays["qImages"][i]) for i in np.asarray(arrays["qIdx"], dtype=np.int64)]
    if len(kept) != len(arrays["pIdx"]):
        raise DatasetError(
            f"{folder / MSLS_FILES['pIdx']}: {len(arrays['pIdx'])} rows for {len(kept)} kept "
            f"queries of {MSLS_FILES['qIdx']}"
        )
    db_names = [Path(str(p)).name for p in arrays["dbImages"]]
    db_city = [msls_city(str(p)) for p in arrays["dbImages"]]
    ref_index = {p.name: i for i, p in enumerate(reference)}
    positives_of = {}
    for path, positives in zip(kept, arrays["pIdx"], strict=True):
        if city == "all" or msls_city(path) == city:
            positives_of[Path(path).name] = [
                int(p)
                for p in np.asarray(positives, dtype=np.int64)
                if city == "all" or db_city[p] == city
            ]
    unknown = [q.name for q in query if q.name not in positives_of]
    if unknown:
        raise DatasetError(
            f"ground_truth (msls, city {city}): {len(unknown)} query image(s) are not among "
            f"the {len(positives_of)} kept {city} queries of {MSLS_FILES['qIdx']} (e.g. "
            f"{', '.join(unknown[:5])}); the published protocol evaluates only those"
        )
    truth = []
    for q in query:
        names = [db_names[p] for p in positives_of[q.name]]
        absent = [n for n in names if n not in ref_index]
        if absent:
            raise DatasetError(
                f"ground_truth (msls, city {city}): positives of query {q.name} are missing "
                f"from the reference folder (e.g. {', '.join(absent[:5])})"
            )
        truth.append(np.unique(np.array([ref_index[n] for n in names], dtype=np.int64)))
    return truth


def matches_csv_ground_truth(path: Path, n_query: int, n_ref: int) -> list[np.ndarray]:
    """Positives from a table of ranked matches, AnyLoc's Nardo-Air ``gt_matches.csv``:
    row ``i`` (after the header) holds query ``i``'s positives in its ``top_<k>_ref_ind``
    columns (the authors' ``aerial_dataloader`` reads rows by position; ``query_ind`` is
    not consulted). Indices must be integers within the references."""
    import csv

    if not path.is_file():
        raise DatasetError(f"ground_truth.file {path} does not exist")
    with open(path, newline="", encoding="utf-8-sig") as f:
        reader = csv.DictReader(f)
        columns = [c for c in reader.fieldnames or [] if re.fullmatch(r"top_\d+_ref_ind", c)]
        if not columns:
            raise DatasetError(
                f"{path}: no top_<k>_ref_ind columns (header: {reader.fieldnames}); expected "
                "AnyLoc's gt_matches.csv"
            )
        columns.sort(key=lambda c: int(c.split("_")[1]))
        truth = []
        for row, record in enumerate(reader):
            indices = []
            for column in columns:
                text = (record[column] or "").strip()
                try:
                    value = float(text)
                except ValueError:
                    value = float("nan")
                if not value.is_integer() or not 0 <= value < n_ref:
                    raise DatasetError(
                        f"{path} row {row + 2}: {column} = {text!r} is not a reference index "
                        f"(0..{n_ref - 1})"
                    )
                indices.append(int(value))
            truth.append(np.unique(np.array(indices, dtype=np.int64)))
    if len(truth) != n_query:
        raise DatasetError(f"{path} has {len(truth)} rows but the dataset has {n_query} queries")
    return truth

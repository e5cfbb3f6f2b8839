"""Place datasets: folder layouts, image lists and ground truth (docs/methods.md §9).

A dataset is a reference folder and a query folder under ``<data_root>/<path>``
(VPR-Bench layout: ``ref/`` and ``query/``; paired RGB-thermal layout: ``vi/`` and
``ir/`` with matching file names). Ground truth is a list, per query, of the
reference indices that count as correct. Four kinds are supported:

- ``vprbench``: a VPR-Bench ``ground_truth_new.npy`` object array of
  ``[query_index, [ref indices]]`` rows, read without executing arbitrary pickles;
- ``frame_window``: query ``i`` matches references ``j`` with ``|i - j| <= radius``;
- ``utm``: references within ``radius`` metres, UTM easting and northing taken from
  ``@easting@northing@`` in the file names (Pitts30k, SF-XL, MSLS convention);
- ``pairs``: query ``i`` matches reference ``i`` (aligned RGB-thermal pairs).
"""

from __future__ import annotations

import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vprflow.images import list_images


class DatasetError(ValueError):
    """Bad dataset input; the message names the folder, file or value at fault."""


@dataclass(frozen=True)
class DatasetFiles:
    """Image paths of one dataset, each list in natural sort order."""

    reference: list[Path]
    query: list[Path]


def dataset_folder(data_root: str | Path, spec: dict) -> Path:
    return Path(data_root) / spec["path"]


def list_dataset(data_root: str | Path, name: str, spec: dict) -> DatasetFiles:
    """List reference and query images, failing with a message that says what is missing.

    ``spec`` keys: ``path``, ``reference``, ``query`` (folder names), ``paired``
    (file names must match one to one), optional ``source`` (where to get the data).
    """
    root = dataset_folder(data_root, spec)
    hint = f" Get it from {spec['source']}." if spec.get("source") else ""
    if not root.is_dir():
        if spec.get("download"):
            from vprflow.download import download_hint

            hint = f" Download it with `{download_hint(name)}` (then run again).{hint}"
        raise DatasetError(
            f"dataset '{name}': folder {root} does not exist. Put the dataset there "
            f"(with '{spec['reference']}/' and '{spec['query']}/' inside) or set "
            f"data_root.{hint}"
        )
    lists = []
    for role in ("reference", "query"):
        folder = root / spec[role]
        if not folder.is_dir():
            raise DatasetError(f"dataset '{name}': {role} folder {folder} does not exist.{hint}")
        images = list_images(folder)
        if not images:
            raise DatasetError(f"dataset '{name}': {role} folder {folder} contains no images")
        lists.append(images)
    files = DatasetFiles(reference=lists[0], query=lists[1])
    if spec.get("paired"):
        check_pairs(name, files)
    return files


def check_pairs(name: str, files: DatasetFiles) -> None:
    """Paired layouts need the same file names (up to suffix) in both folders."""
    ref = {p.stem: p for p in files.reference}
    query = {p.stem: p for p in files.query}
    only_ref = sorted(set(ref) - set(query))
    only_query = sorted(set(query) - set(ref))
    if only_ref or only_query:
        problems = [str(ref[s]) for s in only_ref[:5]] + [str(query[s]) for s in only_query[:5]]
        raise DatasetError(
            f"dataset '{name}' is paired but {len(only_ref) + len(only_query)} file(s) have "
            f"no partner in the other folder, e.g. {', '.join(problems)}"
        )


# ---------------------------------------------------------------- ground truth


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler for numpy object arrays of plain lists and ints: nothing else loads."""

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
                array = _NumpyOnlyUnpickler(f).load()
            except (pickle.UnpicklingError, EOFError, AttributeError) as error:
                raise DatasetError(f"{path}: unreadable object array: {error}") from error
            return np.asarray(array)
        f.seek(0)
    return np.load(path, allow_pickle=False)


def vprbench_ground_truth(
    path: str | Path, n_query: int, n_ref: int, drop_out_of_range: bool = False
) -> list[np.ndarray]:
    """Per-query reference indices from a VPR-Bench ``ground_truth_new.npy``.

    Rows are ``[query_index, [ref indices]]``. The number of rows must equal the
    number of query images. Reference indices beyond the reference set are an error
    unless ``drop_out_of_range`` (the published 17places file lists references 406
    and 407 of a 406-image set).
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"ground-truth file {path} does not exist")
    table = load_object_npy(path)
    if table.ndim != 2 or table.shape[1] != 2:
        raise DatasetError(
            f"{path}: expected rows of [query_index, [ref indices]], got {table.shape}"
        )
    if len(table) != n_query:
        raise DatasetError(
            f"{path} has {len(table)} ground-truth rows but the dataset has {n_query} query images"
        )
    query_indices = [int(q) for q in table[:, 0]]
    outside = [(row, q) for row, q in enumerate(query_indices) if not 0 <= q < n_query]
    if outside:
        row, q = outside[0]
        raise DatasetError(f"{path}: row {row} has query index {q}, outside 0..{n_query - 1}")
    rows_of: dict[int, list[int]] = {}
    for row, q in enumerate(query_indices):
        rows_of.setdefault(q, []).append(row)
    repeated = {q: rows for q, rows in rows_of.items() if len(rows) > 1}
    if repeated:
        listing = "; ".join(f"query {q} in rows {rows}" for q, rows in sorted(repeated.items())[:5])
        missing = sorted(set(range(n_query)) - set(rows_of))
        raise DatasetError(
            f"{path}: {len(repeated)} query index(es) appear in more than one row ({listing}); "
            f"queries with no row: {missing[:10]}. Each query must have exactly one row."
        )
    truth: list[np.ndarray] = [np.zeros(0, dtype=np.int64)] * n_query
    for query_index, refs in table:
        q = int(query_index)
        refs = np.asarray(refs, dtype=np.int64).reshape(-1)
        bad = refs[(refs < 0) | (refs >= n_ref)]
        if len(bad) and not drop_out_of_range:
            raise DatasetError(
                f"{path}: query {q} lists reference indices {bad.tolist()} but the dataset has "
                f"{n_ref} reference images (set ground_truth.drop_out_of_range: true to drop them)"
            )
        truth[q] = np.unique(refs[(refs >= 0) & (refs < n_ref)])
    return truth


def frame_window_ground_truth(n_query: int, n_ref: int, radius: int) -> list[np.ndarray]:
    """Query ``i`` matches every reference ``j`` with ``|i - j| <= radius``."""
    return [
        np.arange(max(0, i - radius), min(n_ref, i + radius + 1), dtype=np.int64)
        for i in range(n_query)
    ]


def pairs_ground_truth(n_query: int, n_ref: int) -> list[np.ndarray]:
    """Query ``i`` matches reference ``i`` (aligned pairs)."""
    if n_query != n_ref:
        raise DatasetError(
            f"pairs ground truth needs as many queries as references ({n_query} vs {n_ref})"
        )
    return [np.array([i], dtype=np.int64) for i in range(n_query)]


def utm_from_name(path: str | Path) -> tuple[float, float]:
    """``(easting, northing)`` from a file name of the form ``@easting@northing@...``."""
    parts = Path(path).name.split("@")
    try:
        return float(parts[1]), float(parts[2])
    except (IndexError, ValueError) as error:
        raise DatasetError(
            f"{path}: file name has no '@easting@northing@' UTM coordinates"
        ) from error


def utm_ground_truth(
    reference: list[Path], query: list[Path], radius: float = 25.0
) -> list[np.ndarray]:
    """References within ``radius`` metres (Euclidean in UTM) of each query."""
    from scipy.spatial import cKDTree

    ref_xy = np.array([utm_from_name(p) for p in reference], dtype=np.float64)
    query_xy = np.array([utm_from_name(p) for p in query], dtype=np.float64)
    tree = cKDTree(ref_xy)
    return [
        np.array(sorted(hits), dtype=np.int64) for hits in tree.query_ball_point(query_xy, radius)
    ]


def ground_truth(files: DatasetFiles, spec: dict, folder: Path) -> list[np.ndarray]:
    """Dispatch on ``spec['kind']``; see the module docstring for the kinds."""
    n_query, n_ref = len(files.query), len(files.reference)
    kind = spec["kind"]
    if kind == "vprbench":
        truth = vprbench_ground_truth(
            folder / spec["file"], n_query, n_ref, spec.get("drop_out_of_range", False)
        )
    elif kind == "frame_window":
        truth = frame_window_ground_truth(n_query, n_ref, int(spec["radius"]))
    elif kind == "utm":
        truth = utm_ground_truth(files.reference, files.query, float(spec.get("radius", 25.0)))
    elif kind == "pairs":
        truth = pairs_ground_truth(n_query, n_ref)
    else:
        raise DatasetError(f"unknown ground-truth kind {kind!r}")
    if not any(len(t) for t in truth):
        source = folder / spec["file"] if kind == "vprbench" else f"{folder} ({kind})"
        raise DatasetError(
            f"ground truth {ground_truth_rule(spec)} from {source}: no query has a positive "
            f"among the {n_ref} references, so recall is undefined; check the file or rule"
        )
    return truth


def ground_truth_rule(spec: dict) -> str:
    """A short human-readable name of the rule, for results tables."""
    kind = spec["kind"]
    if kind == "vprbench":
        return f"vprbench:{spec['file']}"
    if kind == "frame_window":
        return f"frame_window:+-{spec['radius']}"
    if kind == "utm":
        return f"utm:{spec.get('radius', 25.0)}m"
    return kind


def ground_truth_files(data_root: str | Path, spec: dict) -> list[Path]:
    """Files the ground truth is read from (inputs of the dataset stage)."""
    if spec["ground_truth"]["kind"] == "vprbench":
        return [dataset_folder(data_root, spec) / spec["ground_truth"]["file"]]
    return []

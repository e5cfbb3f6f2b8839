"""Ground-truth files as the papers' code ships them (docs/datasets.md), read without
running arbitrary pickles, each matched to the images by name rather than by position.

- Baidu Mall: one plain-text ``.camera`` file per image (AnyLoc/Revisit-Anything
  ``dataloaders/baidu_dataloader.py``): the camera centre is the second-to-last line.
- Position arrays (InsideOut's ``gps_db_correct.pkl`` / ``gps_q_new.pkl``): ``[N, 2]``
  metric coordinates in the authors' image order, ``natsorted`` file names.
- MSLS validation lists (``msls_val_{qImages,qIdx,pIdx,dbImages}.npy``, shipped by
  serizba/salad and Revisit-Anything): positives as database indices per kept query;
  the lists also name the dataset's images (:func:`msls_listed_images`).
"""

from __future__ import annotations

import csv
import logging
import pickle
import re
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from vprflow.core.errors import DatasetError, short_repr
from vprflow.core.lazy import lazy_import
from vprflow.data.images import natural_key

spatial = lazy_import("scipy.spatial")

log = logging.getLogger("vprflow")


def as_index(value, where: str) -> int:
    """``value`` as an index: an integer (Python or numpy) or an integral float.

    A fractional float truncated (2.5 -> 2) or a boolean read as 0 or 1 would give a
    believable but wrong ground truth, so both are refused. ``where``
    names the file, row and field (``"<file> row 4: reference index"``).
    """
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    # bool is an int and timedelta64 a numpy integer, but neither is an index.
    if isinstance(value, (bool, np.bool_)):
        raise DatasetError(f"{where} {value!r} is a boolean, not an integer")
    if isinstance(value, (int, np.integer)) and not isinstance(value, np.timedelta64):
        return int(value)
    if isinstance(value, (float, np.floating)) and float(value).is_integer():
        return int(value)
    raise DatasetError(f"{where} {short_repr(value)} is not an integer")


def reference_indices(refs, where: str) -> list[int]:
    """The positives of one row: a list, tuple or 1-D array of indices, or one index."""
    if isinstance(refs, np.ndarray) and refs.ndim > 1:
        raise DatasetError(
            f"{where} positives are a {refs.ndim}-D array of shape {refs.shape}; "
            "expected a flat list of reference indices"
        )
    if isinstance(refs, np.ndarray) and refs.ndim == 1 and refs.dtype.kind in "iu":
        return refs.tolist()  # valid as a whole: spares long arrays the loop below
    if isinstance(refs, (list, tuple)) or (isinstance(refs, np.ndarray) and refs.ndim == 1):
        items = list(refs)
    elif isinstance(refs, (np.ndarray, int, float, np.number, np.bool_)):
        items = [refs]  # a single index, as the old reshape(-1) read it
    else:
        raise DatasetError(
            f"{where} positives {short_repr(refs)}: expected a list of reference indices"
        )
    return [as_index(item, f"{where} reference index") for item in items]


def published_order(names: list[str]) -> list[int]:
    """Indices that put ``names`` in ``natsort.natsorted`` order (its default ``ns.INT``),
    the order in which the authors' code lists images and writes per-image arrays: the
    order vprflow lists images in (:func:`vprflow.data.images.natural_key`)."""
    return sorted(range(len(names)), key=lambda i: natural_key(names[i]))


class _PlainUnpickler(pickle._Unpickler):
    """Lists, tuples, numbers and numpy arrays of them: any other class is refused, and
    so is an array larger than the file could hold (``limit``: the file's size in bytes).

    The pure-Python unpickler, because numpy's ``ndarray.__setstate__`` allocates the
    shape its state names before it looks at the data: the state is checked first
    (:meth:`load_build`). Ground-truth pickles are small, so its speed does not matter.
    """

    dispatch = dict(pickle._Unpickler.dispatch)

    def __init__(self, file, limit: int):
        super().__init__(file)
        self.limit = limit

    def find_class(self, module, name):
        if module in ("numpy.core.multiarray", "numpy._core.multiarray"):
            if name == "_reconstruct":
                return _Reconstruct(self.limit)
            if name == "scalar":
                return _Scalar(self.limit, super().find_class(module, name))
        if (module, name) == ("numpy", "ndarray"):
            return _NdarrayName
        if (module, name) == ("numpy", "dtype"):
            return np.dtype
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} from a ground-truth file")

    def load_build(self):
        inst, state = self.stack[-2], self.stack[-1]
        if isinstance(inst, np.ndarray):
            # ndarray state: ([version,] shape, dtype, is_fortran, data)
            fields = state[1:] if isinstance(state, tuple) and len(state) == 5 else state
            if not isinstance(fields, tuple) or len(fields) != 4:
                raise pickle.UnpicklingError(f"array state {type(state).__name__} is malformed")
            _check_array_fits(fields[0], fields[1], self.limit)
        super().load_build()

    dispatch[pickle.BUILD[0]] = load_build


def _array_bytes(shape, dtype) -> tuple[int, int]:
    """Elements and bytes of an array of ``shape`` and ``dtype`` (Python ints: a shape
    such as ``(2**40, 2**40)`` must not overflow)."""
    count = 1
    for side in shape:
        count *= int(side)
    return count, count * int(dtype.itemsize)


def _check_array_fits(shape, dtype, limit: int, room: str = "the whole file") -> None:
    """Refuse, before any memory is asked for, an array that a file of ``limit`` bytes
    cannot hold: its raw bytes (or, for Python objects, one byte of pickle per element at
    the least) would have to be in the file. A crafted shape otherwise ends in a
    ``MemoryError`` that names no file."""
    if not isinstance(shape, tuple) or not all(
        isinstance(side, (int, np.integer)) and not isinstance(side, (bool, np.bool_))
        for side in shape
    ):
        raise pickle.UnpicklingError(f"array shape {shape!r} is not a tuple of integers")
    if not isinstance(dtype, np.dtype):
        raise pickle.UnpicklingError(f"array dtype {dtype!r} is not a numpy dtype")
    if any(int(side) < 0 for side in shape):
        raise pickle.UnpicklingError(f"array shape {shape} has a negative side")
    count, size = _array_bytes(shape, dtype)
    need = count if dtype.hasobject else size
    if need > limit:
        what = f"{count:,} objects" if dtype.hasobject else f"{size:,} bytes"
        raise pickle.UnpicklingError(
            f"an array of shape {shape} and dtype {dtype} ({what}), more than {room} "
            f"({limit:,} bytes) could hold; refusing to allocate it"
        )


class _NdarrayName:
    """What ``numpy.ndarray`` unpickles to: a name that only :class:`_Reconstruct`
    accepts. The class itself would let a pickle call ``ndarray(shape)``, which
    allocates whatever the shape asks."""

    def __new__(cls, *args, **kwargs):
        raise pickle.UnpicklingError(
            "refusing to call numpy.ndarray from a ground-truth file (numpy's own pickles never do)"
        )


class _Reconstruct:
    """numpy's ``_reconstruct(ndarray, shape, dtype)``, after :func:`_check_array_fits`."""

    def __init__(self, limit: int):
        self.limit = limit

    def __call__(self, subtype, shape, dtype):
        if subtype is not _NdarrayName:
            raise pickle.UnpicklingError(f"refusing to reconstruct an array of {subtype!r}")
        try:
            dtype = np.dtype(dtype)
        except TypeError as error:
            raise pickle.UnpicklingError(f"array dtype {dtype!r}: {error}") from error
        _check_array_fits(shape, dtype, self.limit)
        return np.ndarray.__new__(np.ndarray, shape, dtype)


class _Scalar:
    """numpy's ``scalar(dtype, data)``, after checking that one item fits the file."""

    def __init__(self, limit: int, function):
        self.limit, self.function = limit, function

    def __call__(self, dtype, *args):
        _check_array_fits((), dtype, self.limit)
        return self.function(dtype, *args)


def _load_plain_pickle(f, limit: int):
    """The object pickled in ``f`` (see :class:`_PlainUnpickler`); a malformed pickle
    raises :class:`pickle.UnpicklingError` whatever the pure-Python unpickler raised."""
    try:
        return _PlainUnpickler(f, limit).load()
    except (pickle.UnpicklingError, EOFError):
        raise
    except (AttributeError, ValueError, TypeError, IndexError, KeyError, RecursionError) as error:
        raise pickle.UnpicklingError(
            f"malformed pickle ({type(error).__name__}: {error})"
        ) from error


def load_object_npy(path: str | Path) -> np.ndarray:
    """Load a ``.npy`` file, including object arrays, without running arbitrary pickles
    and without allocating more than the file could hold: an array whose header or
    pickle declares a shape too large for the file's size is refused, naming the file."""
    path = Path(path)
    limit = path.stat().st_size
    with open(path, "rb") as f:
        try:
            version = np.lib.format.read_magic(f)
            read_header = {
                (1, 0): np.lib.format.read_array_header_1_0,
                (2, 0): np.lib.format.read_array_header_2_0,
            }.get(version)
            if read_header is None:
                raise ValueError(f"unsupported .npy version {version}")
            shape, _fortran, dtype = read_header(f)
        except ValueError as error:
            raise DatasetError(f"{path} is not a .npy file: {error}") from error
        try:
            _check_array_fits(shape, dtype, limit - f.tell(), "the data after it")
        except pickle.UnpicklingError as error:
            raise DatasetError(f"{path}: its header declares {error}") from error
        if dtype.hasobject:
            try:
                array = _load_plain_pickle(f, limit)
            except pickle.UnpicklingError as error:
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
                raw = _load_plain_pickle(f, path.stat().st_size)
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
    tree = spatial.cKDTree(reference)
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


@dataclass(frozen=True)
class MslsLists:
    """The four published MSLS validation lists, their values checked: ``db`` the
    database paths (``dbImages``), ``kept`` the kept query paths (``qImages[qIdx]``, in
    ``qIdx`` order) and ``positives`` per kept query its ``pIdx`` row (indices into
    ``db``)."""

    db: list[str]
    kept: list[str]
    positives: list[list[int]]

    def database(self, city: str) -> list[int]:
        """Rows of ``db`` in ``city`` (``"all"``: every row), as Revisit-Anything's
        ``segregate_data_by_city`` splits them."""
        return [i for i, p in enumerate(self.db) if city == "all" or msls_city(p) == city]

    def queries(self, city: str) -> list[int]:
        """Rows of ``kept`` (and ``positives``) in ``city`` (``"all"``: every row)."""
        return [i for i, p in enumerate(self.kept) if city == "all" or msls_city(p) == city]


def _msls_paths(array: np.ndarray, path: Path) -> list[str]:
    """A list of image paths (``dbImages``, ``qImages``): a 1-D array of strings."""
    if array.ndim != 1 or not all(isinstance(v, str) for v in array.tolist()):
        raise DatasetError(
            f"{path} holds {array.dtype} {array.shape}; expected a flat list of image paths"
        )
    return [str(v) for v in array.tolist()]


def _msls_index(value, where: str, n: int, listing: str) -> int:
    """``value`` as an index into a list of ``n`` (VPR-Bench files' value rules: no
    fraction, boolean or string; no negative index, which numpy would wrap to the end)."""
    index = as_index(value, where)
    if not 0 <= index < n:
        raise DatasetError(f"{where} {index} is outside 0..{n - 1} ({listing} has {n})")
    return index


def read_msls_lists(folder: Path) -> MslsLists:
    """The published lists in ``folder``, read as serizba/salad's
    ``dataloaders/val/MapillaryDataset.py`` reads them (``qImages[qIdx]``, ``pIdx``),
    with the values VPR-Bench files must hold: every index an integer (no fraction,
    boolean or string) within its list (no ``-1``, which numpy wraps to the last image),
    each kept query once. Errors name the file, the row and the value."""
    arrays, paths = {}, {}
    for key, name in MSLS_FILES.items():
        paths[key] = folder / name
        if not paths[key].is_file():
            raise DatasetError(
                f"ground_truth (msls): {paths[key]} does not exist; copy the four "
                "msls_val_*.npy files (serizba/salad datasets/msls_val/) into the dataset folder"
            )
        arrays[key] = load_object_npy(paths[key])
    db = _msls_paths(arrays["dbImages"], paths["dbImages"])
    queries = _msls_paths(arrays["qImages"], paths["qImages"])
    if arrays["qIdx"].ndim != 1:
        raise DatasetError(
            f"{paths['qIdx']} holds {arrays['qIdx'].dtype} {arrays['qIdx'].shape}; expected "
            "a flat list of query indices"
        )
    rows_of: dict[int, int] = {}
    for row, value in enumerate(arrays["qIdx"].tolist()):
        where = f"{paths['qIdx']} row {row}: query index"
        index = _msls_index(value, where, len(queries), MSLS_FILES["qImages"])
        if index in rows_of:
            raise DatasetError(
                f"{paths['qIdx']} rows {rows_of[index]} and {row}: query index {index} "
                f"({queries[index]}) is kept twice; each kept query has one row of positives "
                f"in {MSLS_FILES['pIdx']}"
            )
        rows_of[index] = row
    kept = [queries[i] for i in rows_of]
    n_rows = len(arrays["pIdx"]) if arrays["pIdx"].ndim else 0
    if n_rows != len(kept):
        raise DatasetError(
            f"{paths['pIdx']}: {n_rows} rows for {len(kept)} kept queries of {MSLS_FILES['qIdx']}"
        )
    positives = []
    for row, refs in enumerate(arrays["pIdx"]):
        where = f"{paths['pIdx']} row {row}:"
        positives.append(
            [
                _msls_index(p, f"{where} reference index", len(db), MSLS_FILES["dbImages"])
                for p in reference_indices(refs, where)
            ]
        )
    return MslsLists(db, kept, positives)


def _by_name(paths: list[str], list_file: str, rows: list[int]) -> dict[str, int]:
    """Row of each listed file name (``rows`` of ``paths``): images are matched to the
    lists by name, so two listed paths of one name are an error naming both rows."""
    first: dict[str, int] = {}
    for row in rows:
        name = PurePosixPath(paths[row]).name
        if name in first and paths[first[name]] != paths[row]:
            raise DatasetError(
                f"{list_file} rows {first[name]} and {row} ({paths[first[name]]}, "
                f"{paths[row]}) have one file name, {name}; images are matched by name"
            )
        first.setdefault(name, row)
    return first


def msls_listed_images(
    folder: Path, city: str, reference: list[Path], query: list[Path]
) -> tuple[list[Path], list[Path]]:
    """The images of an MSLS dataset as the published reader reads them: the references
    are the database images the lists name (``dbImages`` of ``city``), the queries the
    kept ones (``qImages[qIdx]`` of ``city``), matched to ``reference`` and ``query``
    (the images found, in their order) by file name. Images found but not listed are
    left out and counted in a warning (the raw Copenhagen database holds 12,601 images,
    the lists 12,556: the other 45 would be distractors no published number ranks); a
    listed image that was not found is an error naming it."""
    lists = read_msls_lists(folder)
    out = []
    for role, found, paths, rows, list_file in (
        ("reference", reference, lists.db, lists.database(city), MSLS_FILES["dbImages"]),
        ("query", query, lists.kept, lists.queries(city), MSLS_FILES["qIdx"]),
    ):
        listed = _by_name(paths, list_file, rows)
        found_by_name: dict[str, Path] = {}
        for path in found:
            if path.name in listed and path.name in found_by_name:
                raise DatasetError(
                    f"ground_truth (msls): {found_by_name[path.name]} and {path} are both "
                    f"{path.name}, listed once in {list_file}; keep one"
                )
            found_by_name[path.name] = path
        missing = [name for name in listed if name not in found_by_name]
        if missing:
            raise DatasetError(
                f"ground_truth (msls, city {city}): {len(missing)} {role} image(s) listed in "
                f"{folder / list_file} were not found among the {len(found)} {role} images "
                f"(e.g. {', '.join(missing[:5])}); the published protocol reads every one"
            )
        kept = [path for path in found if path.name in listed]
        left_out = [path for path in found if path.name not in listed]
        if left_out:
            log.warning(
                "ground_truth (msls, city %s): %d of the %d %s images are not in %s and are "
                "left out, as the published reader never reads them (e.g. %s)",
                city,
                len(left_out),
                len(found),
                role,
                list_file,
                ", ".join(p.name for p in left_out[:5]),
            )
        out.append(kept)
    return out[0], out[1]


def msls_ground_truth(
    folder: Path, city: str, reference: list[Path], query: list[Path]
) -> list[np.ndarray]:
    """Positives of one MSLS validation city from the published lists
    (:func:`read_msls_lists`): the kept queries ``qImages[qIdx]``, their positives
    ``pIdx`` (indices into ``dbImages``), both restricted to ``city`` (Revisit-Anything's
    mslsSF / mslsCPH) or, with ``"all"``, as they stand (the 740-query MSLS-val of MixVPR
    and SALAD); images are matched by file name. The images must be the listed ones
    (:func:`msls_listed_images`): a query outside the kept list, a reference outside the
    database list (a distractor no published number ranks) or a listed positive missing
    from the references is an error. A kept query whose listed positives all lie in the
    other city has none left; a warning counts and names those queries (Revisit-Anything
    leaves them out of Recall@N, the ``with_positives`` denominator)."""
    lists = read_msls_lists(folder)
    db_names = [PurePosixPath(p).name for p in lists.db]
    db_rows = lists.database(city)
    listed_db = _by_name(lists.db, MSLS_FILES["dbImages"], db_rows)
    kept_rows = _by_name(lists.kept, MSLS_FILES["qIdx"], lists.queries(city))
    in_city = set(db_rows)
    for paths, listed, what, why in (
        (query, kept_rows, f"kept {city} queries of {MSLS_FILES['qIdx']}", "evaluates only"),
        (reference, listed_db, f"{city} database images of {MSLS_FILES['dbImages']}", "ranks only"),
    ):
        outside = [p.name for p in paths if p.name not in listed]
        if outside:
            raise DatasetError(
                f"ground_truth (msls, city {city}): {len(outside)} "
                f"{'query' if paths is query else 'reference'} image(s) are not among the "
                f"{len(listed)} {what} (e.g. {', '.join(outside[:5])}); the published "
                f"protocol {why} those"
            )
    ref_index = {p.name: i for i, p in enumerate(reference)}
    truth = []
    elsewhere = []
    for q in query:
        listed = lists.positives[kept_rows[q.name]]
        names = [db_names[p] for p in listed if p in in_city]
        if listed and not names:
            elsewhere.append(q.name)
        absent = [n for n in names if n not in ref_index]
        if absent:
            raise DatasetError(
                f"ground_truth (msls, city {city}): positives of query {q.name} are missing "
                f"from the reference folder (e.g. {', '.join(absent[:5])})"
            )
        truth.append(np.unique(np.array([ref_index[n] for n in names], dtype=np.int64)))
    if elsewhere:
        log.warning(
            "ground_truth (msls, city %s): %d of the %d kept %s queries have their listed "
            "positives (%s) only in the other city, so none after the city filter (e.g. %s)",
            city,
            len(elsewhere),
            len(query),
            city,
            MSLS_FILES["pIdx"],
            ", ".join(elsewhere[:5]),
        )
    return truth


def matches_csv_ground_truth(path: Path, n_query: int, n_ref: int) -> list[np.ndarray]:
    """Positives from a table of ranked matches, AnyLoc's Nardo-Air ``gt_matches.csv``:
    row ``i`` (after the header) holds query ``i``'s positives in its ``top_<k>_ref_ind``
    columns (the authors' ``aerial_dataloader`` reads rows by position; ``query_ind`` is
    not consulted). Indices must be integers within the references."""
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

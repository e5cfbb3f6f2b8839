"""Place datasets: folder layouts, image lists and ground truth (docs/methods.md §9).

A dataset is a reference folder and a query folder under ``<data_root>/<path>``
(VPR-Bench layout: ``ref/`` and ``query/``; paired RGB-thermal layout: ``vi/`` and
``ir/`` with matching file names), searched recursively unless ``recursive: false``;
either may instead be a ``.txt`` file listing image paths relative to the dataset
folder, one per line, in the order given. Ground truth is a list, per query, of the
reference indices that count as correct. The kinds:

- ``vprbench``: a VPR-Bench ``ground_truth_new.npy`` object array of
  ``[query_index, [ref indices]]`` rows, read without executing arbitrary pickles;
- ``frame_window``: query ``i`` matches references ``j`` with ``|i - j| <= radius``;
- ``utm``: references within ``radius`` metres, UTM easting and northing taken from
  ``@easting@northing@`` in the file names (Pitts30k, SF-XL, MSLS convention);
- ``pairs``: query ``i`` matches reference ``i`` (aligned RGB-thermal pairs);
- ``coordinates``: references within ``radius_m`` metres of each query, positions
  from a CSV file (``lat``/``lon``: great-circle distance; ``easting``/``northing``:
  Euclidean) or from the images' EXIF GPS tags (``source: exif``), optionally also
  within ``max_heading_diff`` degrees of the query's ``heading`` (as MSLS);
- ``none``: no ground truth; the workflow ranks and draws, but computes no recall.
"""

from __future__ import annotations

import os
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vprflow.images import IMAGE_SUFFIXES, ImageScan, natural_key, scan_images


class DatasetError(ValueError):
    """Bad dataset input; the message names the folder, file or value at fault."""


@dataclass(frozen=True)
class DatasetFiles:
    """Image paths of one dataset (folders: natural order of relative paths; list
    files: their order), and per role how many entries were skipped (hidden, other)."""

    reference: list[Path]
    query: list[Path]
    skipped: dict[str, tuple[int, int]] | None = None


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
    scans: dict[str, ImageScan] = {}
    for role in ("reference", "query"):
        entry = root / spec[role]
        if entry.suffix.lower() == ".txt":
            scans[role] = read_image_list(entry, root, f"dataset '{name}': {role} list")
            continue
        if not entry.is_dir():
            raise DatasetError(f"dataset '{name}': {role} folder {entry} does not exist.{hint}")
        scans[role] = scan_images(entry, spec["recursive"], spec["follow_links"])
        if not scans[role].paths:
            raise DatasetError(f"dataset '{name}': {role} folder {entry} contains no images")
    reference, query = scans["reference"].paths, scans["query"].paths
    check_disjoint(name, reference, query)
    if spec["paired"]:
        query = paired_queries(
            name,
            reference,
            query,
            _role_base(root, spec, "reference", reference),
            _role_base(root, spec, "query", query),
        )
    return DatasetFiles(
        reference=reference,
        query=query,
        skipped={r: (s.skipped_hidden, s.skipped_other) for r, s in scans.items()},
    )


def _role_base(root: Path, spec: dict, role: str, paths: list[Path]) -> Path:
    """What a role's images are named relative to when pairing: its folder, or for a
    list file the folder its images have in common (``vi/`` of ``vi/1.jpg``)."""
    entry = root / spec[role]
    if entry.suffix.lower() != ".txt":
        return entry
    return Path(os.path.commonpath([p.parent for p in paths]))


def check_disjoint(
    name: str,
    reference: list[Path],
    query: list[Path],
    identity=os.path.realpath,
    same: str = "are also reference images",
) -> None:
    """References and queries must be different images: a query that is also a
    reference (the same folder twice, a link, an overlapping list; with ``identity`` a
    content hash, a copied file) is its own top-1. ``same`` says how they are the same."""
    first: dict[str, Path] = {}
    for path in reference:
        first.setdefault(identity(path), path)
    shared = [(first[key], q) for q in query if (key := identity(q)) in first]
    if shared:
        examples = ", ".join(f"{q} = {ref}" for ref, q in shared[:5])
        raise DatasetError(
            f"dataset '{name}': {len(shared)} query image(s) {same} (e.g. {examples}); "
            "each query would find itself at rank 1. Use separate reference and query images"
        )


def read_image_list(list_file: Path, root: Path, what: str) -> ImageScan:
    """Images named in ``list_file``, one path per line relative to ``root`` (blank
    lines and ``#`` comments ignored), in the file's order. Errors name the line."""
    if not list_file.is_file():
        raise DatasetError(f"{what}: image list {list_file} does not exist")
    paths: list[Path] = []
    seen: dict[str, int] = {}
    for number, line in enumerate(list_file.read_text().splitlines(), start=1):
        name = line.strip()
        if not name or name.startswith("#"):
            continue
        where = f"{what}: {list_file} line {number}"
        path = root / name
        if path.suffix.lower() not in IMAGE_SUFFIXES:
            raise DatasetError(f"{where}: {name!r} is not an image file name")
        if name in seen:
            raise DatasetError(f"{where}: {name!r} is listed again (first on line {seen[name]})")
        if not path.is_file():
            raise DatasetError(f"{where}: image {path} does not exist")
        seen[name] = number
        paths.append(path)
    if not paths:
        raise DatasetError(f"{what}: image list {list_file} names no images")
    return ImageScan(paths)


def paired_queries(
    name: str, reference: list[Path], query: list[Path], ref_base: Path, query_base: Path
) -> list[Path]:
    """The queries in the order of their partner references (query ``i`` pairs with
    reference ``i``). Partners have the same path relative to their role's folder, up
    to the suffix (``a/1.jpg`` and ``a/1.png``): matched by name, never by sort order.
    A name twice in one role (``1.jpg`` and ``1.png``) or without a partner is an error
    naming examples."""
    keyed = []
    for role, paths, base in (("reference", reference, ref_base), ("query", query, query_base)):
        by_key: dict[str, Path] = {}
        clashes = []
        for path in paths:
            key = path.relative_to(base).with_suffix("").as_posix()
            if key in by_key:
                clashes.append(f"{by_key[key]} and {path}")
            by_key[key] = path
        if clashes:
            raise DatasetError(
                f"dataset '{name}' is paired, but {len(clashes)} {role} name(s) occur with "
                f"two suffixes, so partners are ambiguous: {'; '.join(clashes[:5])}"
            )
        keyed.append(by_key)
    refs, queries = keyed
    only_ref = [refs[k] for k in refs if k not in queries]
    only_query = [queries[k] for k in queries if k not in refs]
    if only_ref or only_query:
        problems = [str(p) for p in only_ref[:5] + only_query[:5]]
        raise DatasetError(
            f"dataset '{name}' is paired but {len(only_ref) + len(only_query)} file(s) have "
            f"no partner of the same relative path (suffix aside) in the other folder, "
            f"e.g. {', '.join(problems)}"
        )
    return [queries[path.relative_to(ref_base).with_suffix("").as_posix()] for path in reference]


def contents_digest(files: DatasetFiles, data_root: str | Path, spec: dict, file_hash) -> str:
    """SHA-256 over every image's and the ground-truth file's name and content hash:
    what a dataset's key covers. ``file_hash(path, where) -> hex sha256``, ``where`` a
    config key (``reference``, ``query``, ``ground_truth.file``) to name in errors."""
    import hashlib

    digest = hashlib.sha256()
    root = dataset_folder(data_root, spec)
    for role, paths in (("reference", files.reference), ("query", files.query)):
        # Named relative to the role's folder (a list file's: the dataset folder), so a
        # flat folder hashes its file names and a nested one its relative paths.
        base = root / spec[role] if (root / spec[role]).is_dir() else root
        for path in paths:
            label = path.relative_to(base).as_posix()
            digest.update(f"{role}/{label}:{file_hash(path, role)}\n".encode())
    for path in ground_truth_files(data_root, spec):
        if path.exists():
            sha = file_hash(path, "ground_truth.file")
            digest.update(f"truth/{path.name}:{sha}\n".encode())
    return digest.hexdigest()[:32]


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


def _short_repr(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _as_index(value, where: str) -> int:
    """``value`` as an index: an integer (Python or numpy) or an integral float.

    A fractional float used to be truncated (2.5 -> 2) and a boolean read as 0 or 1;
    either gives a believable but wrong ground truth, so both are refused. ``where``
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
    raise DatasetError(f"{where} {_short_repr(value)} is not an integer")


def _reference_indices(refs, where: str) -> list[int]:
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
            f"{where} positives {_short_repr(refs)}: expected a list of reference indices"
        )
    return [_as_index(item, f"{where} reference index") for item in items]


def _folder_of(name: str) -> str:
    parent = name.rpartition("/")[0]
    return parent + "/" if parent else ""


def folder_counts(names: list[str], among: list[str] | None = None) -> str:
    """``" (query/: 111, query/extra/: 9; ...)"``: how many of ``names`` (image paths
    relative to the dataset folder) lie in each folder, for errors about counts.

    When one of those folders lies inside another folder holding images of ``among``
    (default ``names``), the recursive search found them, the usual source of extra
    images; the text then says how to switch it off.
    """
    counts: dict[str, int] = {}
    for folder in map(_folder_of, names):
        counts[folder] = counts.get(folder, 0) + 1
    # The dataset folder itself ("") holds only listed images: it is no search root.
    holding = {_folder_of(name) for name in (names if among is None else among)} - {""}
    nested = any(
        "/".join(parts[:depth]) + "/" in holding
        for parts in (folder.split("/") for folder in counts)
        for depth in range(1, len(parts) - 1)
    )
    ordered = sorted(counts.items(), key=lambda item: natural_key(item[0]))
    listing = ", ".join(f"{folder or './'}: {count}" for folder, count in ordered[:8])
    if len(ordered) > 8:
        listing += f", ... ({len(ordered) - 8} more folders)"
    if nested:
        listing += "; images in subfolders are found too unless the dataset sets recursive: false"
    return f" ({listing})"


def _role_folders(paths: list[Path], folder: Path) -> str:
    """:func:`folder_counts` of one role's images when they lie in more than one folder;
    empty when they share one, since the count then says all there is."""
    prefix = folder.as_posix().rstrip("/") + "/"
    # String prefixes, not Path.relative_to: this runs over every image of a dataset.
    names = [
        text[len(prefix) :] if text.startswith(prefix) else text
        for text in map(Path.as_posix, paths)
    ]
    if len({_folder_of(name) for name in names}) < 2:
        return ""
    return folder_counts(names)


def vprbench_ground_truth(
    path: str | Path,
    n_query: int,
    n_ref: int,
    drop_out_of_range: bool = False,
    *,
    query_folders: str = "",
    reference_folders: str = "",
) -> list[np.ndarray]:
    """Per-query reference indices from a VPR-Bench ``ground_truth_new.npy``.

    Rows are ``[query_index, [ref indices]]``: integers or integral floats, positives
    a list, tuple, 1-D array or single index; anything else (fractions, booleans,
    strings, nested lists) is an error naming the row. The number of rows must equal
    the number of query images. Reference indices beyond the reference set are an
    error unless ``drop_out_of_range`` (the published 17places file lists references
    406 and 407 of a 406-image set). ``query_folders`` and ``reference_folders``
    (:func:`folder_counts`) follow the image counts in errors.
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
            f"{path} has {len(table)} ground-truth rows but the dataset has {n_query} query "
            f"images{query_folders}"
        )
    query_indices = [
        _as_index(q, f"{path} row {row}: query index") for row, q in enumerate(table[:, 0])
    ]
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
    for row, (q, refs) in enumerate(zip(query_indices, table[:, 1], strict=True)):
        indices = _reference_indices(refs, f"{path} row {row}:")
        # Checked as Python ints: an index such as 1e30 would overflow int64.
        bad = [r for r in indices if not 0 <= r < n_ref]
        if bad and not drop_out_of_range:
            raise DatasetError(
                f"{path}: query {q} lists reference indices {bad} but the dataset has "
                f"{n_ref} reference images{reference_folders} (set "
                "ground_truth.drop_out_of_range: true to drop them)"
            )
        truth[q] = np.unique(np.array([r for r in indices if 0 <= r < n_ref], dtype=np.int64))
    return truth


def frame_window_ground_truth(n_query: int, n_ref: int, radius: int) -> list[np.ndarray]:
    """Query ``i`` matches every reference ``j`` with ``|i - j| <= radius``."""
    return [
        np.arange(max(0, i - radius), min(n_ref, i + radius + 1), dtype=np.int64)
        for i in range(n_query)
    ]


def pairs_ground_truth(
    n_query: int, n_ref: int, *, query_folders: str = "", reference_folders: str = ""
) -> list[np.ndarray]:
    """Query ``i`` matches reference ``i`` (aligned pairs). ``query_folders`` and
    ``reference_folders`` (:func:`folder_counts`) follow the image counts in errors."""
    if n_query != n_ref:
        raise DatasetError(
            "pairs ground truth needs as many queries as references, but the dataset has "
            f"{n_query} query images{query_folders} and {n_ref} reference "
            f"images{reference_folders}"
        )
    return [np.array([i], dtype=np.int64) for i in range(n_query)]


def utm_from_name(path: str | Path) -> tuple[float, float]:
    """``(easting, northing)`` from a file name of the form ``@easting@northing@...``."""
    parts = Path(path).name.split("@")
    try:
        easting, northing = float(parts[1]), float(parts[2])
    except (IndexError, ValueError) as error:
        raise DatasetError(
            f"{path}: file name has no '@easting@northing@' UTM coordinates"
        ) from error
    # float() reads 'nan' and 'inf'; left in, the distance search fails without a name.
    for axis, text, value in (("easting", parts[1], easting), ("northing", parts[2], northing)):
        if not np.isfinite(value):
            raise DatasetError(
                f"{path}: UTM {axis} {text!r} in the file name is not a finite number"
            )
    return easting, northing


def utm_ground_truth(reference: list[Path], query: list[Path], radius: float) -> list[np.ndarray]:
    """References within ``radius`` metres (Euclidean in UTM) of each query."""
    from scipy.spatial import cKDTree

    ref_xy = np.array([utm_from_name(p) for p in reference], dtype=np.float64)
    query_xy = np.array([utm_from_name(p) for p in query], dtype=np.float64)
    tree = cKDTree(ref_xy)
    return [
        np.array(sorted(hits), dtype=np.int64) for hits in tree.query_ball_point(query_xy, radius)
    ]


EARTH_RADIUS_M = 6_371_008.8  # mean Earth radius (IUGG), for great-circle distances


def haversine_m(lat1, lon1, lat2, lon2) -> np.ndarray:
    """Great-circle distance in metres between points given in degrees (broadcast)."""
    phi1, phi2 = np.radians(lat1), np.radians(lat2)
    dphi, dlam = phi2 - phi1, np.radians(np.asarray(lon2) - np.asarray(lon1))
    a = np.sin(dphi / 2) ** 2 + np.cos(phi1) * np.cos(phi2) * np.sin(dlam / 2) ** 2
    return 2 * EARTH_RADIUS_M * np.arcsin(np.sqrt(np.clip(a, 0.0, 1.0)))


def heading_difference(a, b) -> np.ndarray:
    """Smallest angle in degrees between headings ``a`` and ``b`` (broadcast), 0..180."""
    return np.abs((np.asarray(b) - np.asarray(a) + 180.0) % 360.0 - 180.0)


@dataclass(frozen=True)
class Positions:
    """Per image ``[n]`` float64: ``x, y`` (lat/lon in degrees when ``geographic``,
    else easting/northing in metres) and ``heading`` (degrees, or None)."""

    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray | None
    geographic: bool


def read_positions(csv_path: Path, names: list[str]) -> Positions:
    """Positions of ``names`` (image paths relative to the dataset folder) from a CSV
    with an ``image`` column and ``lat``/``lon`` or ``easting``/``northing`` columns
    (and optionally ``heading``). Errors name the file and the line at fault."""
    import codecs
    import csv
    import io

    if not csv_path.is_file():
        raise DatasetError(f"coordinates file {csv_path} does not exist")
    data = csv_path.read_bytes()
    try:
        # utf-8-sig: spreadsheet programs write a byte-order mark, which would otherwise
        # stick to the first column's name ('\ufeffimage') and hide it.
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        start = error.start + (len(codecs.BOM_UTF8) if data.startswith(codecs.BOM_UTF8) else 0)
        line = data.count(b"\n", 0, start) + 1
        raise DatasetError(
            f"{csv_path} line {line}: not UTF-8 text (byte "
            f"{data[start]:#04x} at offset {start}); save the file as UTF-8"
        ) from None
    header = text.partition("\n")[0].rstrip("\r")
    found = [name for sep, name in ((";", "';'"), ("\t", "tabs")) if sep in header]
    if "," not in header and found:
        # Read as CSV such a header is one column, reported as missing without a reason.
        raise DatasetError(
            f"{csv_path}: the header {header!r} separates columns with {' and '.join(found)}; "
            "the file must be comma-separated"
        )
    with io.StringIO(text, newline="") as f:
        reader = csv.DictReader(f)
        columns = reader.fieldnames or []
        # DictReader keeps the last of two equal names: the other column would be ignored.
        repeated = sorted({c for c in columns if c and columns.count(c) > 1})
        if repeated:
            raise DatasetError(
                f"{csv_path}: column(s) {repeated} appear more than once in the header "
                f"{columns}; each column name must be unique"
            )
        if {"lat", "lon"} <= set(columns):
            keys, geographic = ("lat", "lon"), True
        elif {"easting", "northing"} <= set(columns):
            keys, geographic = ("easting", "northing"), False
        else:
            keys, geographic = (), False
        if "image" not in columns or not keys:
            raise DatasetError(
                f"{csv_path}: needs an 'image' column and 'lat'/'lon' or "
                f"'easting'/'northing' columns; found {columns}"
            )
        with_heading = "heading" in columns
        rows: dict[str, tuple[int, tuple[float, ...]]] = {}
        for line, row in enumerate(reader, start=2):
            image = (row.get("image") or "").strip()
            if image in rows:
                raise DatasetError(
                    f"{csv_path} line {line}: image {image!r} is listed again "
                    f"(first on line {rows[image][0]})"
                )
            wanted = (*keys, "heading") if with_heading else keys
            try:
                values = tuple(float(row[k]) for k in wanted)
            except (TypeError, ValueError):
                bad = {k: row.get(k) for k in wanted}
                raise DatasetError(
                    f"{csv_path} line {line}: non-numeric coordinates for {image!r}: {bad}"
                ) from None
            if not np.all(np.isfinite(values)):
                raise DatasetError(f"{csv_path} line {line}: coordinates of {image!r} not finite")
            if geographic and not (-90 <= values[0] <= 90 and -180 <= values[1] <= 180):
                raise DatasetError(
                    f"{csv_path} line {line}: lat {values[0]} / lon {values[1]} of {image!r} "
                    "are outside -90..90 / -180..180"
                )
            rows[image] = (line, values)
    unknown = [(line, image) for image, (line, _) in rows.items() if image not in set(names)]
    if unknown:
        listing = ", ".join(f"line {line}: {image!r}" for line, image in unknown[:5])
        raise DatasetError(
            f"{csv_path}: {len(unknown)} row(s) name images that are not in the dataset "
            f"({listing}); names are paths relative to the dataset folder, e.g. {names[0]!r}"
        )
    missing = [name for name in names if name not in rows]
    if missing:
        raise DatasetError(
            f"{csv_path}: {len(missing)} image(s) of the dataset have no row, "
            f"e.g. {', '.join(missing[:5])}{folder_counts(missing, names)}"
        )
    table = np.array([rows[name][1] for name in names], dtype=np.float64)
    heading = table[:, 2] if with_heading else None
    return Positions(table[:, 0], table[:, 1], heading, geographic)


def exif_lat_lon(path: Path) -> tuple[float, float]:
    """Latitude and longitude in degrees from an image's EXIF GPS tags."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            gps = image.getexif().get_ifd(0x8825)
    except OSError as error:
        raise DatasetError(f"{path}: cannot read EXIF: {error}") from error

    def degrees(value, ref, negative: str) -> float:
        d, m, s = (float(v) for v in value)
        return (-1 if str(ref).upper() == negative else 1) * (d + m / 60 + s / 3600)

    try:
        return degrees(gps[2], gps[1], "S"), degrees(gps[4], gps[3], "W")
    except (KeyError, TypeError, ValueError, ZeroDivisionError):
        raise DatasetError(f"{path}: no EXIF GPS latitude/longitude") from None


def coordinates_ground_truth(
    reference: Positions, query: Positions, radius_m: float, max_heading_diff: float | None
) -> list[np.ndarray]:
    """References within ``radius_m`` metres of each query (great-circle for lat/lon,
    Euclidean for easting/northing) and, when ``max_heading_diff`` is set, within that
    many degrees of its heading."""
    truth = []
    block = 1024  # queries per distance block: memory ~ block x n_ref float64
    for start in range(0, len(query.x), block):
        rows = slice(start, start + block)
        if query.geographic:
            distance = haversine_m(
                query.x[rows, None], query.y[rows, None], reference.x[None], reference.y[None]
            )
        else:
            distance = np.hypot(
                query.x[rows, None] - reference.x[None], query.y[rows, None] - reference.y[None]
            )
        close = distance <= radius_m
        if max_heading_diff is not None:
            close &= (
                heading_difference(query.heading[rows, None], reference.heading[None])
                <= max_heading_diff
            )
        truth += [np.flatnonzero(row).astype(np.int64) for row in close]
    return truth


def _positions(files: DatasetFiles, spec: dict, folder: Path) -> tuple[Positions, Positions]:
    """Reference and query positions of a ``coordinates`` ground truth."""
    if spec["source"] == "exif":
        parts = []
        for paths in (files.reference, files.query):
            table = np.array([exif_lat_lon(p) for p in paths], dtype=np.float64)
            parts.append(Positions(table[:, 0], table[:, 1], None, True))
        return parts[0], parts[1]
    names = [p.relative_to(folder).as_posix() for p in files.reference + files.query]
    both = read_positions(folder / spec["file"], names)
    if spec.get("max_heading_diff") is not None and both.heading is None:
        raise DatasetError(
            f"{folder / spec['file']}: ground_truth.max_heading_diff is set but the file "
            "has no 'heading' column"
        )
    n = len(files.reference)

    def part(rows: slice) -> Positions:
        heading = None if both.heading is None else both.heading[rows]
        return Positions(both.x[rows], both.y[rows], heading, both.geographic)

    return part(slice(0, n)), part(slice(n, None))


def ground_truth(files: DatasetFiles, spec: dict, folder: Path) -> list[np.ndarray]:
    """Dispatch on ``spec['kind']``; see the module docstring for the kinds."""
    n_query, n_ref = len(files.query), len(files.reference)
    kind = spec["kind"]
    if kind == "none":
        return [np.zeros(0, dtype=np.int64) for _ in range(n_query)]
    if kind == "vprbench":
        truth = vprbench_ground_truth(
            folder / spec["file"],
            n_query,
            n_ref,
            spec["drop_out_of_range"],
            query_folders=_role_folders(files.query, folder),
            reference_folders=_role_folders(files.reference, folder),
        )
    elif kind == "frame_window":
        truth = frame_window_ground_truth(n_query, n_ref, int(spec["radius"]))
    elif kind == "utm":
        truth = utm_ground_truth(files.reference, files.query, float(spec["radius"]))
    elif kind == "pairs":
        truth = pairs_ground_truth(
            n_query,
            n_ref,
            query_folders=_role_folders(files.query, folder),
            reference_folders=_role_folders(files.reference, folder),
        )
    elif kind == "coordinates":
        reference, query = _positions(files, spec, folder)
        truth = coordinates_ground_truth(
            reference, query, float(spec["radius_m"]), spec.get("max_heading_diff")
        )
    else:
        raise DatasetError(f"unknown ground-truth kind {kind!r}")
    if not any(len(t) for t in truth):
        source = folder / spec["file"] if spec.get("file") else f"{folder} ({kind})"
        raise DatasetError(
            f"ground truth {ground_truth_rule(spec)} from {source}: no query has a positive "
            f"among the {n_ref} references, so recall is undefined; check the file or rule "
            "(or use ground_truth: {kind: none} to rank without recall)"
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
        return f"utm:{spec['radius']}m"
    if kind == "coordinates":
        source = "exif" if spec["source"] == "exif" else spec["file"]
        rule = f"coordinates:{source}:{spec['radius_m']}m"
        if spec.get("max_heading_diff") is not None:
            rule += f",heading<={spec['max_heading_diff']}deg"
        return rule
    return kind


def ground_truth_files(data_root: str | Path, spec: dict) -> list[Path]:
    """Files the ground truth is read from (inputs of the dataset stage)."""
    truth = spec["ground_truth"]
    if truth["kind"] == "vprbench" or (
        truth["kind"] == "coordinates" and truth["source"] == "file"
    ):
        return [dataset_folder(data_root, spec) / truth["file"]]
    return []

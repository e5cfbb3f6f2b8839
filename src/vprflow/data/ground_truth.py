"""Ground truth: per query, the reference indices that count as correct (docs/methods.md §9).

One table, :data:`KINDS`, holds every ``ground_truth.kind``: how its truth is computed,
its name in results tables and the files it reads. The kinds:

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
- ``positions``: references within ``radius`` of each query (Euclidean, in the
  positions' units), positions per role from a folder of Baidu Mall ``.camera`` files or
  an array file in the authors' image order (InsideOut's pickles);
- ``matches_csv``: a table of ranked matches, row ``i`` query ``i``'s positives in
  its ``top_<k>_ref_ind`` columns (AnyLoc's Nardo-Air ``gt_matches.csv``);
- ``msls``: the published MSLS validation lists of one ``city``;
- ``none``: no ground truth; the workflow ranks and draws, but computes no recall.

Positions and distances (``utm``, ``coordinates``) are :mod:`vprflow.data.positions`; the
papers' own files (``positions``, ``msls``, the safe unpickler) :mod:`vprflow.data.published_truth`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vprflow.core.errors import DatasetError, short_repr
from vprflow.core.paths import dataset_folder
from vprflow.data.datasets import DatasetFiles, role_folders
from vprflow.data.positions import (
    Positions,
    check_one_system,
    coordinates_ground_truth,
    exif_lat_lon,
    read_positions,
    utm_ground_truth,
)
from vprflow.data.published_truth import (
    MSLS_FILES,
    as_index,
    camera_centres,
    in_published_order,
    load_object_npy,
    matches_csv_ground_truth,
    msls_ground_truth,
    radius_ground_truth,
    read_position_array,
    reference_indices,
)

log = logging.getLogger("vprflow")

# ---------------------------------------------------------------- settings as applied


def whole_number(entry: dict, key: str, unit: str = "") -> int | list[int]:
    """``entry[key]`` (``ground_truth.<key>``) as the whole number (or list of whole
    numbers) it is applied as: an integral float such as ``2.0`` is read as 2, a
    fractional one (``0.9`` frames, rows ``[0, 100.5]``) or a boolean is refused,
    naming the key and the value; ``int()`` would have truncated it silently."""
    value = entry[key]
    items = value if isinstance(value, (list, tuple)) else [value]
    whole = []
    for item in items:
        number = None
        if isinstance(item, (int, np.integer)) and not isinstance(item, (bool, np.bool_)):
            number = int(item)
        elif isinstance(item, (float, np.floating)) and float(item).is_integer():
            number = int(item)
        if number is None:
            raise DatasetError(
                f"ground_truth.{key}: {item!r} is not a whole number{unit}; "
                f"kind {entry['kind']} applies it as an integer and will not round it"
            )
        whole.append(number)
    return whole if isinstance(value, (list, tuple)) else whole[0]


def _optional_whole(entry: dict, key: str) -> int | list[int] | None:
    return None if entry.get(key) is None else whole_number(entry, key)


# The settings each kind applies as whole numbers (what the number counts, for errors).
WHOLE_NUMBERS: dict[str, dict[str, str]] = {
    "frame_window": {"radius": " of frames"},
    "vprbench": {"rows": " (a row of the file)"},
    "positions": {
        "reference_rows": " (a row of the file)",
        "query_rows": " (a row of the file)",
        "dims": " of columns",
    },
}


def check_settings(entry: dict) -> None:
    """Refuse a setting of ``entry`` (a dataset's ``ground_truth``) that its kind cannot
    apply as given: a fractional count (:data:`WHOLE_NUMBERS`), or a heading limit on
    EXIF positions, which carry no heading. Run before the truth is computed and before
    its rule is named, so a table never states a setting that was not applied."""
    for key, unit in WHOLE_NUMBERS.get(entry["kind"], {}).items():
        if entry.get(key) is not None:
            whole_number(entry, key, unit)
    if (
        entry["kind"] == "coordinates"
        and entry.get("source") == "exif"
        and entry.get("max_heading_diff") is not None
    ):
        raise DatasetError(
            f"ground_truth.max_heading_diff: {entry['max_heading_diff']!r} is set but "
            "source: exif reads no heading; give the headings in a coordinates file "
            "(source: file, a 'heading' column) or drop the key"
        )


def _frame_radius(entry: dict) -> int:
    """The frame window's radius as applied: a whole number of frames."""
    return whole_number(entry, "radius", " of frames")


def _number_text(value) -> str:
    """A number as a rule states it: ``25``, ``7.5``."""
    value = float(value)
    return str(int(value)) if value.is_integer() else repr(value)


# ---------------------------------------------------------------- VPR-Bench files


def vprbench_ground_truth(
    path: str | Path,
    n_query: int,
    n_ref: int,
    drop_out_of_range: bool = False,
    *,
    rows: list[int] | None = None,
    query_index: str = "column",
    query_folders: str = "",
    reference_folders: str = "",
) -> list[np.ndarray]:
    """Per-query reference indices from a VPR-Bench ``ground_truth_new.npy``.

    ``rows = [start, stop]`` keeps those rows of the file (AnyLoc's Mid-Atlantic Ridge
    uses rows 101 on); ``query_index="position"`` makes row ``i`` the positives of
    query ``i`` whatever its first field says (AnyLoc's and Revisit-Anything's readers
    of such files), ``"column"`` reads the query from the first field (VPR-Bench).

    Rows are ``[query_index, [ref indices]]``: integers or integral floats, positives
    a list, tuple, 1-D array or single index; anything else (fractions, booleans,
    strings, nested lists) is an error naming the row. The number of rows must equal
    the number of query images. Reference indices beyond the reference set are an
    error unless ``drop_out_of_range`` (the published 17places file lists references
    406 and 407 of a 406-image set). ``query_folders`` and ``reference_folders``
    (:func:`vprflow.data.datasets.role_folders`) follow the image counts in errors.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"ground-truth file {path} does not exist")
    table = load_object_npy(path)
    if table.ndim != 2 or table.shape[1] != 2:
        raise DatasetError(
            f"{path}: expected rows of [query_index, [ref indices]], got {table.shape}"
        )
    if rows is not None:
        if not rows[0] < rows[1] <= len(table):
            raise DatasetError(f"{path}: rows {rows} asked of a file of {len(table)} rows")
        table = table[rows[0] : rows[1]]
    if len(table) != n_query:
        raise DatasetError(
            f"{path} has {len(table)} ground-truth rows but the dataset has {n_query} query "
            f"images{query_folders}"
        )
    if query_index == "position":
        query_indices = list(range(len(table)))
    else:
        query_indices = [
            as_index(q, f"{path} row {row}: query index") for row, q in enumerate(table[:, 0])
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
    positives = [
        reference_indices(refs, f"{path} row {row}:") for row, refs in enumerate(table[:, 1])
    ]
    # A file made for a sequence that ran on past the reference set (17places lists 406
    # and 407 of 406) overshoots the end by less than one list of positives: only such
    # indices are droppable. Checked as Python ints: 1e30 would overflow int64.
    reach = n_ref + max((len(p) for p in positives), default=0)
    truth: list[np.ndarray] = [np.zeros(0, dtype=np.int64)] * n_query
    dropped = []
    for row, (q, indices) in enumerate(zip(query_indices, positives, strict=True)):
        negative = [r for r in indices if r < 0]
        if negative:
            raise DatasetError(
                f"{path} row {row}: query {q} lists negative reference indices "
                f"{short_repr(negative)}; indices count from 0 (drop_out_of_range drops "
                "only indices past the last reference)"
            )
        past = [r for r in indices if r >= n_ref]
        far = [r for r in past if r >= reach]
        if far:
            raise DatasetError(
                f"{path} row {row}: query {q} lists reference indices {short_repr(far)}, "
                f"beyond the {n_ref} reference images{reference_folders} by more than the "
                f"file's longest list of positives ({reach - n_ref}); drop_out_of_range "
                "drops only indices just past the last reference (a sequence that ran on), "
                "not these: the file does not belong to this reference set"
            )
        if past and not drop_out_of_range:
            raise DatasetError(
                f"{path} row {row}: query {q} lists reference indices {short_repr(past)} but "
                f"the dataset has {n_ref} reference images{reference_folders} (set "
                "ground_truth.drop_out_of_range: true to drop them)"
            )
        dropped += [(row, r) for r in past]
        truth[q] = np.unique(np.array([r for r in indices if r < n_ref], dtype=np.int64))
    if dropped:
        listing = ", ".join(f"row {row}: {r}" for row, r in dropped[:10])
        log.warning(
            "%s: drop_out_of_range dropped %d reference index(es) past the last of the %d "
            "references (%s%s)",
            path,
            len(dropped),
            n_ref,
            listing,
            ", ..." if len(dropped) > 10 else "",
        )
    return truth


# ---------------------------------------------------------------- rules over indices


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
    ``reference_folders`` (:func:`vprflow.data.datasets.role_folders`) follow the image
    counts in errors."""
    if n_query != n_ref:
        raise DatasetError(
            "pairs ground truth needs as many queries as references, but the dataset has "
            f"{n_query} query images{query_folders} and {n_ref} reference "
            f"images{reference_folders}"
        )
    return [np.array([i], dtype=np.int64) for i in range(n_query)]


# ---------------------------------------------------------------- the kinds


def _none_truth(files: DatasetFiles, entry: dict, folder: Path) -> list[np.ndarray]:
    return [np.zeros(0, dtype=np.int64) for _ in range(len(files.query))]


def _vprbench_truth(files: DatasetFiles, entry: dict, folder: Path) -> list[np.ndarray]:
    return vprbench_ground_truth(
        folder / entry["file"],
        len(files.query),
        len(files.reference),
        entry["drop_out_of_range"],
        rows=_optional_whole(entry, "rows"),
        query_index=entry["query_index"],
        query_folders=role_folders(files.query, folder),
        reference_folders=role_folders(files.reference, folder),
    )


def _frame_window_truth(files: DatasetFiles, entry: dict, folder: Path) -> list[np.ndarray]:
    return frame_window_ground_truth(len(files.query), len(files.reference), _frame_radius(entry))


def _utm_truth(files: DatasetFiles, entry: dict, folder: Path) -> list[np.ndarray]:
    return utm_ground_truth(files.reference, files.query, float(entry["radius"]))


def _pairs_truth(files: DatasetFiles, entry: dict, folder: Path) -> list[np.ndarray]:
    return pairs_ground_truth(
        len(files.query),
        len(files.reference),
        query_folders=role_folders(files.query, folder),
        reference_folders=role_folders(files.reference, folder),
    )


def _positions(files: DatasetFiles, entry: dict, folder: Path) -> tuple[Positions, Positions]:
    """Reference and query positions of a ``coordinates`` ground truth."""
    if entry["source"] == "exif":
        paths = files.reference + files.query
        table = np.array([exif_lat_lon(p) for p in paths], dtype=np.float64).reshape(-1, 2)
        labels = [p.relative_to(folder).as_posix() for p in paths]
        check_one_system(table[:, 0], table[:, 1], True, labels, f"{folder}: EXIF GPS")
        n = len(files.reference)
        return (
            Positions(table[:n, 0], table[:n, 1], None, True),
            Positions(table[n:, 0], table[n:, 1], None, True),
        )
    names = [p.relative_to(folder).as_posix() for p in files.reference + files.query]
    both = read_positions(folder / entry["file"], names)
    if entry.get("max_heading_diff") is not None and both.heading is None:
        raise DatasetError(
            f"{folder / entry['file']}: ground_truth.max_heading_diff is set but the file "
            "has no 'heading' column"
        )
    n = len(files.reference)

    def part(rows: slice) -> Positions:
        heading = None if both.heading is None else both.heading[rows]
        return Positions(both.x[rows], both.y[rows], heading, both.geographic)

    return part(slice(0, n)), part(slice(n, None))


def _coordinates_truth(files: DatasetFiles, entry: dict, folder: Path) -> list[np.ndarray]:
    reference, query = _positions(files, entry, folder)
    return coordinates_ground_truth(
        reference, query, float(entry["radius_m"]), entry.get("max_heading_diff")
    )


def _coordinates_rule(entry: dict) -> str:
    source = "exif" if entry["source"] == "exif" else entry["file"]
    rule = f"coordinates:{source}:{_number_text(entry['radius_m'])}m"
    if entry.get("max_heading_diff") is not None:
        rule += f",heading<={_number_text(entry['max_heading_diff'])}deg"
    return rule


def _role_positions(files: DatasetFiles, entry: dict, folder: Path, role: str) -> np.ndarray:
    """A role's positions: a folder of Baidu Mall ``.camera`` files (matched by name) or
    an array file in the authors' image order."""
    key = f"{role}_positions"
    path = folder / entry[key]
    images = files.reference if role == "reference" else files.query
    if path.is_dir():
        return camera_centres(path, images, f"ground_truth.{key}")
    table = read_position_array(
        path,
        len(images),
        f"ground_truth.{key}",
        rows=_optional_whole(entry, f"{role}_rows"),
        dims=_optional_whole(entry, "dims"),
    )
    return in_published_order(table, images)


def _positions_truth(files: DatasetFiles, entry: dict, folder: Path) -> list[np.ndarray]:
    reference = _role_positions(files, entry, folder, "reference")
    query = _role_positions(files, entry, folder, "query")
    if reference.shape[1] != query.shape[1]:
        raise DatasetError(
            f"ground_truth: reference positions have {reference.shape[1]} coordinates and "
            f"query positions {query.shape[1]}"
        )
    return radius_ground_truth(reference, query, float(entry["radius"]))


def _matches_csv_truth(files: DatasetFiles, entry: dict, folder: Path) -> list[np.ndarray]:
    return matches_csv_ground_truth(folder / entry["file"], len(files.query), len(files.reference))


def _msls_truth(files: DatasetFiles, entry: dict, folder: Path) -> list[np.ndarray]:
    return msls_ground_truth(folder, entry["city"], files.reference, files.query)


def _no_files(entry: dict) -> list[str]:
    return []


@dataclass(frozen=True)
class Kind:
    """One ground-truth kind.

    ``truth(files, entry, folder)``: per query, the sorted int64 indices of its correct
    references (``entry`` the dataset's ``ground_truth``, ``folder`` the dataset folder);
    ``rule(entry)``: the short name of the rule in results tables (the ``ground_truth``
    column); ``files(entry)``: the files it reads, relative to the dataset folder (inputs
    of the dataset stage, hashed into its key); ``judged``: whether it says which
    references are correct at all (``none`` does not: its empty lists are no error);
    ``description``: what it means, in the config's words (the schema's ``kind``
    description lists every kind's, so a new kind is described there).
    """

    truth: Callable[[DatasetFiles, dict, Path], list[np.ndarray]]
    rule: Callable[[dict], str]
    files: Callable[[dict], list[str]] = _no_files
    judged: bool = True
    description: str = field(kw_only=True)


# In the order of the schema's enum (``ground_truth.kind``), which a test compares.
KINDS: dict[str, Kind] = {
    "vprbench": Kind(
        _vprbench_truth,
        lambda entry: f"vprbench:{entry['file']}",
        lambda entry: [entry["file"]],
        description="VPR-Bench .npy (query, positives) rows",
    ),
    "frame_window": Kind(
        _frame_window_truth,
        lambda entry: f"frame_window:+-{_frame_radius(entry)}",
        description="paired sequences, positives within `radius` frames",
    ),
    "utm": Kind(
        _utm_truth,
        lambda entry: f"utm:{_number_text(entry['radius'])}m",
        description="positives within `radius` metres of `@easting@northing@` file names",
    ),
    "pairs": Kind(_pairs_truth, lambda entry: "pairs", description="query i matches reference i"),
    "coordinates": Kind(
        _coordinates_truth,
        _coordinates_rule,
        lambda entry: [entry["file"]] if entry["source"] == "file" else [],
        description="positives within `radius_m` metres, positions from a CSV `file` or EXIF GPS",
    ),
    "positions": Kind(
        _positions_truth,
        lambda entry: f"positions:{entry['reference_positions']}:{_number_text(entry['radius'])}",
        lambda entry: [entry["reference_positions"], entry["query_positions"]],
        description="positives within `radius` of per-image positions (Baidu Mall camera "
        "files, InsideOut position pickles)",
    ),
    "matches_csv": Kind(
        _matches_csv_truth,
        lambda entry: f"matches_csv:{entry['file']}",
        lambda entry: [entry["file"]],
        description="row i of a CSV `file` lists query i's positives in its "
        "top_<k>_ref_ind columns (AnyLoc's Nardo-Air)",
    ),
    "msls": Kind(
        _msls_truth,
        lambda entry: f"msls:{entry['city']}",
        lambda entry: list(MSLS_FILES.values()),
        description="the published MSLS validation lists of one `city`",
    ),
    "none": Kind(
        _none_truth,
        lambda entry: "none",
        judged=False,
        description="no ground truth (predictions and figures, no recall)",
    ),
}


def _kind(entry: dict) -> Kind:
    kind = entry["kind"]
    if kind not in KINDS:
        raise DatasetError(f"unknown ground-truth kind {kind!r}")
    return KINDS[kind]


def ground_truth(files: DatasetFiles, entry: dict, folder: Path) -> list[np.ndarray]:
    """Per query, the correct reference indices under ``entry`` (the dataset's
    ``ground_truth``; see :data:`KINDS`). A truth in which no query has a positive is an
    error (recall would be undefined), except for ``none``."""
    kind = _kind(entry)
    check_settings(entry)
    truth = kind.truth(files, entry, folder)
    if kind.judged and not any(len(t) for t in truth):
        source = folder / entry["file"] if entry.get("file") else f"{folder} ({entry['kind']})"
        raise DatasetError(
            f"ground truth {ground_truth_rule(entry)} from {source}: no query has a positive "
            f"among the {len(files.reference)} references, so recall is undefined; check the "
            "file or rule (or use ground_truth: {kind: none} to rank without recall)"
        )
    return truth


def ground_truth_rule(entry: dict) -> str:
    """A short human-readable name of the rule, for results tables: the settings as
    applied (:func:`check_settings` refuses one that cannot be)."""
    kind = _kind(entry)
    check_settings(entry)
    return kind.rule(entry)


def ground_truth_files(data_root: str | Path, entry: dict) -> list[Path]:
    """Files the ground truth of dataset ``entry`` is read from (inputs of the dataset
    stage)."""
    truth = entry["ground_truth"]
    check_settings(truth)  # at planning: a setting that cannot apply stops the run here
    return [dataset_folder(data_root, entry) / name for name in _kind(truth).files(truth)]

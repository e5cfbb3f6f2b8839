"""Where images were taken, and which references lie near each query (docs/methods.md §9).

Positions come from a coordinates CSV (``lat``/``lon`` in degrees, or
``easting``/``northing`` in metres, optionally ``heading``), from each image's EXIF GPS
tags, or from ``@easting@northing@`` in the file names (UTM: Pitts30k, SF-XL, MSLS). A
reference within a radius of a query (great-circle distance for lat/lon, Euclidean for
easting/northing and UTM; optionally within a heading difference) is a positive of the
``coordinates`` and ``utm`` ground-truth kinds (:mod:`vprflow.data.ground_truth`).
"""

from __future__ import annotations

import codecs
import csv
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from vprflow.core.errors import DatasetError
from vprflow.core.lazy import lazy_import
from vprflow.data.datasets import by_composed_name, folder_counts, nfc

spatial = lazy_import("scipy.spatial")


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
    ref_xy = np.array([utm_from_name(p) for p in reference], dtype=np.float64)
    query_xy = np.array([utm_from_name(p) for p in query], dtype=np.float64)
    both = np.concatenate([ref_xy, query_xy]).reshape(-1, 2)
    check_one_system(
        both[:, 0],
        both[:, 1],
        False,
        [p.name for p in (*reference, *query)],
        "UTM file names ('@easting@northing@')",
        ("easting", "northing"),
    )
    tree = spatial.cKDTree(ref_xy)
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


def swapped_rows(x: np.ndarray, y: np.ndarray, geographic: bool) -> np.ndarray:
    """Indices of the rows of one file whose two coordinates look swapped (lat/lon, or
    easting/northing): as given, a row lies farther from the median position of the
    file than twice the farthest of the rows that are not suspect (whose swap would
    take them farther away), and swapped back it lies nearer than that. ``x, y [n]``
    float64: lat/lon in degrees when ``geographic`` (great-circle distances; a swap that
    gives a latitude beyond +-90 is impossible), else metres (Euclidean).

    The rule reads only the file's own spread, so it needs no threshold in metres or
    degrees; it relies on fewer than half of the rows being swapped (the coordinate-wise
    median stays among the true positions) and on the places lying clear of their own
    mirror image (``lat = lon``): where they straddle it a swap is indistinguishable
    from a position and nothing is flagged."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if len(x) < 3:
        return np.zeros(0, dtype=np.int64)
    cx, cy = float(np.median(x)), float(np.median(y))

    def distance(a, b):
        return haversine_m(a, b, cx, cy) if geographic else np.hypot(a - cx, b - cy)

    as_given = distance(x, y)
    swapped = np.full(len(x), np.inf)
    possible = np.abs(y) <= 90 if geographic else np.ones(len(x), dtype=bool)
    swapped[possible] = distance(y[possible], x[possible])
    suspect = swapped < as_given
    if suspect.all():
        return np.zeros(0, dtype=np.int64)
    # Twice the spread: a margin on both sides, so a true position at the edge of the
    # others is found swapped, and a position just past their edge is no swap.
    bound = 2 * float(as_given[~suspect].max())
    return np.flatnonzero(suspect & (swapped <= bound) & (as_given > bound))


def check_one_system(
    x: np.ndarray,
    y: np.ndarray,
    geographic: bool,
    labels: list[str],
    where: str,
    axes: tuple[str, str] = ("lat", "lon"),
) -> None:
    """Refuse positions of one file (``labels[i]`` names row ``i``: a line and image, or
    an image) of which some have their two coordinates swapped (:func:`swapped_rows`):
    such a query gets no positive, or the wrong ones, and would leave the count without
    a word."""
    rows = swapped_rows(x, y, geographic)
    if not len(rows):
        return
    cx, cy = float(np.median(x)), float(np.median(y))

    def far(a, b) -> float:
        return float(haversine_m(a, b, cx, cy) if geographic else np.hypot(a - cx, b - cy))

    listing = "; ".join(
        f"{labels[i]} ({axes[0]} {x[i]:.6g}, {axes[1]} {y[i]:.6g}: {far(x[i], y[i]):.4g} "
        f"m from the median, {far(y[i], x[i]):.4g} m swapped)"
        for i in rows[:5]
    )
    raise DatasetError(
        f"{where}: {axes[0]} and {axes[1]} look swapped on {len(rows)} of {len(x)} rows "
        f"({listing}{'; ...' if len(rows) > 5 else ''}); the median of the file's positions "
        f"is {axes[0]} {cx:.6g}, {axes[1]} {cy:.6g}. One file holds one coordinate "
        f"system: give these rows' {axes[0]} and {axes[1]} in that order"
    )


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
        # By the composed (NFC) name: a name typed composed matches a file whose name
        # macOS wrote decomposed.
        rows: dict[str, tuple[int, tuple[float, ...]]] = {}
        typed: dict[str, str] = {}
        for line, row in enumerate(reader, start=2):
            image = (row.get("image") or "").strip()
            if nfc(image) in rows:
                first = typed[nfc(image)]
                form = "" if first == image else f", as {first!r}, in another Unicode form"
                raise DatasetError(
                    f"{csv_path} line {line}: image {image!r} is listed again "
                    f"(first on line {rows[nfc(image)][0]}{form})"
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
            rows[nfc(image)] = (line, values)
            typed[nfc(image)] = image
    composed = by_composed_name(names, str(csv_path))
    unknown = [(line, typed[key]) for key, (line, _) in rows.items() if key not in composed]
    if unknown:
        listing = ", ".join(f"line {line}: {image!r}" for line, image in unknown[:5])
        raise DatasetError(
            f"{csv_path}: {len(unknown)} row(s) name images that are not in the dataset "
            f"({listing}); names are paths relative to the dataset folder, e.g. {names[0]!r}"
        )
    missing = [name for name in names if nfc(name) not in rows]
    if missing:
        raise DatasetError(
            f"{csv_path}: {len(missing)} image(s) of the dataset have no row, "
            f"e.g. {', '.join(missing[:5])}{folder_counts(missing, names)}"
        )
    table = np.array([rows[nfc(name)][1] for name in names], dtype=np.float64)
    labels = [f"line {rows[nfc(name)][0]}: {name!r}" for name in names]
    check_one_system(table[:, 0], table[:, 1], geographic, labels, str(csv_path), keys)
    heading = table[:, 2] if with_heading else None
    return Positions(table[:, 0], table[:, 1], heading, geographic)


def exif_lat_lon(path: Path) -> tuple[float, float]:
    """Latitude and longitude in degrees from an image's EXIF GPS tags."""
    try:
        with Image.open(path) as image:
            gps = image.getexif().get_ifd(0x8825)
    except OSError as error:
        raise DatasetError(f"{path}: cannot read EXIF: {error}") from error

    def dms(value, ref) -> tuple[tuple[float, ...], str]:
        # Degrees, minutes, seconds, each non-negative: the sign is the reference letter.
        parts = tuple(float(v) for v in value)
        if len(parts) != 3:
            raise ValueError
        return parts, str(ref).strip().upper()

    try:
        lat, lat_ref = dms(gps[2], gps[1])
        lon, lon_ref = dms(gps[4], gps[3])
    except (KeyError, TypeError, ValueError, ZeroDivisionError):
        raise DatasetError(f"{path}: no EXIF GPS latitude/longitude") from None
    signed = []
    for axis, parts, ref, refs, limit in (
        ("latitude", lat, lat_ref, "NS", 90),
        ("longitude", lon, lon_ref, "EW", 180),
    ):
        # A rational 0/0 reads as NaN; NaN compares false, so it must be named here.
        if not all(np.isfinite(parts)) or any(v < 0 for v in parts):
            raise DatasetError(
                f"{path}: EXIF GPS {axis} {parts} (degrees, minutes, seconds) is not a "
                "finite non-negative number"
            )
        if ref not in tuple(refs):
            raise DatasetError(
                f"{path}: EXIF GPS {axis} reference {ref!r} is not one of {' or '.join(refs)}"
            )
        value = parts[0] + parts[1] / 60 + parts[2] / 3600
        if value > limit:
            raise DatasetError(
                f"{path}: EXIF GPS {axis} {value:.6g} degrees {ref} {parts} is beyond "
                f"{limit} degrees"
            )
        signed.append(-value if ref == refs[1] else value)
    return signed[0], signed[1]


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

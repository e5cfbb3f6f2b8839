"""Positions (vprflow.data.positions): distances against written-out formulas, coordinate
files and EXIF GPS tags read by name with errors naming the line, UTM file names, and
the radius rules against pairwise loops."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
from dataset_helpers import assert_truth_equal, utm_name
from PIL import Image
from PIL.TiffImagePlugin import IFDRational
from workflow_helpers import dataset_spec

from vprflow.core.errors import DatasetError
from vprflow.data.datasets import list_dataset
from vprflow.data.ground_truth import ground_truth, ground_truth_rule
from vprflow.data.positions import (
    EARTH_RADIUS_M,
    Positions,
    coordinates_ground_truth,
    exif_lat_lon,
    haversine_m,
    heading_difference,
    read_positions,
    swapped_rows,
    utm_from_name,
    utm_ground_truth,
)

METRES_PER_DEGREE = math.pi * EARTH_RADIUS_M / 180  # along a meridian: 111,195.08 m


# ------------------------------------------------------------------ distances


def test_haversine_at_known_distances():
    # A quarter meridian, a quarter equator, one degree of latitude, and antipodes.
    assert haversine_m(0, 0, 90, 0) == pytest.approx(math.pi / 2 * EARTH_RADIUS_M, rel=1e-12)
    assert haversine_m(0, 0, 0, 90) == pytest.approx(math.pi / 2 * EARTH_RADIUS_M, rel=1e-12)
    assert haversine_m(45, 7, 46, 7) == pytest.approx(METRES_PER_DEGREE, rel=1e-12)
    # Antipodes: arcsin near 1 amplifies rounding (the haversine form's weak spot, ~0.2 m
    # of 20,000 km); VPR distances are metres, where the form is exact to ~1e-9 m.
    assert haversine_m(10, 20, -10, -160) == pytest.approx(math.pi * EARTH_RADIUS_M, rel=1e-7)
    # 25 m north of Pittsburgh; one degree of longitude at 60 N is half of one at the
    # equator (the spherical law of cosines, small-angle limit).
    lat = 40.4406
    assert haversine_m(lat, -79.9959, lat + 25 / METRES_PER_DEGREE, -79.9959) == pytest.approx(
        25.0, abs=1e-6
    )
    tiny = 1e-4
    east = haversine_m(60, 0, 60, tiny) / haversine_m(0, 0, 0, tiny)
    assert east == pytest.approx(0.5, abs=1e-6)


def test_heading_difference_wraps_around():
    np.testing.assert_allclose(
        heading_difference([350, 10, 90, 0], [10, 350, 270, 180]), [20, 20, 180, 180]
    )


def direct_truth(ref: np.ndarray, query: np.ndarray, radius: float, distance) -> list[list[int]]:
    return [
        [r for r in range(len(ref)) if distance(query[q], ref[r]) <= radius]
        for q in range(len(query))
    ]


def test_lat_lon_ground_truth_equals_a_pairwise_loop():
    rng = np.random.default_rng(0)
    ref = np.c_[47.0 + rng.uniform(0, 0.001, 60), 8.0 + rng.uniform(0, 0.001, 60)]
    query = np.c_[47.0 + rng.uniform(0, 0.001, 20), 8.0 + rng.uniform(0, 0.001, 20)]
    truth = coordinates_ground_truth(
        Positions(ref[:, 0], ref[:, 1], None, True),
        Positions(query[:, 0], query[:, 1], None, True),
        25.0,
        None,
    )

    def great_circle(a, b):  # spherical law of haversines, written out
        p1, p2 = math.radians(a[0]), math.radians(b[0])
        h = (
            math.sin((p2 - p1) / 2) ** 2
            + math.cos(p1) * math.cos(p2) * math.sin(math.radians(b[1] - a[1]) / 2) ** 2
        )
        return 2 * EARTH_RADIUS_M * math.asin(math.sqrt(h))

    expected = direct_truth(ref, query, 25.0, great_circle)
    assert [t.tolist() for t in truth] == expected
    assert sum(map(len, expected)) > 20  # the radius matters: some in, some out
    assert any(len(t) < len(ref) for t in expected)


def test_easting_northing_and_heading_ground_truth():
    ref = np.array([[0.0, 0.0], [20.0, 0.0], [0.0, 30.0], [3.0, 4.0]])
    query = np.array([[0.0, 0.0]])
    heading_ref = np.array([0.0, 100.0, 350.0, 200.0])
    both = coordinates_ground_truth(
        Positions(ref[:, 0], ref[:, 1], heading_ref, False),
        Positions(query[:, 0], query[:, 1], np.array([10.0]), False),
        25.0,
        None,
    )
    assert both[0].tolist() == [0, 1, 3]  # 0, 20 and 5 m away; 30 m is out
    headed = coordinates_ground_truth(
        Positions(ref[:, 0], ref[:, 1], heading_ref, False),
        Positions(query[:, 0], query[:, 1], np.array([10.0]), False),
        25.0,
        40.0,
    )
    assert headed[0].tolist() == [0]  # 10 deg apart; 90 and 170 are too much


# ------------------------------------------------------------------ coordinate files


def write_coordinates(path: Path, rows: list[list], header=("image", "lat", "lon")) -> Path:
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)
    return path


NAMES = ["ref/a.jpg", "ref/b.jpg", "query/q.jpg"]


def test_positions_are_read_by_image_name_in_dataset_order(tmp_path):
    path = write_coordinates(
        tmp_path / "c.csv", [["query/q.jpg", 1, 2], ["ref/b.jpg", 3, 4], ["ref/a.jpg", 5, 6]]
    )
    positions = read_positions(path, NAMES)
    assert positions.geographic and positions.heading is None
    assert positions.x.tolist() == [5, 3, 1] and positions.y.tolist() == [6, 4, 2]


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        ([["ref/a.jpg", 1, 2], ["query/q.jpg", 1, 2]], r"1 image\(s\) .* no row, e.g. ref/b.jpg"),
        (
            [["ref/a.jpg", 1, 2], ["ref/b.jpg", 1, 2], ["query/q.jpg", 1, 2], ["ref/c.jpg", 1, 2]],
            r"line 5: 'ref/c.jpg'",
        ),
        (
            [["ref/a.jpg", 1, 2], ["ref/a.jpg", 1, 2]],
            r"line 3: image 'ref/a.jpg' is listed again \(first on line 2\)",
        ),
        ([["ref/a.jpg", "north", 2]], r"line 2: non-numeric coordinates for 'ref/a.jpg'"),
        ([["ref/a.jpg", 91, 2]], r"line 2: lat 91.0 / lon 2.0"),
    ],
)
def test_bad_coordinate_files_name_the_row(tmp_path, rows, message):
    path = write_coordinates(tmp_path / "c.csv", rows)
    with pytest.raises(DatasetError, match=message):
        read_positions(path, NAMES)


def test_images_without_a_row_in_a_subfolder_are_named_with_their_folder(tmp_path):
    # The recursive search found query/extra/, which the file does not cover.
    path = write_coordinates(
        tmp_path / "c.csv", [["ref/a.jpg", 1, 2], ["ref/b.jpg", 1, 2], ["query/q.jpg", 1, 2]]
    )
    names = [*NAMES, "query/extra/1.jpg", "query/extra/2.jpg"]
    with pytest.raises(DatasetError) as error:
        read_positions(path, names)
    assert str(error.value).endswith(
        "2 image(s) of the dataset have no row, e.g. query/extra/1.jpg, query/extra/2.jpg "
        "(query/extra/: 2; images in subfolders are found too unless the dataset sets "
        "recursive: false)"
    )


def test_a_coordinate_file_without_coordinate_columns_names_what_it_found(tmp_path):
    path = write_coordinates(tmp_path / "c.csv", [["ref/a.jpg", 1]], header=("image", "x"))
    with pytest.raises(DatasetError, match=r"'lat'/'lon' or 'easting'/'northing'.*'x'"):
        read_positions(path, NAMES)


def test_a_repeated_column_name_is_refused_naming_it(tmp_path):
    # Today the last 'lat' column silently wins, whichever one the user meant.
    path = write_coordinates(
        tmp_path / "c.csv",
        [["ref/a.jpg", 1, 2, 5], ["ref/b.jpg", 3, 4, 6], ["query/q.jpg", 1, 2, 7]],
        header=("image", "lat", "lon", "lat"),
    )
    with pytest.raises(DatasetError, match=r"c\.csv: column\(s\) \['lat'\] appear more than once"):
        read_positions(path, NAMES)


def test_a_utf8_byte_order_mark_is_read(tmp_path):
    # Spreadsheet programs write one; it used to hide the 'image' column.
    path = tmp_path / "c.csv"
    path.write_bytes(
        b"\xef\xbb\xbfimage,lat,lon\r\nref/a.jpg,1,2\r\nref/b.jpg,3,4\r\nquery/q.jpg,5,6\r\n"
    )
    positions = read_positions(path, NAMES)
    assert positions.x.tolist() == [1, 3, 5] and positions.y.tolist() == [2, 4, 6]


@pytest.mark.parametrize(("separator", "named"), [(";", "';'"), ("\t", "tabs")])
def test_a_semicolon_or_tab_separated_file_names_its_delimiter(tmp_path, separator, named):
    # Read as CSV its header is one column, which used to be reported only as missing.
    path = tmp_path / "c.csv"
    path.write_text(
        "\n".join(
            separator.join(row) for row in [["image", "lat", "lon"], ["ref/a.jpg", "1,5", "2"]]
        )
    )
    message = rf"c\.csv: the header .* separates columns with {named}; the file must be comma-"
    with pytest.raises(DatasetError, match=message):
        read_positions(path, NAMES)


def test_a_coordinate_file_that_is_not_utf8_names_the_line(tmp_path):
    path = tmp_path / "c.csv"
    path.write_bytes("image,lat,lon\nref/a.jpg,1,2\nref/caf\u00e9.jpg,3,4\n".encode("latin-1"))
    with pytest.raises(DatasetError, match=r"c\.csv line 3: not UTF-8 text \(byte 0xe9"):
        read_positions(path, NAMES)


# ------------------------------------------------------------------ EXIF GPS


def gps_jpeg(path: Path, lat: tuple, lat_ref: str, lon: tuple, lon_ref: str) -> Path:
    exif = Image.Exif()
    exif[0x8825] = {1: lat_ref, 2: lat, 3: lon_ref, 4: lon}
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(path, exif=exif)
    return path


def test_exif_gps_is_read_in_signed_degrees(tmp_path):
    path = gps_jpeg(tmp_path / "g.jpg", (40.0, 26.0, 46.5), "N", (79.0, 58.0, 56.0), "W")
    lat, lon = exif_lat_lon(path)
    assert lat == pytest.approx(40 + 26 / 60 + 46.5 / 3600, abs=1e-9)
    assert lon == pytest.approx(-(79 + 58 / 60 + 56 / 3600), abs=1e-9)
    plain = tmp_path / "plain.jpg"
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(plain)
    with pytest.raises(DatasetError, match="plain.jpg: no EXIF GPS"):
        exif_lat_lon(plain)


def test_exif_ground_truth_through_list_dataset(tmp_path):
    root = tmp_path / "walk"
    for role in ("ref", "query"):
        (root / role).mkdir(parents=True)
    step = 10 / METRES_PER_DEGREE  # 10 m between references, along a meridian
    for i in range(5):
        gps_jpeg(root / "ref" / f"{i}.jpg", (50.0, 0.0, i * step * 3600), "N", (4.0, 0, 0), "E")
    gps_jpeg(root / "query" / "0.jpg", (50.0, 0.0, 2.2 * step * 3600), "N", (4.0, 0, 0), "E")
    spec = dataset_spec(path="walk", reference="ref", query="query")
    files = list_dataset(tmp_path, "walk", spec)
    truth_spec = {"kind": "coordinates", "source": "exif", "radius_m": 15}
    truth = ground_truth(files, truth_spec, root)
    assert truth[0].tolist() == [1, 2, 3]  # 12, 2 and 8 m away; 22 m is out
    assert ground_truth_rule(truth_spec) == "coordinates:exif:15m"


# ------------------------------------------------------------------ UTM file names


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


# ------------------------------------------------------------------ one coordinate system


def street(n: int, seed: int, centre=(40.4406, -79.9959), spread_deg=0.004) -> np.ndarray:
    """``n`` lat/lon positions scattered over a few hundred metres around ``centre``."""
    rng = np.random.default_rng(seed)
    return np.asarray(centre) + rng.uniform(-spread_deg, spread_deg, (n, 2))


def test_a_coordinate_file_with_lat_and_lon_swapped_on_a_few_rows_is_refused_naming_them(
    tmp_path,
):
    # Swapped, (-79.99, 40.44) is still a valid lat/lon (in Antarctica): the range check
    # passed it and the query got no positive, leaving n_queries without a word.
    positions = street(30, 0)
    names = [f"ref/{i:02d}.jpg" for i in range(20)] + [f"query/{i:02d}.jpg" for i in range(10)]
    rows = [[name, lat, lon] for name, (lat, lon) in zip(names, positions, strict=True)]
    for i in (4, 23):
        rows[i][1], rows[i][2] = rows[i][2], rows[i][1]
    path = write_coordinates(tmp_path / "c.csv", rows)
    with pytest.raises(DatasetError) as error:
        read_positions(path, names)
    message = str(error.value)
    assert message.startswith(f"{path}: lat and lon look swapped on 2 of 30 rows")
    assert "line 6: 'ref/04.jpg' (lat -79.99" in message
    assert "line 25: 'query/03.jpg' (lat -79.99" in message
    assert "One file holds one coordinate system" in message


@pytest.mark.parametrize(
    "centre", [(40.4406, -79.9959), (45.0, 45.0), (-33.86, 151.21), (0.0, 0.0)]
)
def test_consistent_positions_are_never_taken_for_swapped_ones_wherever_they_lie(centre):
    # (45, 45) and (0, 0) straddle the lat = lon line, where a swap cannot be told from
    # a position: nothing is flagged there either.
    for seed in range(20):
        positions = street(50, seed, centre, spread_deg=0.01 * (1 + seed))
        assert swapped_rows(positions[:, 0], positions[:, 1], True).tolist() == []


def test_swapped_rows_are_found_by_the_files_own_spread_not_a_distance_in_metres():
    # The same file, a town or a city wide: the rule reads only the spread of its rows.
    for spread in (0.0005, 0.05, 0.5):
        positions = street(40, 1, spread_deg=spread)
        positions[[3, 17]] = positions[[3, 17], ::-1]
        assert swapped_rows(positions[:, 0], positions[:, 1], True).tolist() == [3, 17]


def test_an_easting_northing_file_with_swapped_rows_is_refused(tmp_path):
    rng = np.random.default_rng(2)
    xy = rng.uniform(0, 300, (12, 2)) + [585300.0, 4477300.0]
    names = [f"ref/{i}.jpg" for i in range(12)]
    rows = [[name, e, n] for name, (e, n) in zip(names, xy, strict=True)]
    rows[7][1], rows[7][2] = rows[7][2], rows[7][1]
    path = write_coordinates(tmp_path / "c.csv", rows, ("image", "easting", "northing"))
    with pytest.raises(DatasetError, match=r"easting and northing look swapped on 1 of 12 rows"):
        read_positions(path, names)


def test_utm_file_names_with_easting_and_northing_swapped_are_refused_naming_the_image(
    tmp_path,
):
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 100, (10, 2)) + [585300.0, 4477300.0]
    reference = [tmp_path / utm_name(e, n, f"r{i}") for i, (e, n) in enumerate(xy[:6])]
    query = [tmp_path / utm_name(e, n, f"q{i}") for i, (e, n) in enumerate(xy[6:])]
    query[1] = tmp_path / utm_name(xy[7, 1], xy[7, 0], "q1")
    with pytest.raises(DatasetError, match=rf"UTM file names .* 1 of 10 rows \({query[1].name}"):
        utm_ground_truth(reference, query, 25.0)


@pytest.mark.parametrize(
    ("lat", "lat_ref", "lon", "lon_ref", "message"),
    [
        ((IFDRational(0, 0), 0.0, 0.0), "N", (4.0, 0.0, 0.0), "E", r"latitude \(nan, 0.0, 0.0\)"),
        ((50.0, 0.0, 0.0), "N", (4.0, IFDRational(0, 0), 0.0), "E", r"longitude \(4.0, nan"),
        ((95.0, 0.0, 0.0), "N", (4.0, 0.0, 0.0), "E", r"latitude 95 degrees N .* beyond 90"),
        ((50.0, 0.0, 0.0), "S", (181.0, 0.0, 0.0), "W", r"longitude 181 degrees W .* beyond 180"),
        ((50.0, 0.0, 0.0), "E", (4.0, 0.0, 0.0), "N", r"latitude reference 'E' is not one of"),
    ],
)
def test_exif_gps_holding_nan_or_95_degrees_is_refused_naming_the_image_and_value(
    tmp_path, lat, lat_ref, lon, lon_ref, message
):
    # NaN compared false and 95 degrees was taken as given: the query got no positive.
    path = gps_jpeg(tmp_path / "g.jpg", lat, lat_ref, lon, lon_ref)
    with pytest.raises(DatasetError, match=rf"g.jpg: EXIF GPS {message}"):
        exif_lat_lon(path)


def test_exif_positions_of_one_image_swapped_are_refused_naming_the_image(tmp_path):
    root = tmp_path / "walk"
    for role in ("ref", "query"):
        (root / role).mkdir(parents=True)
    for i in range(5):
        gps_jpeg(root / "ref" / f"{i}.jpg", (50.0, 0.0, 2.0 * i), "N", (4.0, 0, 0), "E")
    gps_jpeg(root / "query" / "0.jpg", (4.0, 0.0, 0.0), "N", (50.0, 0.0, 1.0), "E")
    gps_jpeg(root / "query" / "1.jpg", (50.0, 0.0, 3.0), "N", (4.0, 0, 0), "E")
    files = list_dataset(
        tmp_path, "walk", dataset_spec(path="walk", reference="ref", query="query")
    )
    spec = {"kind": "coordinates", "source": "exif", "radius_m": 15}
    with pytest.raises(
        DatasetError,
        match=r"EXIF GPS: lat and lon look swapped on 1 of 7 rows \(query/0.jpg \(lat 4, lon 50",
    ):
        ground_truth(files, spec, root)


# ------------------------------------------------------------------ Unicode forms of names
# "Café" as macOS writes file names (decomposed, NFD: e + combining acute) and as one
# types it in a CSV (composed, NFC): the two print alike.
CAFE_NFD, CAFE_NFC = "Cafe\u0301", "Caf\u00e9"


def test_a_csv_typed_composed_matches_files_named_decomposed(tmp_path):
    root = tmp_path / "walk"
    for name in (f"ref/{CAFE_NFD}_0.jpg", f"ref/{CAFE_NFD}_1.jpg", f"query/{CAFE_NFD}.jpg"):
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(root / name)
    assert {p.name for p in (root / "ref").iterdir()} == {f"{CAFE_NFD}_0.jpg", f"{CAFE_NFD}_1.jpg"}
    write_coordinates(
        root / "gps.csv",
        [
            [f"ref/{CAFE_NFC}_0.jpg", 50.0, 4.0],
            [f"ref/{CAFE_NFC}_1.jpg", 50.001, 4.0],  # 111 m north
            [f"query/{CAFE_NFC}.jpg", 50.00001, 4.0],
        ],
    )
    files = list_dataset(
        tmp_path, "walk", dataset_spec(path="walk", reference="ref", query="query")
    )
    truth = ground_truth(
        files, {"kind": "coordinates", "source": "file", "file": "gps.csv", "radius_m": 25}, root
    )
    assert truth[0].tolist() == [0]
    # The files keep their own names for reading.
    assert files.query[0].name == f"{CAFE_NFD}.jpg" and files.query[0].is_file()


def test_a_name_twice_in_two_unicode_forms_is_named_as_such(tmp_path):
    path = write_coordinates(
        tmp_path / "c.csv", [[f"ref/{CAFE_NFC}.jpg", 1, 2], [f"ref/{CAFE_NFD}.jpg", 1, 2]]
    )
    with pytest.raises(DatasetError, match="listed again .*in another Unicode form"):
        read_positions(path, [f"ref/{CAFE_NFD}.jpg"])
    # Two files whose names differ only in their form: a typed name would match both.
    path = write_coordinates(tmp_path / "d.csv", [[f"ref/{CAFE_NFC}.jpg", 1, 2]])
    with pytest.raises(DatasetError, match="differ only in Unicode normalisation"):
        read_positions(path, [f"ref/{CAFE_NFC}.jpg", f"ref/{CAFE_NFD}.jpg"])

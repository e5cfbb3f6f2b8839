"""Dataset layouts (vprflow.data.datasets): folders in natural order, image lists, references
that are also queries, and paired layouts matched by name; errors name what is at fault."""

from __future__ import annotations

import re

import numpy as np
import pytest
from dataset_helpers import SPEC, touch_images
from PIL import Image
from workflow_helpers import dataset_spec

from vprflow.core.errors import DatasetError
from vprflow.data.datasets import list_dataset
from vprflow.data.images import ImageReadError, scan_images

# ------------------------------------------------------------------ folders


def test_list_dataset_natural_order(tmp_path):
    touch_images(tmp_path / "ds/ref", ["10.jpg", "2.jpg", "1.jpg", "notes.txt", "img10.PNG"])
    touch_images(tmp_path / "ds/query", ["frame_10.png", "frame_2.png", "frame_9.png"])
    files = list_dataset(tmp_path, "toy", SPEC)
    assert [p.name for p in files.reference] == ["1.jpg", "2.jpg", "10.jpg", "img10.PNG"]
    assert [p.name for p in files.query] == ["frame_2.png", "frame_9.png", "frame_10.png"]
    assert scan_images(tmp_path / "ds/query").paths == files.query


def test_list_dataset_missing_and_empty_folders(tmp_path):
    spec = dict(SPEC, source="https://example.org/toy")
    with pytest.raises(DatasetError, match=r"folder .*ds does not exist.*example\.org"):
        list_dataset(tmp_path, "toy", spec)
    touch_images(tmp_path / "ds/ref", ["1.jpg"])
    with pytest.raises(DatasetError, match=r"query folder .*query does not exist"):
        list_dataset(tmp_path, "toy", spec)
    touch_images(tmp_path / "ds/query", ["readme.txt"])
    with pytest.raises(DatasetError, match=r"query folder .*query contains no images"):
        list_dataset(tmp_path, "toy", spec)


def test_broken_link_or_folder_with_an_image_name_is_an_error_naming_it(tmp_path):
    # Skipping it would shift every later reference index against the ground truth.
    touch_images(tmp_path / "ds/ref", ["1.jpg", "3.jpg"])
    touch_images(tmp_path / "ds/query", ["1.jpg"])
    (tmp_path / "ds/ref/2.jpg").symlink_to(tmp_path / "gone.jpg")
    with pytest.raises(ImageReadError, match=r"ref/2\.jpg") as error:
        list_dataset(tmp_path, "toy", SPEC)
    assert "broken link" in str(error.value)
    (tmp_path / "ds/ref/2.jpg").unlink()
    (tmp_path / "ds/ref/2.jpg").mkdir()
    with pytest.raises(ImageReadError, match=r"ref/2\.jpg"):
        list_dataset(tmp_path, "toy", SPEC)


@pytest.mark.parametrize("recursive", [False, True])
def test_a_loop_of_links_among_the_images_is_an_error_naming_the_loop(tmp_path, recursive):
    """``a.jpg -> b.jpg -> a.jpg`` leads to no file (os.stat: ELOOP); named like images,
    the links are refused as a broken link is, naming the loop. Links in a loop named
    otherwise are passed over and counted, as a broken link is."""
    touch_images(tmp_path / "ds/ref", ["1.jpg", "3.jpg"])
    touch_images(tmp_path / "ds/query", ["1.jpg"])
    ref = tmp_path / "ds/ref"
    (ref / "notes").symlink_to("notes2")
    (ref / "notes2").symlink_to("notes")
    assert scan_images(ref, recursive=recursive).skipped_other == 2
    (ref / "a.jpg").symlink_to("b.jpg")
    (ref / "b.jpg").symlink_to("a.jpg")
    spec = {**SPEC, "recursive": recursive}
    with pytest.raises(ImageReadError) as error:
        list_dataset(tmp_path, "toy", spec)
    message = str(error.value)
    assert f"{ref / 'a.jpg'} is a link in a loop (a.jpg -> b.jpg -> a.jpg)" in message
    assert f"{ref / 'b.jpg'} is a link in a loop (b.jpg -> a.jpg -> b.jpg)" in message
    assert "which leads to no file: remove the links, or point one at the image" in message


def test_an_image_list_naming_a_link_in_a_loop_names_the_loop(tmp_path):
    root = tmp_path / "mine"
    write_pngs(root, ["db/1.png", "q/1.png"])
    (root / "db/2.png").symlink_to("3.png")
    (root / "db/3.png").symlink_to("2.png")
    (root / "ref.txt").write_text("db/1.png\ndb/2.png\n")
    (root / "query.txt").write_text("q/1.png\n")
    spec = dataset_spec(path="mine", reference="ref.txt", query="query.txt")
    loop = re.escape(f"image {root / 'db/2.png'} is a link in a loop (2.png -> 3.png -> 2.png)")
    with pytest.raises(DatasetError, match=rf"ref.txt line 2: {loop}, which leads to no file"):
        list_dataset(tmp_path, "mine", spec)


def test_listing_a_dataset_whose_defaults_were_not_filled_fails_with_key_error(tmp_path):
    touch_images(tmp_path / "ds/ref", ["1.jpg"])
    touch_images(tmp_path / "ds/query", ["2.jpg"])
    unfilled = {"path": "ds", "reference": "ref", "query": "query"}
    with pytest.raises(KeyError, match="recursive"):
        list_dataset(tmp_path, "toy", unfilled)


def test_paired_dataset_names_unpaired_files(tmp_path):
    spec = dict(SPEC, reference="vi", query="ir", paired=True)
    touch_images(tmp_path / "ds/vi", ["a.png", "b.png", "c.png"])
    touch_images(tmp_path / "ds/ir", ["a.png", "c.jpg", "d.png"])  # suffix may differ
    with pytest.raises(DatasetError) as error:
        list_dataset(tmp_path, "toy", spec)
    message = str(error.value)
    assert "2 file(s)" in message
    assert str(tmp_path / "ds/vi/b.png") in message and str(tmp_path / "ds/ir/d.png") in message
    (tmp_path / "ds/vi/b.png").unlink()
    (tmp_path / "ds/ir/d.png").unlink()
    files = list_dataset(tmp_path, "toy", spec)
    assert [p.stem for p in files.reference] == [p.stem for p in files.query] == ["a", "c"]


# ------------------------------------------------------------------ image lists


def write_pngs(folder, names):
    for name in names:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(folder / name)


def test_image_list_files_keep_their_order_and_name_bad_lines(tmp_path):
    root = tmp_path / "mine"
    write_pngs(root, ["db/1.png", "db/2.png", "q/1.png"])
    (root / "ref.txt").write_text("# database\ndb/2.png\n\ndb/1.png\n")
    (root / "query.txt").write_text("q/1.png\n")
    spec = dataset_spec(path="mine", reference="ref.txt", query="query.txt")
    files = list_dataset(tmp_path, "mine", spec)
    assert [p.relative_to(root).as_posix() for p in files.reference] == ["db/2.png", "db/1.png"]
    for text, message in (
        ("db/1.png\ndb/3.png\n", r"ref.txt line 2: image .*db/3.png does not exist"),
        ("db/1.png\ndb/1.png\n", r"line 2: 'db/1.png' is listed again \(first on line 1\)"),
        ("db/1.png\nnotes.txt\n", r"line 2: 'notes.txt' is not an image"),
    ):
        (root / "ref.txt").write_text(text)
        with pytest.raises(DatasetError, match=message):
            list_dataset(tmp_path, "mine", spec)


@pytest.mark.parametrize("again", ["./db/1.png", "db/../db/1.png", "db//1.png", "link.png"])
def test_an_image_list_naming_one_file_twice_in_two_spellings_is_refused(tmp_path, again):
    root = tmp_path / "mine"
    write_pngs(root, ["db/1.png", "db/2.png", "q/1.png"])
    (root / "link.png").symlink_to(root / "db/1.png")
    (root / "ref.txt").write_text(f"db/1.png\ndb/2.png\n{again}\n")
    (root / "query.txt").write_text("q/1.png\n")
    spec = dataset_spec(path="mine", reference="ref.txt", query="query.txt")
    message = rf"line 3: '{re.escape(again)}' is listed again \(first on line 1, as 'db/1.png'"
    with pytest.raises(DatasetError, match=message):
        list_dataset(tmp_path, "mine", spec)


def test_an_image_list_saved_with_a_byte_order_mark_reads_its_first_line(tmp_path):
    # Notepad's "UTF-8": the mark used to become part of the first path, an invisible
    # character in "image \ufeffdb/1.png does not exist".
    root = tmp_path / "mine"
    write_pngs(root, ["db/1.png", "db/2.png", "q/1.png"])
    (root / "ref.txt").write_bytes("db/1.png\r\ndb/2.png\r\n".encode("utf-8-sig"))
    (root / "query.txt").write_bytes("q/1.png\n".encode("utf-8-sig"))
    spec = dataset_spec(path="mine", reference="ref.txt", query="query.txt")
    files = list_dataset(tmp_path, "mine", spec)
    assert [p.relative_to(root).as_posix() for p in files.reference] == ["db/1.png", "db/2.png"]
    assert [p.relative_to(root).as_posix() for p in files.query] == ["q/1.png"]


def test_an_image_list_that_is_not_utf8_names_the_file_and_line(tmp_path):
    root = tmp_path / "mine"
    write_pngs(root, ["db/1.png", "q/1.png"])
    (root / "ref.txt").write_bytes(b"db/1.png\ndb/caf\xe9.png\n")  # Latin-1
    (root / "query.txt").write_text("q/1.png\n")
    spec = dataset_spec(path="mine", reference="ref.txt", query="query.txt")
    with pytest.raises(DatasetError, match=r"ref\.txt line 2 is not UTF-8 \(byte b'\\xe9'\)"):
        list_dataset(tmp_path, "mine", spec)


# ------------------------------------------------------------------ roles and pairs


def test_references_and_queries_that_are_the_same_files_are_refused(tmp_path):
    write_pngs(tmp_path / "ds/ref", ["1.png", "2.png"])
    same_folder = {**SPEC, "query": "ref"}
    with pytest.raises(DatasetError, match=r"2 query image\(s\) are also reference images"):
        list_dataset(tmp_path, "toy", same_folder)
    (tmp_path / "ds/query").mkdir()
    # A link to a file is read by default (datasets assembled from links), so the
    # overlap check is what refuses a query that links to a reference.
    (tmp_path / "ds/query/9.png").symlink_to(tmp_path / "ds/ref/2.png")
    with pytest.raises(DatasetError, match=r"query/9\.png = .*ref/2\.png"):
        list_dataset(tmp_path, "toy", SPEC)


def test_pairs_ground_truth_over_folders_needs_paired_listing(tmp_path):
    """Query i matched reference i by sort order, silently: rename one query and every
    later pair shifts."""
    write_pngs(tmp_path / "ds/vi", ["a.png", "b.png"])
    write_pngs(tmp_path / "ds/ir", ["a.png", "c.png"])
    spec = {**SPEC, "reference": "vi", "query": "ir", "ground_truth": {"kind": "pairs"}}
    with pytest.raises(
        DatasetError, match=r"dataset 'toy': ground_truth kind 'pairs' .* set `paired: true`"
    ):
        list_dataset(tmp_path, "toy", {**spec, "paired": False})
    # Paired, the renamed query is named instead of paired with b.png.
    with pytest.raises(DatasetError, match=r"c\.png"):
        list_dataset(tmp_path, "toy", {**spec, "paired": True})
    # Two image lists pair line by line (SNSM's published pairing).
    (tmp_path / "ds/vi.txt").write_text("vi/a.png\nvi/b.png\n")
    (tmp_path / "ds/ir.txt").write_text("ir/c.png\nir/a.png\n")
    listed = {**spec, "reference": "vi.txt", "query": "ir.txt", "paired": False}
    files = list_dataset(tmp_path, "toy", listed)
    assert [q.name for q in files.query] == ["c.png", "a.png"]


def test_pairs_are_matched_by_relative_path_not_by_sort_order(tmp_path):
    # The suffixes make the visible and thermal names sort in different orders.
    write_pngs(tmp_path / "ds/vi", ["a.png", "a.m.png"])  # a.m.png sorts first
    write_pngs(tmp_path / "ds/ir", ["a.jpg", "a.m.jpg"])  # a.jpg sorts first
    spec = {**SPEC, "reference": "vi", "query": "ir", "paired": True}
    files = list_dataset(tmp_path, "toy", spec)
    pairs = [(r.name, q.name) for r, q in zip(files.reference, files.query, strict=True)]
    assert pairs == [("a.m.png", "a.m.jpg"), ("a.png", "a.jpg")]


def test_pairs_in_subfolders_need_partners_in_the_same_subfolders(tmp_path):
    write_pngs(tmp_path / "ds/vi", ["day/1.png", "night/1.png"])
    write_pngs(tmp_path / "ds/ir", ["1.png", "2.png"])  # same stems, flat: not partners
    spec = {**SPEC, "reference": "vi", "query": "ir", "paired": True}
    with pytest.raises(DatasetError, match=r"no partner of the same relative path.*day/1\.png"):
        list_dataset(tmp_path, "toy", spec)


def test_a_name_with_two_suffixes_makes_pairs_ambiguous(tmp_path):
    write_pngs(tmp_path / "ds/vi", ["1.png", "1.jpg", "2.png"])
    write_pngs(tmp_path / "ds/ir", ["1.png", "2.png", "3.png"])
    spec = {**SPEC, "reference": "vi", "query": "ir", "paired": True}
    with pytest.raises(DatasetError, match=r"two suffixes.*vi/1\.jpg and .*vi/1\.png"):
        list_dataset(tmp_path, "toy", spec)


# "Café" decomposed (NFD, as macOS writes file names) and composed (NFC, as typed).
CAFE_NFD, CAFE_NFC = "Cafe\u0301", "Caf\u00e9"


def test_an_image_list_typed_composed_finds_files_named_decomposed(tmp_path):
    root = tmp_path / "mine"
    write_pngs(root, [f"db/{CAFE_NFD}/1.png", f"db/{CAFE_NFD}/2.png", "q/1.png"])
    (root / "ref.txt").write_text(f"db/{CAFE_NFC}/2.png\ndb/{CAFE_NFC}/1.png\n")
    (root / "query.txt").write_text("q/1.png\n")
    spec = dataset_spec(path="mine", reference="ref.txt", query="query.txt")
    files = list_dataset(tmp_path, "mine", spec)
    # Read under the files' own (decomposed) names, in the list's order.
    assert [p.relative_to(root).as_posix() for p in files.reference] == [
        f"db/{CAFE_NFD}/2.png",
        f"db/{CAFE_NFD}/1.png",
    ]
    assert all(p.is_file() for p in files.reference)


def test_pairs_named_in_two_unicode_forms_are_partners(tmp_path):
    root = tmp_path / "pairs"
    write_pngs(root, [f"vi/{CAFE_NFC}.png", "vi/b.png", f"ir/{CAFE_NFD}.png", "ir/b.png"])
    spec = dataset_spec(path="pairs", reference="vi", query="ir", paired=True)
    files = list_dataset(tmp_path, "pairs", spec)
    assert [p.name for p in files.query] == [f"{CAFE_NFD}.png", "b.png"]

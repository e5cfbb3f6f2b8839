"""Place datasets: folder layouts and image lists (docs/methods.md §9).

A dataset is a reference folder and a query folder under ``<data_root>/<path>``
(VPR-Bench layout: ``ref/`` and ``query/``; paired RGB-thermal layout: ``vi/`` and
``ir/`` with matching file names), searched recursively unless ``recursive: false``;
either may instead be a ``.txt`` file listing image paths relative to the dataset
folder, one per line, in the order given. References and queries must be different
images; a paired dataset's queries are put in the order of their partner references.
What the images are of (the ground truth) is :mod:`vprflow.data.ground_truth`.
"""

from __future__ import annotations

import os
import unicodedata
from dataclasses import dataclass
from pathlib import Path, PurePath

from vprflow.core.errors import DatasetError
from vprflow.core.files import link_loop
from vprflow.core.paths import dataset_folder, download_hint
from vprflow.data.images import IMAGE_SUFFIXES, ImageScan, natural_key, scan_images
from vprflow.data.presets import layout_hint, presets
from vprflow.data.published_truth import msls_listed_images


def nfc(name: str) -> str:
    """``name`` in Unicode's composed form (NFC), the one form names are compared in:
    macOS writes file names decomposed (NFD: ``e`` then a combining accent), while a
    name typed in a CSV or list is composed, and the two print alike."""
    return unicodedata.normalize("NFC", name)


def by_composed_name(names: list[str], what: str) -> dict[str, str]:
    """Each of ``names`` (a dataset's image names) by its :func:`nfc` form, refusing two
    that differ only in Unicode normalisation (one file name could not tell them apart)."""
    found: dict[str, str] = {}
    for name in names:
        other = found.setdefault(nfc(name), name)
        if other != name:
            raise DatasetError(
                f"{what}: {other!r} and {name!r} differ only in Unicode normalisation "
                "(composed and decomposed accents), so a name typed in a file matches "
                "both; rename one"
            )
    return found


def existing_path(root: Path, name: str) -> Path | None:
    """``root / name`` if it exists, else the path whose every part equals ``name``'s up
    to Unicode normalisation (a list typed composed, files written decomposed), with
    its real names; None if there is none."""
    path = root / name
    if path.exists():
        return path
    found = root
    for part in PurePath(name).parts:
        if (found / part).exists():
            found = found / part
            continue
        try:
            matches = [e.name for e in os.scandir(found) if nfc(e.name) == nfc(part)]
        except OSError:
            return None
        if len(matches) != 1:
            return None
        found = found / matches[0]
    return found


@dataclass(frozen=True)
class DatasetFiles:
    """Image paths of one dataset (folders: natural order of relative paths; list
    files: their order), and per role how many entries were skipped (hidden, other)."""

    reference: list[Path]
    query: list[Path]
    skipped: dict[str, tuple[int, int]] | None = None


def check_pairing(name: str, dataset: dict) -> None:
    """``ground_truth: {kind: pairs}`` matches query i with reference i, so the order of
    the two roles must be a pairing: two image lists (line i with line i, the published
    SNSM pairing) or ``paired: true`` (folders paired by name). Two folders without it
    were paired by sort order, silently: one renamed file shifted every later pair."""
    truth = dataset.get("ground_truth") or {}
    lists = all(str(dataset[role]).lower().endswith(".txt") for role in ("reference", "query"))
    if truth.get("kind") == "pairs" and not dataset.get("paired") and not lists:
        raise DatasetError(
            f"dataset '{name}': ground_truth kind 'pairs' matches query i with reference i, "
            f"but '{dataset['reference']}' and '{dataset['query']}' are not paired: set "
            "`paired: true` (each query is paired with the reference of the same path, "
            "suffix aside; a file without its partner is named), or give both roles as "
            ".txt image lists whose lines pair one to one"
        )


def list_dataset(data_root: str | Path, name: str, dataset: dict) -> DatasetFiles:
    """List reference and query images, failing with a message that says what is missing.

    ``dataset`` keys: ``path``, ``reference``, ``query`` (folder names), ``paired``
    (file names must match one to one), optional ``source`` (where to get the data).
    """
    check_pairing(name, dataset)
    root = dataset_folder(data_root, dataset)
    hint = f" Get it from {dataset['source']}." if dataset.get("source") else ""
    if not root.is_dir():
        if dataset.get("download"):
            hint = f" Download it with `{download_hint(name)}` (then run again).{hint}"

        if name in presets():
            hint += f"\nThe preset's published layout (docs/datasets.md):\n{presets()[name].layout}"
        raise DatasetError(
            f"dataset '{name}': folder {root} does not exist. Put the dataset there "
            f"(with '{dataset['reference']}/' and '{dataset['query']}/' inside) or set "
            f"data_root.{hint}"
        )
    scans: dict[str, ImageScan] = {}
    for role in ("reference", "query"):
        entry = root / dataset[role]
        listed = entry.suffix.lower() == ".txt"
        if not (entry.is_file() if listed else entry.is_dir()):
            raise DatasetError(
                f"dataset '{name}': {role} {'list' if listed else 'folder'} {entry} does not "
                f"exist.{hint}{layout_hint(name, root, dataset)}"
            )
        if listed:
            scans[role] = read_image_list(entry, root, f"dataset '{name}': {role} list")
            continue
        scans[role] = scan_images(entry, dataset["recursive"], dataset["follow_links"])
        if not scans[role].paths:
            raise DatasetError(f"dataset '{name}': {role} folder {entry} contains no images")
    reference, query = scans["reference"].paths, scans["query"].paths
    truth = listing_truth(dataset.get("ground_truth") or {})
    if truth:  # MSLS: the published lists name the images
        reference, query = msls_listed_images(root, truth["city"], reference, query)
    real = {}
    for scan in scans.values():
        if scan.real_paths is not None:  # known from discovery: spares a realpath each
            real.update(zip(scan.paths, scan.real_paths, strict=True))
    check_disjoint(name, reference, query, lambda p: real.get(p) or os.path.realpath(p))
    if dataset["paired"]:
        query = paired_queries(
            name,
            reference,
            query,
            _role_base(root, dataset, "reference", reference),
            _role_base(root, dataset, "query", query),
        )
    return DatasetFiles(
        reference=reference,
        query=query,
        skipped={r: (s.skipped_hidden, s.skipped_other) for r, s in scans.items()},
    )


def _role_base(root: Path, dataset: dict, role: str, paths: list[Path]) -> Path:
    """What a role's images are named relative to when pairing: its folder, or for a
    list file the folder its images have in common (``vi/`` of ``vi/1.jpg``)."""
    entry = root / dataset[role]
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
    lines and ``#`` comments ignored), in the file's order. Errors name the line.

    The file is UTF-8, with or without a byte-order mark (Windows editors write one).
    A file named twice is refused whatever the spelling (``ref/x.jpg``,
    ``./ref/x.jpg``, a link to it): names are compared as resolved paths."""
    if not list_file.is_file():
        raise DatasetError(f"{what}: image list {list_file} does not exist")
    try:
        text = list_file.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as error:
        line = list_file.read_bytes()[: error.start].count(b"\n") + 1
        raise DatasetError(
            f"{what}: {list_file} line {line} is not UTF-8 (byte "
            f"{error.object[error.start : error.start + 1]!r}): save the list as UTF-8"
        ) from error
    paths: list[Path] = []
    real_paths: list[str] = []
    seen: dict[str, tuple[int, str]] = {}
    for number, line in enumerate(text.splitlines(), start=1):
        name = line.strip()
        if not name or name.startswith("#"):
            continue
        where = f"{what}: {list_file} line {number}"
        path = root / name
        if path.suffix.lower() not in IMAGE_SUFFIXES:
            raise DatasetError(f"{where}: {name!r} is not an image file name")
        path = existing_path(root, name) or path  # the file's own spelling
        if not path.is_file():
            loop = link_loop(path)
            if loop:
                raise DatasetError(
                    f"{where}: image {path} is a link in a loop ({loop}), which leads to "
                    "no file: remove the links, or point one at the image"
                )
            raise DatasetError(f"{where}: image {path} does not exist")
        real = os.path.realpath(path)
        if real in seen:
            first, first_name = seen[real]
            same = "" if first_name == name else f", as {first_name!r}, the same file"
            raise DatasetError(f"{where}: {name!r} is listed again (first on line {first}{same})")
        seen[real] = (number, name)
        paths.append(path)
        real_paths.append(real)
    if not paths:
        raise DatasetError(f"{what}: image list {list_file} names no images")
    return ImageScan(paths, real_paths=real_paths)


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
            key = nfc(path.relative_to(base).with_suffix("").as_posix())
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
    return [
        queries[nfc(path.relative_to(ref_base).with_suffix("").as_posix())] for path in reference
    ]


def listing_truth(truth: dict) -> dict:
    """The ground-truth settings that decide which images a dataset lists: MSLS's
    published lists name its images (``kind`` and ``city``); no other kind's do. They
    shape the images store; every other ground-truth setting only the truth store."""
    return {"kind": "msls", "city": truth["city"]} if truth.get("kind") == "msls" else {}


# ---------------------------------------------------------------- images by folder, for errors


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


def role_folders(paths: list[Path], folder: Path) -> str:
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

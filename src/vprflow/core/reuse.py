"""Per-image results reused across stores: an image a per-image stage (features,
segments) already computed, with the same settings, in any finished store of this
results folder is not computed again.

A store's key hashes its record, whose ``inputs`` name the images store (the whole
image list of a dataset); everything else of the record (stage, format versions,
params: the model, its weights' digest, resolution, EXIF handling) is what shapes one
image's result. So an image's result is identified by that rest of the record (its
**settings**) and the image's SHA-256, which the images store holds: a finished store
of the same stage with equal settings holds the result of each image of its images
store, row for row. A changed image under an old name has another digest and is
computed; a renamed or copied one with the same bytes is found.

The results are found in the stores themselves, not in a separate pool: a store is
finished only once renamed into place (:func:`vprflow.core.stores.atomic_store`), so a
job killed mid-way leaves nothing here to find; a store deleted (cleanup) takes its
results with it; and on a cluster the shared results folder is the lookup. A store
that fails :func:`~vprflow.core.stores.open_store`'s checks is passed over, and every
result taken is checked again as it is read (:func:`link_chunk`, the stores' checked
reads), so a corrupted result is computed afresh, never used.
"""

from __future__ import annotations

import errno
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import google_crc32c
import numpy as np

from vprflow.core import stores

log = logging.getLogger("vprflow")

# The stages whose results are reused per image (their stores' layouts: one image a
# chunk, linked; ragged masks, a chunk of theirs that lands on a whole chunk of ours
# linked, the other rows copied).
STAGES = ("features", "segments")
# Each per-image job's log line (one), which the run's closing line sums
# (vprflow.planning.reports.reuse_line).
IMAGES_LINE = "images: %d computed, %d reused"
IMAGES_PATTERN = r"images: (\d+) computed, (\d+) reused"


def settings(record: dict) -> dict:
    """What of a per-image stage's ``record`` shapes each image's result: all of it but
    ``inputs`` (the images store's key, which is the dataset's image list)."""
    return {name: value for name, value in record.items() if name != "inputs"}


@dataclass(frozen=True)
class Source:
    """Image ``index`` of the finished store ``group`` holds the result wanted."""

    group: stores.CheckedGroup
    index: int


def find_sources(
    images_store: str | Path, record: dict, digests: list[str], wanted: range | list[int]
) -> dict[int, Source]:
    """For each image of ``wanted`` (indices into ``digests``, the SHA-256 of the job's
    images in the order of its images store, ``images_store``) whose result a finished
    store of ``record``'s stage with equal :func:`settings` holds: where. The stores
    looked at are those beside the job's own (``results/cache/<stage>/*.zarr``, the
    images stores beside ``images_store``), tried in the order of their keys, so the
    answer does not depend on the directory's listing order."""
    wanted_digests = {}
    for index in wanted:
        wanted_digests.setdefault(digests[index], []).append(index)
    found: dict[int, Source] = {}
    images_store = Path(images_store)
    for path, other in equal_stores(images_store.parent.parent / record["stage"], record):
        if not wanted_digests:
            break
        if "images" not in other.get("inputs", {}):
            continue
        try:
            images = stores.open_store(images_store.with_name(f"{other['inputs']['images']}.zarr"))
            theirs = stores.read_strings(images, "sha256")
            matches = [(i, digest) for i, digest in enumerate(theirs) if digest in wanted_digests]
            # Opened only where it holds a wanted image (a store is ~4 ms to open).
            group = stores.open_store(path) if matches else None
        except (stores.StoreCorruptError, FileNotFoundError, KeyError) as error:
            log.warning("not reusing results of %s: %s", path, error)
            continue
        for their_index, digest in matches:
            for index in wanted_digests.pop(digest, ()):
                found[index] = Source(group, their_index)
    return found


def equal_stores(folder: Path, record: dict) -> list[tuple[Path, dict]]:
    """``(path, record)`` of each finished store in ``folder`` (a stage's folder of
    ``results/cache``) whose record has ``record``'s :func:`settings`, in key order (so
    that no answer depends on the directory's listing order)."""
    found, own = [], settings(record)
    for path in sorted(folder.glob("*.zarr")) if folder.is_dir() else []:
        other = _record(path)
        if other is not None and settings(other) == own:
            found.append((path, other))
    return found


def _record(path: Path) -> dict | None:
    """The record a finished store's group attributes hold, or None (unreadable)."""
    try:
        attributes = json.loads((path / "zarr.json").read_text()).get("attributes", {})
    except (OSError, ValueError):
        return None
    record = attributes.get("record")
    return record if isinstance(record, dict) else None


def chunk_file(array, index: int) -> Path:
    """The file of chunk ``index`` along the first axis of ``array`` (a zarr array
    chunked along its first axis only: row ``index``'s where a chunk is one row, as a
    features store's ``features``)."""
    key = array.metadata.encode_chunk_key((index,) + (0,) * (array.ndim - 1))
    return stores.array_directory(array) / key


# Why a hard link fails where a copy does: another file system (EXDEV), one without
# hard links (EPERM, ENOTSUP: some network and FUSE mounts), too many links (EMLINK).
_NO_LINK = (errno.EXDEV, errno.EPERM, errno.ENOTSUP, errno.EMLINK)


def link_chunk(source: Path, target: Path, chunk_bytes: int | None) -> bool:
    """Put the chunk file ``source`` at ``target`` as a hard link, so the bytes are
    stored once for every store that holds them (a copy where the file system refuses
    the link) -> whether it was: :func:`read_chunk`, then :func:`place_chunk`."""
    data = read_chunk(source, chunk_bytes)
    if data is None:
        return False
    place_chunk(source, target, data)
    return True


def read_chunk(source: Path, chunk_bytes: int | None) -> bytes | None:
    """The bytes of the chunk file ``source`` where it is whole and intact: its CRC-32C
    (the last 4 bytes, as :data:`vprflow.core.stores.COMPRESSORS` and
    :data:`~vprflow.core.stores.CHECKSUM_ONLY` store it) matches and, given
    ``chunk_bytes`` (an uncompressed chunk's size), its size is that and the checksum's.
    None where it is absent (its store deleted meanwhile, or a chunk equal to the fill
    value, which zarr does not store: rare enough to compute again) or, with a warning,
    not whole and intact: the caller computes or reads that chunk's rows instead."""
    try:
        data = source.read_bytes()
    except FileNotFoundError:
        return None
    whole = chunk_bytes is None or len(data) == chunk_bytes + 4
    if (
        not whole
        or len(data) < 4
        or google_crc32c.value(data[:-4]) != int.from_bytes(data[-4:], "little")
    ):
        log.warning("not reusing %s: it fails its checksum or size check", source)
        return None
    return data


def place_chunk(source: Path, target: Path, data: bytes) -> None:
    """Hard-link ``target`` to ``source``, a chunk file whose checked bytes are ``data``
    (:func:`read_chunk`); where the file system refuses hard links, or ``source`` is gone
    since it was read, write ``data`` there instead."""
    try:
        os.link(source, target)
        return
    except FileNotFoundError:
        if not target.parent.is_dir():  # a chunk key's first file in its folder
            target.parent.mkdir(parents=True, exist_ok=True)
            place_chunk(source, target, data)
            return
    except OSError as error:
        if error.errno not in _NO_LINK:
            raise
    with open(target, "wb") as file:
        file.write(data)


@dataclass(frozen=True)
class Chunk:
    """A whole chunk file of a finished store, checked (:func:`read_chunk`), to become a
    store's next chunk as it is (:func:`append_rows`)."""

    path: Path
    data: bytes


def read_rows(
    array: stores.CheckedArray, low: int, high: int, position: int, link: bool
) -> list[np.ndarray | Chunk]:
    """Rows ``low:high`` of ``array`` (a finished store's, chunked along its first axis
    only) to append at row ``position`` of an array being written: as whole chunk files
    where ``link`` (the two arrays' chunk files alike: :func:`same_chunks`) and a chunk
    of theirs lands on a whole chunk of ours, so that its bytes are stored once; the
    rest as rows, read and checked. Raises
    :class:`~vprflow.core.stores.StoreCorruptError` where rows fail their checks, before
    anything is appended: the caller computes those images instead."""
    step = array.chunks[0]
    first, last = -(-low // step), high // step
    if not link or (position - low) % step or first >= last:
        return [np.asarray(array[low:high])]
    pieces: list[np.ndarray | Chunk] = [np.asarray(array[low : first * step])]
    for index in range(first, last):
        path = chunk_file(array.raw, index)
        data = read_chunk(path, None)
        if data is None:  # absent (the fill value) or damaged (then the read raises)
            pieces.append(np.asarray(array[index * step : (index + 1) * step]))
        else:
            pieces.append(Chunk(path, data))
    pieces.append(np.asarray(array[last * step : high]))
    return pieces


def append_rows(writer: stores.RowWriter, pieces: list[np.ndarray | Chunk]) -> None:
    """Append :func:`read_rows`' ``pieces`` to ``writer``: rows as rows, a :class:`Chunk`
    (which lands on a whole chunk of ours) hard-linked in as the next chunk's file."""
    for piece in pieces:
        if isinstance(piece, Chunk):
            index = (writer.written + writer.buffered) // writer.chunk_rows
            writer.skip(writer.chunk_rows)
            place_chunk(piece.path, chunk_file(writer.array, index), piece.data)
        elif len(piece):
            writer.append_rows(piece)


def same_chunks(array: Path, other: Path) -> bool:
    """Whether the arrays at ``array`` and ``other`` (folders) store rows in chunk files
    alike: the same chunk shape, type and codecs (all their metadata but the shape and
    attributes), so equal rows are equal files."""
    metadata = _array_metadata(array)
    return metadata is not None and metadata == _array_metadata(other)


def link_equal_chunks(array: Path, record: dict, folder: Path) -> int:
    """Hard-link each chunk file of ``array`` (the folder of an array of a store being
    written, not renamed into place yet) that is byte for byte the chunk file of the
    same index in the same array of a finished store of equal :func:`settings` in
    ``folder`` (the stage's folder of ``results/cache``), so that the bytes are on disk
    once -> how many were linked.

    For arrays that pack many images a chunk (a segments store's masks), whose rows
    cannot be linked one by one: where two stores hold the same images at the same rows
    (a second query set after the same references; images added after the last one),
    their chunks are the same bytes. Equal bytes in arrays of equal chunk shape, type and
    codecs are equal contents, so the store is the one a run from scratch writes; a file
    system without hard links keeps the copy. The job's log says how many of its chunk
    files are another store's, linked here or before (:func:`append_rows`)."""
    twins = [
        path / array.name
        for path, _ in equal_stores(folder, record)
        if same_chunks(array, path / array.name)
    ]
    linked = shared = 0
    for chunk in _chunk_files(array):
        links = chunk.stat().st_nlink
        if links == 1 and twins:  # else another store's already
            outcome = _link_to_twin(chunk, [twin / chunk.relative_to(array) for twin in twins])
            if outcome is None:  # the file system refuses hard links: keep the copies
                twins = []
            linked += bool(outcome)
            links += bool(outcome)
        shared += links > 1
    log.info("%s: %d chunk files shared with other stores", array.name, shared)
    return linked


def _chunk_files(array: Path) -> list[Path]:
    """The chunk files of the array at ``array`` (a folder: its files but ``zarr.json``,
    under ``c/`` or flat, :data:`vprflow.core.stores.FLAT_CHUNK_KEYS`), in order."""
    files = (Path(folder, name) for folder, _, names in os.walk(array) for name in names)
    return sorted(path for path in files if path != array / "zarr.json")


def _link_to_twin(chunk: Path, twins: list[Path]) -> bool | None:
    """Replace ``chunk`` by a hard link to the first of ``twins`` (files) with its bytes
    -> whether one was; None where the file system refuses hard links."""
    size, ours = chunk.stat().st_size, None
    staged = chunk.with_name(chunk.name + ".link")
    for theirs in twins:
        try:
            if theirs.stat().st_size != size:
                continue
            ours = chunk.read_bytes() if ours is None else ours
            if theirs.read_bytes() != ours:
                continue
            os.link(theirs, staged)
        except FileNotFoundError:  # their store deleted meanwhile
            continue
        except OSError as error:
            if error.errno not in _NO_LINK:
                raise
            return None
        os.replace(staged, chunk)
        return True
    return False


def _array_metadata(array: Path) -> dict | None:
    """What an array's metadata (``zarr.json``) says of its chunks' bytes (all but its
    shape and attributes), or None (none there)."""
    try:
        metadata = json.loads((array / "zarr.json").read_text())
    except (OSError, ValueError):
        return None
    return {k: v for k, v in metadata.items() if k not in ("shape", "attributes")}

"""Zarr stores written atomically, with ragged (per-image variable length) arrays.

Every stage writes one Zarr group. It is built at a temporary beside ``<out>``
(``<stem>.<host>-<pid>-<random><suffix>.tmp``, one per writer) and renamed onto
``<out>`` only when complete, so an interrupted job never leaves a store that looks
finished, and two runs writing the same store at once (``snakemake --nolock``) do not
collide: the first to finish puts its store in place, the other finds the same keyed
store there and discards its own (:func:`replace_store`).

Ragged data (a variable number of segments per image) is one concatenated array plus
an ``offsets`` array of length ``n + 1``: image ``i`` owns rows
``offsets[i]:offsets[i + 1]``.

Every chunk carries a CRC-32C checksum (zarr's standard ``crc32c`` codec, after the
compressor), and every array records how many chunk files it was finished with.
:func:`open_store` checks both, so a flipped byte, a truncated file or a lost chunk is
a :class:`StoreCorruptError` naming the store, the array and the remedy, never NaN or
silently different values in a believable table. The stores stay plain Zarr v3.
"""

from __future__ import annotations

import errno
import itertools
import logging
import os
import re
import shutil
import warnings
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor, wait
from contextlib import contextmanager
from pathlib import Path

import google_crc32c
import numcodecs.zstd
import numpy as np
import zarr
import zarr.codecs
import zarr.core.chunk_grids
import zarr.core.chunk_key_encodings
import zarr.storage

from vprflow.core.files import TAG, is_abandoned, writer_tag
from vprflow.core.runs import runs_here

log = logging.getLogger("vprflow")

# Level 1: on descriptor arrays it compresses within 3% of level 3 at a third of the
# time (2.08 vs 2.13 on sparse VLAD rows, 91 vs 262 ms per 26 MB), which bounded the
# per-image speed of stages writing ~400 KB per image. Values are the same at any level.
COMPRESSOR = zarr.codecs.ZstdCodec(level=1)
# The codecs of every array but CHECKSUM_ONLY's. Without a checksum a flipped byte in a
# compressed chunk either fails with a bare "Zstd decompression error" or, worse, decodes
# to other values (NaN included) that a later stage ranks and counts. CRC-32C runs on
# the compressed bytes, so it checks exactly what is on disk.
COMPRESSORS = (COMPRESSOR, zarr.codecs.Crc32cCodec())
# Descriptor rows, the largest arrays a stage compresses as it computes, at zstd's fast
# level -3. SegVLAD's sparse rows without PCA (~400 KB an image) compress in 0.12
# against 0.275 ms an image and decompress 4x faster than at level 1, for 8% more bytes;
# dense rows (anyloc_vlad, SNSM, PCA-projected), which level 1 shrank to 64-92%, stay at
# 73-100% but go through at 2.7-5 GB/s (20-36 GB/s back) against 0.4-0.9. Not
# CHECKSUM_ONLY for those: a store's last chunk is padded to the chunk's 4 MiB, which
# only compression takes back (a 100-image store would be 4.2 MB instead of 1.2). Only
# descriptors: small arrays of integers (search lists, offsets) grow 1.4-2.5x at -3.
FAST_COMPRESSORS = (zarr.codecs.ZstdCodec(level=-3), zarr.codecs.Crc32cCodec())
# The codecs of arrays whose bytes zstd hardly shrinks: the checksum alone. Float patch
# features keep 90% of their bytes at level 1 (DAISY on the corridor), and decoding them
# was 0.1 ms of every image read in every stage that reads them (descriptors,
# vocabulary, matches): 27 of anyloc_vlad's 163 ms over 256 images. Sparse VLAD rows
# shrink to 20-36% and keep COMPRESSORS.
CHECKSUM_ONLY = (zarr.codecs.Crc32cCodec(),)
# Chunk files named c.<i>.<j> in the array's folder instead of zarr's c/<i>/<j>: no
# folder per chunk, for arrays of one image a chunk that other stores' files are linked
# into (features: three folders an image otherwise; per_image masks, vprflow.core.masks).
# Creating a folder took 0.22-0.28 ms here (ext4, 2,000 of them), a hard link 0.013 ms.
# zarr.json names the encoding, so a store of either is read alike.
FLAT_CHUNK_KEYS = {"name": "default", "separator": "."}
# Array attribute: the number of chunk files the array had when its store was finished.
# zarr returns the fill value for a missing chunk file, so a lost file is otherwise
# invisible.
CHUNK_FILES = "chunk_files"

# RowWriter's background writes not yet waited for: a failing stage waits for them
# before it deletes its temporary store, so that none lands in a deleted directory.
_PENDING_WRITES: set[Future] = set()


def temporary_path(path: str | Path, tag: str | None = None) -> Path:
    """Where one writer builds ``path``: ``<stem>.<tag><suffix>.tmp`` beside it (``tag``:
    :func:`vprflow.core.files.writer_tag`, a new one by default), e.g. ``k.zarr`` is built at
    ``k.node1-4242-0f3a9c1e.zarr.tmp``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.{tag or writer_tag()}{path.suffix}.tmp")


def _aside_path(path: Path) -> Path:
    """Where a store being replaced is moved before it is deleted."""
    return path.with_name(f"{path.stem}.{writer_tag()}{path.suffix}.old")


def temporary_paths(path: str | Path) -> list[tuple[Path, re.Match | None]]:
    """The temporaries of ``path`` that exist, each with its writer tag parsed (None for
    ``<out>.tmp``, the name vprflow used before writer tags), sorted by name."""
    path = Path(path)
    pattern = re.compile(re.escape(path.stem + ".") + TAG + re.escape(path.suffix) + r"\.(tmp|old)")
    found = []
    if path.parent.is_dir():
        for entry in sorted(path.parent.iterdir()):
            if entry.name == path.name + ".tmp":
                found.append((entry, None))
            elif match := pattern.fullmatch(entry.name):
                found.append((entry, match))
    return found


def remove_abandoned_temporaries(path: str | Path) -> list[Path]:
    """Delete the temporaries of ``path`` no live writer owns (an interrupted run's);
    return them. A live writer's (another run writing the same store at once) is left
    alone, with a warning."""
    removed = []
    for tmp, match in temporary_paths(path):
        if match is None or is_abandoned(tmp, match["host"], int(match["pid"])):
            log.info("removing %s, left by an interrupted run", tmp)
            _remove(tmp)
            removed.append(tmp)
        else:
            log.warning(
                "another run is writing %s (pid %s on %s, in %s): two runs of one folder "
                "at once; Snakemake's lock prevents this, --nolock bypasses it. Whichever "
                "finishes first is kept",
                path,
                match["pid"],
                match["host"],
                tmp.name,
            )
    return removed


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


class ConcurrentWriteError(RuntimeError):
    """Another run kept replacing a store while this one tried to put its own in place."""


@contextmanager
def atomic_store(path: str | Path, attrs: dict | None = None) -> Iterator[zarr.Group]:
    """Yield a writable Zarr group that appears at ``path`` only if the block succeeds.

    The group is built at this writer's own temporary (:func:`temporary_path`); the
    temporaries of interrupted runs are removed first, a live writer's are left alone
    (:func:`remove_abandoned_temporaries`). On an exception the temporary store is
    deleted and the exception propagates.
    """
    path = Path(path)
    remove_abandoned_temporaries(path)
    tmp = temporary_path(path)
    tmp.parent.mkdir(parents=True, exist_ok=True)
    group = zarr.open_group(str(tmp), mode="w", attributes=attrs)
    try:
        yield group
    except BaseException:
        done, _ = wait(list(_PENDING_WRITES))
        _PENDING_WRITES.difference_update(done)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    try:
        _seal(group, tmp)
        # Snakemake may pre-create (or leave) the directory output; it holds no data.
        replace_store(tmp, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def set_attrs(node: zarr.Group | zarr.Array, **values) -> None:
    """Add or replace attributes of ``node`` in one write of its ``zarr.json``, the
    file zarr's ``attrs.update`` leaves: that writes it once per key, about 1 ms each
    through zarr's event loop, several of a short job's fixed milliseconds."""
    node.attrs.put({**node.attrs.asdict(), **values})


def _seal(group: zarr.Group, path: Path) -> None:
    """Record each array's number of chunk files (checked by :func:`open_store`);
    refuse an array created without the checksum, which no reader would accept."""
    for name, array in array_items(group):
        if not _has_checksum(array):
            raise ValueError(
                f"store {path}: array '{name}' was created without stores.COMPRESSORS "
                f"(codecs {array.compressors}); every array needs the crc32c checksum"
            )
        array.attrs[CHUNK_FILES] = count_chunk_files(path / name)


def count_chunk_files(array_path: Path) -> int:
    """Files of an array's directory other than its ``zarr.json``: its chunks.

    A directory stack over ``os.scandir``, whose entries know their type: ``os.walk``
    also stats every directory (a link check), which made counting a 2,048-image
    features store (a directory per chunk per axis, 6,144 in all) 75 ms against 50.
    """
    files, stack = 0, [os.fspath(array_path)]
    while stack:
        with os.scandir(stack.pop()) as entries:
            for entry in entries:
                if not entry.is_dir():
                    files += 1
                elif not entry.is_symlink():  # as os.walk: a linked directory is not walked
                    stack.append(entry.path)
    return files - 1


def _every_chunk_file_present(array: zarr.Array, directory: Path, written: int) -> bool:
    """Whether ``written`` is every chunk of ``array``'s grid and each has its file.

    Where it is, this check takes a stat per chunk instead of a listing of every
    directory (:func:`count_chunk_files`): a 2,048-image features store, a chunk per
    image three directories deep, opened in 13 ms against 52. It finds the same lost
    chunk files, and only overlooks files that are no chunk of the array, which no
    read opens. Where zarr skipped chunks equal to the fill value, or a file is
    missing, the caller counts the files."""
    if written != array.nchunks:
        return False
    encode = array.metadata.encode_chunk_key
    root = os.fspath(directory)
    return all(
        os.path.isfile(os.path.join(root, encode(coords)))
        for coords in itertools.product(*map(range, array.cdata_shape))
    )


def _has_checksum(array: zarr.Array) -> bool:
    compressors = array.compressors
    return bool(compressors) and isinstance(compressors[-1], zarr.codecs.Crc32cCodec)


def replace_store(source: str | Path, path: str | Path, attempts: int = 5) -> None:
    """Move a finished store from ``source`` to ``path`` in one rename (same file system),
    replacing whatever is at ``path``, unless that is already the same finished store.

    Two runs writing one keyed store at once (``--nolock``) both get here: the first
    rename wins; the second finds a finished store with the same ``record`` (the key
    hashes it, so the two are equivalent), keeps it and deletes ``source``. Anything
    else at ``path`` (Snakemake's empty directory output or its timestamp, a damaged or
    other store) is moved aside in one rename, then deleted. A path that keeps being
    replaced under us is a :class:`ConcurrentWriteError`.
    """
    source, path = Path(source), Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(attempts):
        try:
            os.replace(source, path)  # also replaces an empty directory
            return
        except OSError as error:
            if error.errno not in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOTDIR, errno.EISDIR):
                raise
        if _same_finished_store(source, path):
            log.info(
                "%s was finished by another run meanwhile (the same record): keeping it, "
                "discarding this run's copy",
                path,
            )
            shutil.rmtree(source, ignore_errors=True)
            return
        aside = _aside_path(path)
        try:
            os.replace(path, aside)
        except FileNotFoundError:
            continue  # another run moved it away first
        _remove(aside)
    raise ConcurrentWriteError(
        f"store {path}: another run kept replacing it while this one tried to put its own "
        f"in place ({attempts} tries), and this run's copy was discarded. Two runs are "
        "writing the same store at once: do not use --nolock for concurrent runs of one "
        "target (run it once, or let the second run wait for Snakemake's lock)"
    )


def _same_finished_store(source: Path, path: Path) -> bool:
    """Whether ``path`` holds a finished, undamaged store with ``source``'s record."""
    try:
        ours = zarr.open_group(str(source), mode="r").attrs.get("record")
        if ours is None:
            return False
        theirs = open_store(path)
        return theirs.attrs.get("record") == ours
    except (StoreCorruptError, FileNotFoundError, ValueError, OSError):
        return False


class StoreCorruptError(ValueError):
    """A store cannot be read as written; the message names the store, the array and
    the remedy (delete the store and let Snakemake rebuild it)."""

    def __init__(self, path: str | Path, fault: str):
        super().__init__(
            f"store {path}: {fault}. Delete the store (rm -r {path}) and run snakemake "
            f"again to rebuild it"
        )
        self.path = Path(path)


def open_store(path: str | Path) -> CheckedGroup:
    """Open a finished store read-only, checked: a clear error if it is missing, and a
    :class:`StoreCorruptError` if its metadata cannot be read, an array lacks the
    checksum (a store from before checksums) or lost chunk files. Every later read is
    checked too (see :class:`CheckedArray`)."""
    path = Path(path)
    if not path.exists():
        writers = live_writers(path)
        if writers:
            raise FileNotFoundError(
                f"store {path} does not exist: another run is writing it ({writers}). "
                "Two runs of one folder delete each other's stores; Snakemake's lock "
                "prevents this, --nolock bypasses it"
            )
        runs = runs_here()  # this job's own run among them
        if len(runs) > 1:
            each = ", ".join(f"pid {run['pid']} on {run['host']}" for run in runs)
            raise FileNotFoundError(
                f"store {path} does not exist: {len(runs)} runs of this folder are going "
                f"on at once ({each}), and two runs of one folder delete each other's "
                "stores; Snakemake's lock prevents this, --nolock bypasses it"
            )
        raise FileNotFoundError(f"store {path} does not exist (has its stage run?)")
    return CheckedGroup(path)


def live_writers(path: str | Path) -> str:
    """The processes writing a temporary of ``path`` at this moment, for a message
    (``pid 123 on host``, ...), or ``""``."""
    return ", ".join(
        f"pid {match['pid']} on {match['host']}"
        for tmp, match in temporary_paths(path)
        if match is not None and not is_abandoned(tmp, match["host"], int(match["pid"]))
    )


class CheckedGroup:
    """A finished store, read-only: the part of ``zarr.Group`` the stages use
    (``group[name]``, ``name in group``, ``arrays()``, ``attrs``), with every array a
    :class:`CheckedArray`. Stores are flat: one group of arrays.

    Opening reads every array's metadata and lists its chunk files (a directory
    listing, no chunk is read), so a damaged store fails here, before any work.
    """

    def __init__(self, path: Path):
        self.path = path
        if not (path / "zarr.json").is_file():
            raise StoreCorruptError(path, "its group metadata zarr.json is missing")
        try:
            self.raw = zarr.open_group(str(path), mode="r")
        except (ValueError, RuntimeError, TypeError) as error:
            raise StoreCorruptError(
                path, f"its group metadata zarr.json cannot be read ({_describe(error)})"
            ) from error
        self._arrays = {
            entry.name: self._open_array(entry.name)
            for entry in sorted(os.scandir(path), key=lambda e: e.name)
            if entry.is_dir()
        }

    def _open_array(self, name: str) -> CheckedArray:
        def corrupt(fault: str) -> StoreCorruptError:
            return StoreCorruptError(self.path, f"array '{name}' {fault}")

        if not (self.path / name / "zarr.json").is_file():
            raise corrupt(f"has no metadata ({name}/zarr.json is missing)")
        try:
            array = self.raw[name]
        except (ValueError, RuntimeError, TypeError, KeyError) as error:
            raise corrupt(
                f"has unreadable metadata {name}/zarr.json ({_describe(error)})"
            ) from error
        if not isinstance(array, zarr.Array):
            raise corrupt("is not an array (vprflow stores hold arrays only)")
        if not _has_checksum(array):
            raise corrupt(
                "has no crc32c checksum: the store predates checksums (written by an older "
                "vprflow) and cannot be verified"
            )
        written = array.attrs.get(CHUNK_FILES)
        if written is None:
            raise corrupt(f"records no '{CHUNK_FILES}' count (never finished by vprflow)")
        if not _every_chunk_file_present(array, self.path / name, written):
            found = count_chunk_files(self.path / name)
            if found != written:
                raise corrupt(f"has {found} chunk files, {written} were written")
        return CheckedArray(array, self.path, name)

    @property
    def attrs(self):
        return self.raw.attrs

    def __getitem__(self, name: str) -> CheckedArray:
        try:
            return self._arrays[name]
        except KeyError:
            raise KeyError(
                f"store {self.path} has no array '{name}' (it has {sorted(self._arrays)})"
            ) from None

    def __contains__(self, name: str) -> bool:
        return name in self._arrays

    def __iter__(self) -> Iterator[str]:
        return iter(self._arrays)

    def arrays(self) -> Iterator[tuple[str, CheckedArray]]:
        return iter(self._arrays.items())

    def __repr__(self) -> str:
        return f"<store {self.path}: {', '.join(self._arrays)}>"


class CheckedArray:
    """One array of a :class:`CheckedGroup`, read-only: slicing, ``np.asarray``,
    ``shape``, ``dtype``, ``chunks``, ``attrs`` and ``len`` as on ``zarr.Array``
    (``raw`` is the zarr array itself). A chunk that fails to decode (checksum
    mismatch, decompression error, wrong size) raises :class:`StoreCorruptError`
    instead of zarr's error, which names neither store nor array.

    Whole rows (``a[...]``, ``a[i:j]``, ``a[i]``) of an array with exactly vprflow's
    codecs are read by :class:`_RowReader`, straight from the chunk files, with the same
    checks and values as zarr's read; every other selection or array goes through zarr.
    """

    def __init__(self, array: zarr.Array, store: Path, name: str):
        self.raw = array
        self.store = store
        self.name = name
        self._rows = _RowReader.of(array, store, name)

    def __getitem__(self, selection):
        if self._rows is not None:
            rows = _row_selection(selection, self.raw.shape)
            if rows is not None:
                return self._rows.read(*rows)
        try:
            return self.raw[selection]
        # Selection mistakes are IndexErrors in zarr and pass through; decoding failures
        # are ValueError (checksum, size) or RuntimeError (zstd).
        except (ValueError, RuntimeError) as error:
            raise StoreCorruptError(
                self.store, f"array '{self.name}' cannot be decoded ({_describe(error)})"
            ) from error

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        data = np.asarray(self[...])
        return data if dtype is None else data.astype(dtype, copy=False)

    def __len__(self) -> int:
        return self.shape[0]

    shape = property(lambda self: self.raw.shape)
    dtype = property(lambda self: self.raw.dtype)
    ndim = property(lambda self: self.raw.ndim)
    size = property(lambda self: self.raw.size)
    chunks = property(lambda self: self.raw.chunks)
    attrs = property(lambda self: self.raw.attrs)

    def __repr__(self) -> str:
        return f"<array '{self.name}' {self.shape} {self.dtype} of store {self.store}>"


def _row_selection(selection, shape: tuple[int, ...]) -> tuple[int, int, bool] | None:
    """``(start, stop, squeeze)`` if ``selection`` takes whole rows along axis 0: ``...``,
    ``()``, an ``int`` in range (``squeeze``: the result drops axis 0), or a slice of step
    1, alone or followed by ``...`` or full slices; else None,
    and zarr reads it (steps, fancy indexing, selections inside rows, and every
    selection mistake, which zarr names)."""
    length = shape[0]
    if isinstance(selection, tuple):
        parts = [part for part in selection if part is not Ellipsis]
        if len(selection) - len(parts) > 1 or len(parts) > len(shape):
            return None
        if not all(isinstance(part, slice) and part == slice(None) for part in parts[1:]):
            return None
        if selection and selection[0] is Ellipsis and parts:
            return None  # "..., x" selects along the last axes
        if parts and not isinstance(parts[0], slice):
            return None  # zarr answers "(i, ...)" on 1-D with a scalar, "i" with a 0-d array
        selection = parts[0] if parts else Ellipsis
    if selection is Ellipsis:
        return 0, length, False
    if isinstance(selection, slice):
        if selection.step not in (None, 1):
            return None
        start, stop, _ = selection.indices(length)
        return start, max(start, stop), False
    # Python's int only: zarr returns a numpy scalar for a numpy integer into a 1-D array
    # and a 0-d array for an int, and the two are told apart by zarr itself.
    if type(selection) is int:
        index = selection + (length if selection < 0 else 0)
        return (index, index + 1, True) if 0 <= index < length else None
    return None


_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
# The codec chains the row reader decodes: zarr's bytes serializer, then COMPRESSORS
# (FAST_COMPRESSORS differ by the level alone) or CHECKSUM_ONLY.
_ROW_CODECS = tuple(
    [zarr.codecs.BytesCodec, *(type(codec) for codec in chain)]
    for chain in (COMPRESSORS, FAST_COMPRESSORS, CHECKSUM_ONLY)
)


def _plain_chunk_files(array: zarr.Array) -> bool:
    """Whether vprflow reads and writes ``array``'s chunk files itself (:class:`_RowReader`,
    :func:`store_rows`) instead of through zarr: it understands their every byte. zarr v3
    on a local directory, a regular chunk grid, the default chunk key encoding, exactly
    the codecs bytes, zstd, crc32c (:data:`COMPRESSORS`, :data:`FAST_COMPRESSORS`) or
    bytes, crc32c (:data:`CHECKSUM_ONLY`), and a numeric dtype stored in the byte order
    zarr returns."""
    metadata = array.metadata
    if (
        metadata.zarr_format != 3
        or not isinstance(array.store, zarr.storage.LocalStore)
        or array.ndim == 0
        or metadata.storage_transformers
        or type(metadata.chunk_grid) is not zarr.core.chunk_grids.RegularChunkGrid
        or type(metadata.chunk_key_encoding)
        is not zarr.core.chunk_key_encodings.DefaultChunkKeyEncoding
        or [type(codec) for codec in metadata.codecs] not in _ROW_CODECS
        or not isinstance(array.dtype, np.dtype)
        or array.dtype.kind not in "biufc"
    ):
        return False
    endian = metadata.codecs[0].endian
    stored = array.dtype
    if endian is not None and stored.itemsize > 1:
        stored = stored.newbyteorder("<" if endian.value == "little" else ">")
    return stored == array.dtype


def array_directory(array: zarr.Array) -> Path:
    """The folder of ``array`` (a local store's): its ``zarr.json`` and chunk files."""
    return Path(array.store.root) / array.path


def _write_chunk(array: zarr.Array, index: int, rows: np.ndarray) -> None:
    """Write ``rows``, the whole content of chunk ``index`` of ``array`` (chunked along its
    first axis only, :func:`_plain_chunk_files`), as zarr would write it: padded with
    the fill value to the chunk's shape, encoded by the array's codecs (numcodecs' zstd,
    the library zarr's ``ZstdCodec`` calls; CRC-32C of the result appended,
    little-endian), at the chunk's key."""
    step = array.chunks[0]
    if len(rows) == step:
        chunk = np.ascontiguousarray(rows, dtype=array.dtype)
    else:
        chunk = np.full(array.chunks, array.fill_value, dtype=array.dtype)
        chunk[: len(rows)] = rows
    data = chunk.reshape(-1).view(np.uint8)
    for codec in array.metadata.codecs[1:-1]:  # zstd, where the array has it
        data = np.frombuffer(
            numcodecs.zstd.compress(data, codec.level, codec.checksum), dtype=np.uint8
        )
    path = array_directory(array) / array.metadata.encode_chunk_key(
        (index,) + (0,) * (array.ndim - 1)
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as file:
        file.write(data)
        file.write(google_crc32c.value(data).to_bytes(4, "little"))


class _RowReader:
    """Reads whole rows of one array from its chunk files, as zarr would but without
    zarr's per-chunk machinery (its event loop, buffers and codec pipeline: 0.4-0.5 ms a
    125 KB chunk against 0.2 ms of decompression, benchmarks/README.md "Descriptors").

    Only for arrays whose every stored byte it understands (:func:`_plain_chunk_files`).
    Each chunk file is checked (CRC-32C of the stored bytes, the last 4 bytes,
    little-endian, as zarr's ``Crc32cCodec``), decompressed by numcodecs' zstd (the
    library zarr's ``ZstdCodec`` calls) or read straight into the result where a
    chunk's rows are whole rows of it, and a missing chunk file is the fill value (zarr
    does not store chunks equal to it).
    """

    def __init__(self, array: zarr.Array, directory: Path, store: Path, name: str):
        self.array = array
        self.directory = directory
        self.store = store
        self.name = name
        self.shape = tuple(array.shape)
        self.chunks = tuple(array.chunks)
        self.dtype = array.dtype
        self.fill = np.asarray(array.fill_value, dtype=self.dtype)
        self.chunk_bytes = int(np.prod(self.chunks)) * self.dtype.itemsize
        # Chunks along axis 0 only: a chunk is whole rows, contiguous in the result.
        self.row_chunks = self.chunks[1:] == self.shape[1:]
        self.compressed = any(
            isinstance(codec, zarr.codecs.ZstdCodec) for codec in array.metadata.codecs
        )

    @classmethod
    def of(cls, array: zarr.Array, store: Path, name: str) -> _RowReader | None:
        """The reader of ``array``, or None where zarr must read it."""
        if not _plain_chunk_files(array):
            return None
        return cls(array, array_directory(array), store, name)

    def read(self, start: int, stop: int, squeeze: bool) -> np.ndarray:
        out = np.empty((stop - start, *self.shape[1:]), dtype=self.dtype)
        if stop > start and out.size:
            step = self.chunks[0]
            others = [
                range(-(-s // c)) for s, c in zip(self.shape[1:], self.chunks[1:], strict=True)
            ]
            # One chunk after another on this thread. A pool paid 10-20% on larger
            # chunks only (2 shared cores, best of 7, the same CPU): 222 DAISY feature
            # chunks of 125 KB, what anyloc_vlad's stage reads, 35 ms here, 39 / 38 ms
            # on 2 / 3 threads; 100 of 326 KB 40-43 vs 34-38 ms; 64 of 4 MiB 333 vs
            # 305 / 270 ms (benchmarks/README.md, "Descriptors").
            for first in range(start // step, -(-stop // step)):
                for rest in itertools.product(*others):
                    self._chunk((first, *rest), out, start)
        return out.reshape(self.shape[1:]) if squeeze else out

    def _chunk(self, coords: tuple[int, ...], out: np.ndarray, start: int) -> None:
        """Decode chunk ``coords`` into ``out`` (rows ``start:`` of the array)."""
        # The chunk's part of the array, and of the result.
        region = tuple(
            slice(i * c, min((i + 1) * c, s))
            for i, c, s in zip(coords, self.chunks, self.shape, strict=True)
        )
        low = max(region[0].start, start)
        high = min(region[0].stop, start + len(out))
        into = out[(slice(low - start, high - start), *region[1:])]
        key = self.array.metadata.encode_chunk_key(coords)
        whole = self.row_chunks and high - low == self.chunks[0] and into.flags.c_contiguous
        target = into if whole else np.empty(self.chunks, dtype=self.dtype)
        target_bytes = target.reshape(-1).view(np.uint8)
        try:
            with open(self.directory / key, "rb", buffering=0) as file:
                read = not self.compressed and self._read_into(file, target_bytes, key)
                data = None if read else file.read()
        except FileNotFoundError:
            into[...] = self.fill
            return
        if data is not None:
            self._decode(data, target_bytes, key)
        if not whole:
            into[...] = target[
                (slice(low - region[0].start, high - region[0].start),)
                + tuple(slice(0, r.stop - r.start) for r in region[1:])
            ]

    def _read_into(self, file, target: np.ndarray, key: str) -> bool:
        """Read an uncompressed chunk file of the right size straight into ``target``
        (uint8, the chunk's size) and check its CRC there; False, having read nothing,
        where the file's size is not the chunk's and its checksum's (:meth:`_decode`
        says what is wrong). One copy of the bytes instead of two (into a ``bytes``,
        then into the result)."""
        if os.fstat(file.fileno()).st_size != self.chunk_bytes + 4:
            return False
        view, done = memoryview(target), 0
        while done < self.chunk_bytes and (got := file.readinto(view[done:])):
            done += got
        stored = file.read(4)
        computed = google_crc32c.value(target)
        if done != self.chunk_bytes or len(stored) != 4:
            raise self._corrupt(key, f"changed size while it was read ({done} bytes read)")
        if computed != int.from_bytes(stored, "little"):
            raise self._checksum_error(key, stored, computed)
        return True

    def _decode(self, data: bytes, target: np.ndarray, key: str) -> None:
        """Check and decompress (or copy) one chunk file's bytes into ``target`` (uint8,
        the chunk's size)."""
        if len(data) < 4:
            raise self._corrupt(key, f"has {len(data)} bytes, fewer than its checksum's 4")
        # A numpy view: google_crc32c takes it (not a memoryview), and it copies nothing.
        frame = np.frombuffer(data, dtype=np.uint8)[:-4]
        computed = google_crc32c.value(frame)
        if computed != int.from_bytes(data[-4:], "little"):
            raise self._checksum_error(key, data[-4:], computed)
        if not self.compressed:
            if len(frame) != self.chunk_bytes:
                raise self._corrupt(key, f"holds {len(frame)} bytes, not {self.chunk_bytes}")
            target[...] = frame
            return
        size = _content_size(data)
        if size is not None and size != self.chunk_bytes:
            raise self._corrupt(key, f"decompresses to {size} bytes, not {self.chunk_bytes}")
        try:
            if size is not None:
                numcodecs.zstd.decompress(frame, target)
                return
            # No size in the frame header (not written by numcodecs): decompress, then
            # check the size.
            plain = numcodecs.zstd.decompress(frame)
        except (RuntimeError, ValueError) as error:
            raise self._corrupt(key, f"cannot be decompressed ({_describe(error)})") from error
        if len(plain) != self.chunk_bytes:
            raise self._corrupt(key, f"decompresses to {len(plain)} bytes, not {self.chunk_bytes}")
        target[...] = np.frombuffer(plain, dtype=np.uint8)

    def _checksum_error(self, key: str, stored: bytes, computed: int) -> StoreCorruptError:
        stored_value = int.from_bytes(stored, "little")
        return self._corrupt(
            key,
            f"fails its checksum (stored {stored_value:#010x}, computed {computed:#010x})",
        )

    def _corrupt(self, key: str, fault: str) -> StoreCorruptError:
        return StoreCorruptError(
            self.store,
            f"array '{self.name}' cannot be decoded: chunk file {self.name}/{key} {fault}",
        )


def _content_size(frame: bytes) -> int | None:
    """The decompressed size a zstd frame's header states (RFC 8878 3.1.1.1), or None if
    it states none or ``frame`` is no zstd frame (then decompression says what is
    wrong). numcodecs decompresses into a larger buffer without complaint, so a chunk
    of the wrong size is caught here."""
    if len(frame) < 6 or frame[:4] != _ZSTD_MAGIC:
        return None
    descriptor = frame[4]
    single_segment = (descriptor >> 5) & 1
    width = (single_segment, 2, 4, 8)[descriptor >> 6]
    if width == 0:
        return None
    at = 5 + (not single_segment) + (0, 1, 2, 4)[descriptor & 3]
    field = frame[at : at + width]
    if len(field) < width:
        return None
    return int.from_bytes(field, "little") + (256 if width == 2 else 0)


def _describe(error: BaseException) -> str:
    return f"{type(error).__name__}: {error}"


def array_items(group: zarr.Group | CheckedGroup) -> list[tuple[str, zarr.Array | CheckedArray]]:
    """``(name, array)`` pairs of a group, sorted by name.

    Snakemake drops a ``.snakemake_timestamp`` file into directory outputs; zarr
    warns about it when listing, which is noise here.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*snakemake_timestamp")
        return sorted(group.arrays())


class NonFiniteError(ValueError):
    """A stage was about to store NaN or infinity; the message names stage and array."""


def check_finite(group: zarr.Group, name: str, data: np.ndarray, first_row: int = 0) -> None:
    """Refuse to store NaN/inf: no stage has a legitimate use for them, and a NaN
    descriptor would still be retrieved and counted in a believable table."""
    data = np.asarray(data)
    if data.dtype.kind not in "fc" or data.size == 0:
        return
    finite = np.isfinite(data)
    if finite.all():
        return
    bad_rows = np.unique(np.nonzero(~finite)[0]) + first_row if data.ndim else np.array([0])
    stage = group.attrs.get("stage", "?")
    hint = ""
    if data.dtype == np.float16:
        hint = " (float16 overflows beyond 65504: set the backbone's store_dtype: float32)"
    raise NonFiniteError(
        f"stage '{stage}': array '{name}' would hold {int((~finite).sum())} NaN/inf values "
        f"(rows {bad_rows[:5].tolist()}){hint}; nothing was written"
    )


def write_array(group: zarr.Group, name: str, data: np.ndarray, chunks=None) -> zarr.Array:
    """Write a whole numpy array (numeric or string) into ``group[name]``; NaN/inf is
    an error (:class:`NonFiniteError`)."""
    data = np.asarray(data)
    check_finite(group, name, data)
    if data.dtype.kind in "UOT":
        # dtype=str is zarr 3's variable-length string type (fixed-width unicode has no
        # stable v3 spec).
        strings = group.create_array(
            name,
            shape=data.shape,
            dtype=str,
            chunks=(max(1, len(data)),),
            compressors=COMPRESSORS,
        )
        if data.size:
            strings[...] = data.astype(str)
        return strings
    if data.size == 0:
        # zarr cannot infer chunks from an empty array
        chunks = chunks or tuple(max(1, s) for s in data.shape)
    return group.create_array(name, data=data, chunks=chunks or "auto", compressors=COMPRESSORS)


def read_strings(group: CheckedGroup, name: str) -> list[str]:
    return [str(s) for s in np.asarray(group[name][...]).tolist()]


def rows_per_chunk(row_bytes: int) -> int:
    """Rows in a chunk of about 4 MiB (at least one)."""
    return max(1, (1 << 22) // max(row_bytes, 1))


# RowWriter stores whole chunks of about this many bytes at a time (at least one chunk).
# What is stored is the same: the chunks do not change. A write per 4 MiB chunk made
# SegVLAD's descriptors stage 8% slower (more hand-overs between the two threads).
WRITE_BYTES = 16 << 20


def _cannot_be_empty(array: zarr.Array, rows: np.ndarray) -> bool:
    """Whether ``rows``, all that is written to one chunk of ``array`` (chunked along its
    first axis only), has a nonzero byte, and so cannot leave the chunk equal to a fill
    value of zero bytes.

    zarr does not store a chunk equal to the fill value (``write_empty_chunks=False``)
    and finds out with a comparison over the whole chunk (``NDBuffer.all_equal``, a
    void-dtype ``array_equal``): 23% of a descriptors write's CPU (benchmarks/README.md,
    "Stores: the checksums' cost"). When this is True that comparison can only answer
    "not empty", so :func:`store_rows` skips it and the chunk file is the same. For
    booleans and integers zarr compares values and for floats bit patterns (-0.0 is not
    empty), both of which are the bytes; other dtypes (complex: -0.0 equals 0) answer
    False, and zarr's own comparison runs.
    """
    dtype = array.dtype
    if (
        rows.size == 0
        or not isinstance(dtype, np.dtype)
        or dtype.kind not in "biuf"
        or np.asarray(array.fill_value, dtype=dtype).tobytes() != bytes(dtype.itemsize)
    ):
        return False
    flat = np.ascontiguousarray(rows).reshape(len(rows), -1).view(np.uint8)
    # The first row nearly always decides; a zero row costs a scan of the rest.
    return bool(flat[0].any() or flat.any())


def store_rows(array: zarr.Array, rows: np.ndarray, start: int | None = None) -> None:
    """Append ``rows`` to ``array`` (chunked along its first axis only) as
    ``array.append(rows)`` would, with the same chunk files: one write per chunk, one
    after another. Where :func:`_cannot_be_empty` shows a chunk cannot equal the fill
    value (which zarr would not store), its file is written by :func:`_write_chunk` if
    vprflow writes the array's chunk files (:func:`_plain_chunk_files`) and the chunk
    is new, else by zarr without its empty-chunk comparison; otherwise by zarr.

    With ``start`` (the first row's index, at or past the array's recorded length)
    the array is resized only where zarr writes a chunk (zarr writes within the
    shape), and the caller resizes it once at the end (:class:`RowWriter`): a resize
    rewrites ``zarr.json`` through zarr's event loop, about 1 ms, and resizing once a
    write made SegVLAD's descriptors stage 7% slower (2,048 DAISY images).

    Not zarr's own write where it can be helped: its Python work per chunk (an event
    loop, buffers, codec pipeline) holds the GIL beside a stage's computing thread, and
    took SegVLAD's descriptors stage from 0.70 to 0.83 ms an image (2,048 DAISY images,
    ~400 KB of rows each). One chunk at a time: RowWriter calls this on its background
    thread while the stage computes on another, and 4 chunks compressed at once took
    the cores from it (the same stage 0.72 against 0.65 ms an image), though they write
    a store alone faster (266 MB of sparse rows 0.29 against 0.46 s)."""
    if tuple(array.chunks[1:]) != tuple(array.shape[1:]):
        raise ValueError(
            f"store_rows: array {array.store_path} has chunks {array.chunks} for shape "
            f"{array.shape}: it writes arrays chunked along their first axis only"
        )
    if len(rows) == 0:
        return
    appending = start is None
    start, step = array.shape[0] if appending else start, array.chunks[0]
    stop = start + len(rows)
    if appending:
        array.resize((stop, *array.shape[1:]))
    plain = _plain_chunk_files(array)

    def store(first: int) -> None:
        last = min(first - first % step + step, stop)
        part = rows[first - start : last - start]
        cannot_be_empty = _cannot_be_empty(array, part)
        if cannot_be_empty and plain and first % step == 0:
            _write_chunk(array, first // step, part)
            return
        if array.shape[0] < stop:
            array.resize((stop, *array.shape[1:]))
        if cannot_be_empty:
            # A runtime setting, not stored: zarr.json is the same either way.
            array.with_config({"write_empty_chunks": True})[first:last] = part
        else:
            array[first:last] = part

    for first in [start, *range(start - start % step + step, stop, step)]:
        store(first)


def _split_rows(parts: list[np.ndarray], count: int) -> tuple[list, list]:
    """``parts`` split after their first ``count`` rows (counted along the first axis
    across the arrays in order): ``(head, tail)``, an array that straddles the split
    divided into two views."""
    head, tail, taken = [], [], 0
    for part in parts:
        cut = min(len(part), count - taken)  # 0 once the head is full
        if cut:
            head.append(part[:cut])
        if cut < len(part):
            tail.append(part[cut:])
        taken += cut
    return head, tail


def _store_parts(array: zarr.Array, parts: list[np.ndarray], start: int) -> None:
    """:func:`store_rows` of the arrays ``parts`` joined along their first axis."""
    store_rows(array, parts[0] if len(parts) == 1 else np.concatenate(parts, axis=0), start)


class RowWriter:
    """Append rows ``[n, *row_shape]`` to ``group[name]``, buffered and written in whole
    chunks, so appending one image at a time does not recompress a chunk per image
    (nor a partly filled chunk once per flush); about :data:`WRITE_BYTES` a write.

    Each write (joining the appended arrays into chunks, compressing, writing files)
    runs on a background thread while the caller computes the next rows; one write at
    a time, in order. :meth:`close` waits for the last and re-raises a failed write.
    The rows appended are kept, not copied, until written: a caller must not change an
    array after appending it (the stages append arrays they made for it). Joining
    them on the caller's thread was 0.045 ms of SegVLAD's 0.34 ms of arithmetic an
    image (a copy of 400 KB). ``compressors``: :data:`COMPRESSORS` or
    :data:`FAST_COMPRESSORS`; ``chunk_key_encoding``: zarr's default (None) or
    :data:`FLAT_CHUNK_KEYS`.
    """

    def __init__(
        self,
        group: zarr.Group,
        name: str,
        row_shape: tuple,
        dtype,
        chunk_rows: int,
        compressors: tuple = COMPRESSORS,
        chunk_key_encoding: dict | None = None,
    ):
        self.array = group.create_array(
            name,
            shape=(0, *row_shape),
            chunks=(chunk_rows, *row_shape),
            dtype=dtype,
            compressors=compressors,
            chunk_key_encoding=chunk_key_encoding,
        )
        self.group = group
        self.name = name
        self.chunk_rows = chunk_rows
        row_bytes = np.dtype(dtype).itemsize * int(np.prod(row_shape))
        self.write_rows = chunk_rows * max(1, WRITE_BYTES // max(chunk_rows * row_bytes, 1))
        self.buffer: list[np.ndarray] = []
        self.buffered = 0
        self.written = 0
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"write-{name}")
        self._pending: Future | None = None

    def append(self, rows: np.ndarray, what: str | None = None) -> None:
        """``what`` names the rows in a NaN/inf error (default: the array and row)."""
        rows = np.asarray(rows, dtype=self.array.dtype)
        check_finite(self.group, what or self.name, rows, first_row=self.written + self.buffered)
        self.buffer.append(rows)
        self.buffered += len(rows)
        if self.buffered >= self.write_rows:
            self._flush(whole_chunks=True)

    def skip(self, count: int) -> None:
        """Leave the next ``count`` rows to the caller, who puts their chunk files in
        place itself (:func:`vprflow.core.reuse.link_chunk`): the rows appended so far
        are written, and appending goes on after the gap. Whole chunks only."""
        if count and (self.buffered % self.chunk_rows or count % self.chunk_rows):
            raise ValueError(f"RowWriter.skip: {count} rows after {self.buffered} buffered")
        if count:
            self._flush()
            self.written += count

    def _flush(self, whole_chunks: bool = False) -> None:
        """Write the buffered rows; with ``whole_chunks``, only as many as fill whole
        chunks (the rest stay buffered)."""
        count = self.buffered - self.buffered % self.chunk_rows if whole_chunks else self.buffered
        if count == 0:
            return
        parts, self.buffer = _split_rows(self.buffer, count)
        self._wait()
        self._pending = self._executor.submit(_store_parts, self.array, parts, self.written)
        _PENDING_WRITES.add(self._pending)
        self.written += count
        self.buffered -= count

    def _wait(self) -> None:
        if self._pending is not None:
            pending, self._pending = self._pending, None
            _PENDING_WRITES.discard(pending)
            pending.result()

    def close(self) -> None:
        try:
            self._flush()
            self._wait()
        finally:
            self._executor.shutdown()
        if self.array.shape[0] != self.written:  # store_rows left the length to us
            self.array.resize((self.written, *self.array.shape[1:]))


class RaggedWriter(RowWriter):
    """Append per-image blocks of rows ``[n_i, *row_shape]`` into one concatenated array,
    with ``<name>_offsets [n + 1]`` written on :meth:`close`."""

    def __init__(self, *args, **kwargs):  # RowWriter's
        super().__init__(*args, **kwargs)
        self.offsets = [0]

    def append(self, rows: np.ndarray, what: str | None = None) -> None:
        """One image's rows."""
        super().append(rows, what)
        self.offsets.append(self.offsets[-1] + len(rows))

    def append_rows(self, rows: np.ndarray, what: str | None = None) -> None:
        """Rows of images :meth:`add_images` records, appended in parts that need not
        end where an image does (and whole chunks :meth:`skip` leaves to the caller)."""
        super().append(rows, what)

    def add_images(self, lengths: np.ndarray) -> None:
        """Record images of ``lengths`` rows each, put in place by :meth:`append_rows`
        and :meth:`skip`."""
        self.offsets.extend((self.offsets[-1] + np.cumsum(lengths, dtype=np.int64)).tolist())

    def close(self) -> np.ndarray:
        """Flush and write ``<name>_offsets``; returns the offsets ``[n + 1]``."""
        super().close()
        offsets = np.asarray(self.offsets, dtype=np.int64)
        write_array(self.group, f"{self.name}_offsets", offsets)
        return offsets


class RaggedReader:
    """``reader(index) -> rows [n_i, ...]`` of a ragged array, reading the offsets once
    and about ``block_bytes`` of rows per store access (a stage walks images in order;
    per-image store reads cost more than the arithmetic on small images)."""

    def __init__(self, group: CheckedGroup, name: str, block_bytes: int = 64 << 20):
        self.array = group[name]
        self.offsets = np.asarray(group[f"{name}_offsets"][...])
        row_bytes = self.array.dtype.itemsize * int(np.prod(self.array.shape[1:]))
        self.block_rows = max(1, block_bytes // max(row_bytes, 1))
        self.start, self.rows = 0, self.array[0:0]

    def __call__(self, index: int) -> np.ndarray:
        low, high = int(self.offsets[index]), int(self.offsets[index + 1])
        if not (self.start <= low and high <= self.start + len(self.rows)):
            # Whole images from `index` on, at least this one, up to about block_bytes.
            last = np.searchsorted(self.offsets, low + self.block_rows, side="right") - 1
            stop = int(self.offsets[max(last, index + 1)])
            self.start, self.rows = low, np.asarray(self.array[low:stop])
        return self.rows[low - self.start : high - self.start].copy()


def pack_masks(masks: np.ndarray) -> np.ndarray:
    """bool ``[S, H, W]`` -> uint8 ``[S, ceil(H * W / 8)]`` (row-major bits)."""
    masks = np.asarray(masks, dtype=bool)
    # Explicit row length: reshape(0, -1) is ambiguous for an image with no masks.
    return np.packbits(masks.reshape(len(masks), masks.shape[1] * masks.shape[2]), axis=1)


def unpack_masks(packed: np.ndarray, height: int, width: int) -> np.ndarray:
    """Inverse of :func:`pack_masks`: uint8 ``[S, B]`` -> bool ``[S, height, width]``."""
    bits = np.unpackbits(np.asarray(packed, dtype=np.uint8), axis=1, count=height * width)
    return bits.reshape(len(packed), height, width).astype(bool)

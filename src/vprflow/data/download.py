"""Public datasets on demand: fetch an archive, verify it, lay out the dataset folder.

A dataset's ``download`` entry (``config/README.md``, ``dataset.download``) names an
archive (``url``: ``http(s)://`` or ``file://``, a zip or a tar, compressed or not), its
``sha256``, how many leading folders of each member to drop (``strip``), which archive
sub-paths become which dataset sub-paths (``layout``) and, optionally, a ``manifest``
of the laid-out files' SHA-256 (``sha256sum`` format: ``<hex>  <dataset path>``).

:func:`download_dataset` works in a temporary folder next to the dataset folder and
renames the finished folder into place only after every check passed, so an
interrupted or failed download never leaves a complete-looking dataset folder:

1. fetch the URL to a temporary file (tqdm progress), hashing it on the way;
2. compare with ``sha256`` when given (a mismatch names the URL and both hashes);
   without one the computed hash is recorded and a warning says to pin it;
3. list the archive and refuse it before anything is written if any member is an
   absolute path or contains ``..``, if two members would be laid out at one path or
   one member is a file where another needs a folder, or if the files to lay out
   unpack to more than the file system can take (its free space less a reserve);
4. write each member under a ``layout`` sub-path to its dataset path (regular files
   only; a link there is an error), hashing it and counting its bytes against its
   header; with a manifest only the listed files are written, each must be in the
   archive and match its hash;
5. rename the folder into place; the caller writes the record (:func:`write_record`).

A truncated or damaged archive (a cut-off transfer, a broken file behind a ``file://``
URL) is a :class:`DownloadError` naming the URL, the archive file and what to do, as is
a disk that fills up anyway. A dataset folder that already exists is left alone:
nothing is fetched. Two runs downloading the same dataset at once (``--nolock``) each
work in their own temporary folder; the first to finish lays the folder out and the
other keeps it.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import lzma
import os
import re
import shutil
import sys
import tarfile
import tempfile
import urllib.error
import urllib.request
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path, PurePosixPath, PureWindowsPath

from vprflow.core.files import TAG, is_abandoned, write_text_atomic, writer_tag
from vprflow.core.lazy import lazy_import
from vprflow.core.paths import dataset_folder

tqdm = lazy_import("tqdm")

log = logging.getLogger("vprflow")

CHUNK = 1 << 20
# Unpacking stops short of filling the disk: this much of the file system (5% of it, at
# most RESERVE_MAX) stays free after a dataset is laid out.
RESERVE_FRACTION = 0.05
RESERVE_MAX = 1 << 30
# What a damaged archive raises while it is listed or read: gzip, bz2 and xz streams cut
# short (EOFError), bad CRCs and headers (tarfile, zipfile, zlib, lzma). gzip's and bz2's
# own errors are OSErrors without an errno, told apart from a file system's below.
ARCHIVE_ERRORS = (EOFError, tarfile.TarError, zipfile.BadZipFile, zlib.error, lzma.LZMAError)
# The first bytes of the archive formats read here, to tell a damaged archive from a
# file that is none (an HTML page in place of the archive).
MAGIC = {
    b"PK\x03\x04": "zip",
    b"\x1f\x8b": "gzip",
    b"BZh": "bzip2",
    b"\xfd7zXZ\x00": "xz",
}


class DownloadError(RuntimeError):
    """A failed download; the message names the URL, member or file at fault."""


def requested_datasets(config: dict, targets) -> list[str]:
    """The datasets a ``snakemake`` command's targets ask for: those its ``results/...``
    targets name, or, without such a target, the config's ``targets``."""
    targets = [t for t in targets if t.startswith("results/")]
    if not targets:
        return list(config["targets"])
    named = []
    for name in config["datasets"]:
        token = re.compile(rf"(^|[/_]){re.escape(name)}([/.]|$)")
        if any(token.search(t) for t in targets):
            named.append(name)
    return named


def awaiting_download(config: dict) -> list[str]:
    """The datasets with a ``download`` entry (the shipped samples; presets have none
    and stay manual) whose folder under ``data_root`` is missing: the ``download``
    checkpoint lays them out before their stores are planned."""
    return [
        name
        for name, entry in config["datasets"].items()
        if "download" in entry and not dataset_folder(config["data_root"], entry).is_dir()
    ]


def download_entry(config: dict, name: str) -> dict:
    """Dataset ``name``'s ``download`` entry (the rule's params); a dataset that is not
    configured, or has none, is an error saying where to get it instead."""
    if name not in config["datasets"]:
        raise DownloadError(f"unknown dataset {name!r}; configured: {sorted(config['datasets'])}")
    entry = config["datasets"][name]
    if "download" not in entry:
        where = f" Get it from {entry['source']}." if entry.get("source") else ""
        raise DownloadError(
            f"dataset {name!r} has no `download` entry: no public archive can be fetched "
            f"for it.{where}"
        )
    return entry["download"]


def manifest_inputs(config: dict, name: str, workflow_dir: str | Path) -> list[str]:
    """The rule's input: the entry's manifest, if any (relative paths under ``workflow/``)."""
    manifest = download_entry(config, name).get("manifest")
    return [str(Path(workflow_dir) / manifest)] if manifest else []


# ------------------------------------------------------------------ disk space


def size_text(n: int) -> str:
    """``n`` bytes for a message: ``1.5 GB (1500000000 bytes)``."""
    value, unit = float(n), "bytes"
    for unit in ("bytes", "kB", "MB", "GB", "TB"):
        if value < 1000 or unit == "TB":
            break
        value /= 1000
    return f"{n} bytes" if unit == "bytes" else f"{value:.1f} {unit} ({n} bytes)"


def space_limit(path: str | Path, keep_free: bool = True) -> tuple[int, str]:
    """How many bytes may still be written under ``path`` (its nearest existing
    folder's file system: the free space, less a reserve of ``RESERVE_FRACTION`` of the
    file system, at most ``RESERVE_MAX``, with ``keep_free``), and a sentence saying so
    for messages."""
    probe = Path(path).absolute()
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    usage = shutil.disk_usage(probe)
    free = f"{size_text(usage.free)} free on the file system of {probe}"
    if not keep_free:
        return usage.free, free
    reserve = min(RESERVE_MAX, int(usage.total * RESERVE_FRACTION))
    return max(0, usage.free - reserve), f"{free}, less {size_text(reserve)} kept free"


def _no_space(error: OSError) -> bool:
    return error.errno in (errno.ENOSPC, errno.EDQUOT)


# ------------------------------------------------------------------ fetching


def fetch(url: str, dest: str | Path, timeout: float = 60.0) -> str:
    """Stream ``url`` into ``dest`` with a progress bar; return the SHA-256 of the bytes.

    HTTP errors, unreachable hosts and truncated transfers raise :class:`DownloadError`
    naming the URL, as do an announced size larger than the file system can take
    (:func:`space_limit`, checked before any byte is written) and a disk that fills up.
    """
    request = urllib.request.Request(url, headers={"User-Agent": "vprflow"})
    digest = hashlib.sha256()
    received = 0
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            length = response.headers.get("Content-Length")
            total = int(length) if length and length.isdigit() else None
            if total is not None:
                # The reserve is kept when unpacking; here the file must merely fit.
                limit, why = space_limit(dest, keep_free=False)
                if total > limit:
                    raise DownloadError(
                        f"download of {url} is {size_text(total)}, more than the file "
                        f"system can take: {why}. Free space there or point data_root at "
                        "a larger disk"
                    )
            with (
                open(dest, "wb") as out,
                tqdm.tqdm(
                    total=total,
                    unit="B",
                    unit_scale=True,
                    desc=f"downloading {url}",
                    file=sys.stderr,
                    mininterval=5.0,
                ) as bar,
            ):
                while chunk := response.read(CHUNK):
                    out.write(chunk)
                    digest.update(chunk)
                    received += len(chunk)
                    bar.update(len(chunk))
    except urllib.error.HTTPError as error:
        raise DownloadError(f"download of {url} failed: HTTP {error.code} {error.reason}") from None
    except urllib.error.URLError as error:
        raise DownloadError(f"cannot download {url}: {error.reason} (no network?)") from None
    except (TimeoutError, ConnectionError) as error:
        raise DownloadError(
            f"download of {url} broke off after {received} bytes: {error}"
        ) from None
    except OSError as error:
        if not _no_space(error):
            raise
        raise DownloadError(
            f"download of {url}: the disk filled up after {size_text(received)} written to "
            f"{dest} ({error.strerror}). Free space there or point data_root at a larger disk"
        ) from None
    if total is not None and received != total:
        raise DownloadError(
            f"download of {url} is incomplete: {received} of {total} bytes announced"
        )
    return digest.hexdigest()


def verify_sha256(what: str, expected: str, actual: str) -> None:
    """Raise naming ``what`` (a URL or file) and both hashes unless they agree."""
    if expected.lower() != actual.lower():
        raise DownloadError(
            f"checksum mismatch for {what}: expected sha256 {expected.lower()}, got {actual}"
        )


# ------------------------------------------------------------------ archives


def safe_relative(name: str, what: str) -> PurePosixPath:
    """``name`` as a relative POSIX path; an absolute path, a drive, a backslash path
    or any ``..`` part is refused (path traversal). ``.`` parts are dropped."""
    unsafe = (
        name.startswith(("/", "\\"))
        or PureWindowsPath(name).drive
        or ".." in name.replace("\\", "/").split("/")
    )
    if unsafe:
        raise DownloadError(
            f"{what}: {name!r} is an absolute path or leaves its folder ('..'); refusing it"
        )
    return PurePosixPath(*[p for p in name.split("/") if p not in ("", ".")])


class _Member:
    """One archive entry: its name, whether it is a regular file or a folder, the size
    its header declares, and how to read it."""

    def __init__(self, name: str, is_file: bool, is_dir: bool, size: int, open_):
        self.name, self.is_file, self.is_dir, self.size = name, is_file, is_dir, size
        self.open = open_


def damaged(url: str, path: str | Path, detail: str) -> DownloadError:
    """The error for an archive that cannot be read to its end: names the URL, the
    archive file and what to do."""
    return DownloadError(
        f"archive {url} is truncated or damaged ({detail}, in {path}). If the "
        "transfer was cut short, run the download again to fetch it anew; if this error "
        f"recurs, the archive at {url} itself is damaged: replace it (a file:// URL: "
        "delete that file and copy it again)"
    )


@contextmanager
def reading(url: str, path: str | Path) -> Iterator[None]:
    """Turn what a damaged archive raises inside the block into :func:`damaged`."""
    try:
        yield
    except ARCHIVE_ERRORS as error:
        raise damaged(url, path, f"{type(error).__name__}: {error}") from None
    except OSError as error:
        if error.errno is not None:  # the file system's, not the archive's
            raise
        raise damaged(url, path, f"{type(error).__name__}: {error}") from None


def _magic(path: Path) -> str | None:
    """The archive or compression format ``path`` starts like, if any."""
    with open(path, "rb") as file:
        head = file.read(8)
    return next((kind for magic, kind in MAGIC.items() if head.startswith(magic)), None)


def archive_members(path: str | Path, url: str) -> Iterator[_Member]:
    """Entries of a zip or tar (any compression tarfile reads), in archive order. A file
    that starts like an archive but cannot be opened is :func:`damaged`; one that does
    not is not an archive. Iterate inside :func:`reading`."""
    path = Path(path)
    if zipfile.is_zipfile(path):
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                mode = info.external_attr >> 16
                is_link = (mode & 0o170000) == 0o120000
                yield _Member(
                    info.filename,
                    not info.is_dir() and not is_link,
                    info.is_dir(),
                    info.file_size,
                    lambda info=info, archive=archive: archive.open(info),
                )
        return
    try:
        archive = tarfile.open(path, "r:*")
    except ARCHIVE_ERRORS as error:
        kind = _magic(path)
        if kind == "zip":
            raise damaged(url, path, "a zip archive without its central directory") from None
        if kind is not None:
            raise damaged(url, path, f"{kind} data: {error}") from None
        raise DownloadError(f"{url} is not a zip or tar archive") from None
    with archive:
        for info in archive:
            yield _Member(
                info.name,
                info.isfile(),
                info.isdir(),
                info.size,
                lambda info=info, archive=archive: archive.extractfile(info),
            )


def _target(name: PurePosixPath, strip: int, layout: dict[PurePosixPath, PurePosixPath]):
    """The dataset path of an archive member, or None when no layout entry covers it."""
    if len(name.parts) <= strip:
        return None
    inner = PurePosixPath(*name.parts[strip:])
    for source, dest in layout.items():
        if inner == source:
            return dest, source
        if inner.parts[: len(source.parts)] == source.parts:
            return dest.joinpath(*inner.parts[len(source.parts) :]), source
    return None


def read_manifest(path: str | Path) -> dict[str, str]:
    """``{dataset path: sha256}`` from ``<hex>  <path>`` lines (``#`` starts a comment)."""
    manifest = {}
    for number, line in enumerate(Path(path).read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        digest, _, name = line.partition(" ")
        name = name.strip().lstrip("*")
        if len(digest) != 64 or not name:
            raise DownloadError(f"{path} line {number}: expected '<sha256>  <path>', got {line!r}")
        manifest[str(safe_relative(name, f"{path} line {number}"))] = digest.lower()
    if not manifest:
        raise DownloadError(f"manifest {path} lists no files")
    return manifest


def extract_layout(
    archive: str | Path,
    url: str,
    layout: dict[str, str],
    dest: str | Path,
    strip: int = 0,
    manifest: dict[str, str] | None = None,
    max_bytes: int | None = None,
) -> dict[str, str]:
    """Write the archive members that ``layout`` maps into ``dest``; return
    ``{dataset path: sha256}`` of the written files.

    The archive is listed first and refused, before anything is written, when any
    member name is unsafe (absolute, ``..``), when two members would be laid out at one
    path or one would be a file where another needs a folder, when a layout path or a
    manifest file is missing, or when the files to write declare more bytes than
    ``max_bytes`` (default: what :func:`space_limit` allows under ``dest``). Writing
    counts each member's bytes against its header. With ``manifest``, only its files
    are written (others under a layout path are skipped and counted in the log), each
    must match its hash. A truncated or damaged archive is :func:`damaged`.
    """
    dest = Path(dest)
    where = "config key download.layout"
    mapping = {
        safe_relative(str(k), where): safe_relative(str(v), where) for k, v in layout.items()
    }
    if not mapping or any(not k.parts for k in mapping):
        raise DownloadError(f"{where} must map archive sub-paths (not the archive root) to folders")
    with reading(url, archive):
        listing = [(m.name, m.is_file, m.is_dir, m.size) for m in archive_members(archive, url)]
    for name, *_ in listing:
        safe_relative(name, f"archive {url}, member")
    plan, total = _plan_layout(listing, url, strip, mapping, manifest)
    if max_bytes is None:
        max_bytes, why = space_limit(dest)
    else:
        why = f"the limit given is {size_text(max_bytes)}"
    if total > max_bytes:
        raise DownloadError(
            f"archive {url}: the {len(plan)} file(s) to lay out unpack to "
            f"{size_text(total)}, more than the file system can take ({why}); nothing was "
            "unpacked. Free space there or point data_root at a larger disk"
        )
    written: dict[str, str] = {}
    with reading(url, archive):
        for index, member in enumerate(archive_members(archive, url)):
            if index in plan:
                key = plan[index].as_posix()
                written[key] = _write_member(member, dest / plan[index], url)
                if manifest is not None:
                    what = f"{key} (member {member.name!r} of {url})"
                    verify_sha256(what, manifest[key], written[key])
    if len(written) != len(plan):  # the second reading disagrees with the first
        raise damaged(url, archive, "its members changed between two readings")
    return dict(sorted(written.items()))


def _plan_layout(
    listing: list[tuple[str, bool, bool, int]],
    url: str,
    strip: int,
    mapping: dict[PurePosixPath, PurePosixPath],
    manifest: dict[str, str] | None,
) -> tuple[dict[int, PurePosixPath], int]:
    """``({member index: dataset path}, declared bytes)`` of the files to write, after
    checking the listing: no links under the layout, no two members at one path, no
    member both a file and a folder, every layout path and manifest file present."""
    files: dict[PurePosixPath, tuple[int, str]] = {}
    folders: dict[PurePosixPath, str] = {}
    used: set[PurePosixPath] = set()
    skipped: list[str] = []
    total = 0
    for index, (name, is_file, is_dir, size) in enumerate(listing):
        found = _target(safe_relative(name, url), strip, mapping)
        if found is None:
            continue
        target, source = found
        used.add(source)
        if is_dir:
            folders.setdefault(target, name)
            continue
        key = target.as_posix()
        if not is_file:
            raise DownloadError(
                f"archive {url}: member {name!r} is a link or special file; refusing it"
            )
        if manifest is not None and key not in manifest:
            skipped.append(key)
            continue
        if target in files:
            raise DownloadError(
                f"archive {url}: two members are laid out at {key}: "
                f"{files[target][1]!r} and {name!r}; refusing the archive"
            )
        files[target] = (index, name)
        total += size
    for target, (_, name) in files.items():
        for parent in target.parents:
            if parent in files:
                raise DownloadError(
                    f"archive {url}: member {files[parent][1]!r} is a file at "
                    f"{parent.as_posix()}, where member {name!r} needs a folder; the "
                    "archive holds both, so it cannot be laid out; refusing it"
                )
        if target in folders:
            raise DownloadError(
                f"archive {url}: member {folders[target]!r} is a folder at "
                f"{target.as_posix()}, where member {name!r} is a file; the archive holds "
                "both, so it cannot be laid out; refusing it"
            )
    unused = [k.as_posix() for k in mapping if k not in used]
    if unused:
        names = [n for n, *_ in listing]
        tops = sorted(
            {PurePosixPath(*PurePosixPath(n).parts[: strip + 1]).as_posix() for n in names}
        )
        raise DownloadError(
            f"archive {url} has no member {unused} (after stripping {strip} leading "
            f"folder(s)); its top-level entries: {tops[:10]}"
        )
    if manifest is not None:
        missing = sorted(set(manifest) - {t.as_posix() for t in files})
        if missing:
            raise DownloadError(
                f"archive {url} lacks {len(missing)} file(s) of the manifest, e.g. {missing[:5]}"
            )
    if skipped:
        log.info("skipped %d file(s) not in the manifest, e.g. %s", len(skipped), skipped[:5])
    if not files:
        raise DownloadError(f"archive {url}: the layout selects no files")
    return {index: target for target, (index, _) in files.items()}, total


def _write_member(member: _Member, path: Path, url: str) -> str:
    """Write one member to ``path``, no more bytes than its header declares; return its
    SHA-256."""
    digest = hashlib.sha256()
    count = 0
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with member.open() as src, open(path, "wb") as out:
            while chunk := src.read(CHUNK):
                count += len(chunk)
                if count > member.size:
                    raise DownloadError(
                        f"archive {url}: member {member.name!r} unpacks to more than the "
                        f"{member.size} bytes its header declares; refusing the archive"
                    )
                out.write(chunk)
                digest.update(chunk)
    except (FileExistsError, IsADirectoryError, NotADirectoryError) as error:
        raise DownloadError(
            f"archive {url}: member {member.name!r} cannot be written at {path}: "
            f"{error.strerror} ({error.filename}); another member is a file where this one "
            "needs a folder, or the other way round (on a case-insensitive file system, "
            "two names that differ only in case)"
        ) from None
    except OSError as error:
        if not _no_space(error):
            raise
        raise DownloadError(
            f"archive {url}: the disk filled up while unpacking member {member.name!r} "
            f"to {path} ({error.strerror}). Free space there or point data_root at a "
            "larger disk"
        ) from None
    return digest.hexdigest()


# ------------------------------------------------------------------ the dataset


def download_dataset(
    name: str, entry: dict, folder: str | Path, manifest_path: str | Path | None = None
) -> dict:
    """Fetch and lay out dataset ``name`` at ``folder`` unless it exists; return the record.

    ``entry``: ``url``, optional ``sha256`` (of the archive), ``layout``, ``strip``.
    ``manifest_path``: optional per-file SHA-256 list (see :func:`read_manifest`).
    """
    folder = Path(folder)
    url = entry["url"]
    record = {
        "dataset": name,
        "url": url,
        "folder": str(folder),
        "manifest": str(manifest_path) if manifest_path else None,
    }
    if folder.exists():
        log.info("%s already exists: nothing downloaded (remove it to download again)", folder)
        return {**record, "downloaded": False}
    manifest = read_manifest(manifest_path) if manifest_path else None
    folder.parent.mkdir(parents=True, exist_ok=True)
    prefix = f".{folder.name}.download-"
    remove_abandoned_work(folder.parent, prefix)
    # The writer tag tells this run's folder from a concurrent run's (--nolock).
    work = Path(tempfile.mkdtemp(prefix=f"{prefix}{writer_tag()}-", dir=folder.parent))
    try:
        archive = work / "archive"
        log.info("dataset %s: downloading %s", name, url)
        actual = fetch(url, archive)
        size = archive.stat().st_size
        pinned = entry.get("sha256")
        if pinned:
            verify_sha256(url, pinned, actual)
        else:
            log.warning(
                "dataset %s: no sha256 configured for %s; downloaded %d bytes with sha256 %s. "
                "Pin it with datasets.%s.download.sha256: %s",
                name,
                url,
                size,
                actual,
                name,
                actual,
            )
        staged = work / "data"
        staged.mkdir()
        files = extract_layout(archive, url, entry["layout"], staged, int(entry["strip"]), manifest)
        archive.unlink()
        _move_into_place(staged, folder)
    except DownloadError as error:
        # The console shows this line: name the dataset and what to do, not only the URL.
        raise DownloadError(
            f"dataset {name!r}: {error}. Nothing was laid out at {folder}, and the fetched "
            f"archive was deleted. Run this target again once the cause is fixed, or put "
            f"the dataset at {folder} yourself (or run with --config data_root=<folder "
            "holding it>)"
        ) from None
    finally:
        shutil.rmtree(work, ignore_errors=True)
    log.info("dataset %s: %d files laid out in %s", name, len(files), folder)
    return {
        **record,
        "downloaded": True,
        "sha256": actual,
        "sha256_pinned": bool(pinned),
        "bytes": size,
        "n_files": len(files),
        "files": files,
    }


def remove_abandoned_work(parent: Path, prefix: str) -> None:
    """Delete the temporary folders ``<prefix><writer tag>-*`` in ``parent`` that no live
    download owns (an interrupted one's, or one from before writer tags); a concurrent
    run's is left alone, with a warning."""
    pattern = re.compile(re.escape(prefix) + TAG + "-.+")
    for leftover in sorted(parent.glob(prefix + "*")):
        match = pattern.fullmatch(leftover.name)
        if match is None or is_abandoned(leftover, match["host"], int(match["pid"])):
            log.info("removing %s, left by an interrupted download", leftover)
            shutil.rmtree(leftover, ignore_errors=True)
        else:
            log.warning(
                "%s: process %s on %s is downloading the same dataset at this moment (two "
                "runs with --nolock?); whichever finishes first lays it out",
                leftover,
                match["pid"],
                match["host"],
            )


def _move_into_place(staged: Path, folder: Path) -> None:
    """Rename the finished dataset folder into place; if another run laid the folder
    out meanwhile (--nolock), keep that one."""
    try:
        os.replace(staged, folder)
    except OSError as error:
        if error.errno not in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOTDIR):
            raise
        log.warning(
            "%s appeared while this run downloaded it (another run with --nolock?): "
            "keeping it, discarding this run's copy",
            folder,
        )


def write_record(record: dict, path: str | Path) -> None:
    """Write the record as JSON, atomically (temporary file, then rename)."""
    write_text_atomic(path, json.dumps(record, indent=1, sort_keys=True) + "\n")

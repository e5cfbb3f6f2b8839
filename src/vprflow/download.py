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
3. refuse the archive if any member is an absolute path or contains ``..``;
4. write each member under a ``layout`` sub-path to its dataset path (regular files
   only; a link there is an error), hashing it; with a manifest only the listed files
   are written, each must be in the archive and match its hash;
5. rename the folder into place; the caller writes the record (:func:`write_record`).

A dataset folder that already exists is left alone: nothing is fetched.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import sys
import tarfile
import tempfile
import urllib.error
import urllib.request
import zipfile
from collections.abc import Iterator
from pathlib import Path, PurePosixPath, PureWindowsPath

from vprflow.files import write_text_atomic

log = logging.getLogger("vprflow")

# What `snakemake <RECORD>` builds: the record written once the dataset folder is in place.
RECORD = "results/downloads/{dataset}.json"
LOG = "logs/download/{dataset}.log"
CHUNK = 1 << 20


class DownloadError(RuntimeError):
    """A failed download; the message names the URL, member or file at fault."""


def record_path(name: str) -> str:
    return RECORD.format(dataset=name)


def download_hint(name: str) -> str:
    """The command that downloads dataset ``name`` (for 'folder does not exist' errors)."""
    return f"snakemake --cores 1 {record_path(name)}"


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


# ------------------------------------------------------------------ fetching


def fetch(url: str, dest: str | Path, timeout: float = 60.0) -> str:
    """Stream ``url`` into ``dest`` with a progress bar; return the SHA-256 of the bytes.

    HTTP errors, unreachable hosts and truncated transfers raise :class:`DownloadError`
    naming the URL.
    """
    from tqdm import tqdm

    request = urllib.request.Request(url, headers={"User-Agent": "vprflow"})
    digest = hashlib.sha256()
    received = 0
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            length = response.headers.get("Content-Length")
            total = int(length) if length and length.isdigit() else None
            with (
                open(dest, "wb") as out,
                tqdm(
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
    """One archive entry: its name, whether it is a regular file, and how to read it."""

    def __init__(self, name: str, is_file: bool, is_dir: bool, open_):
        self.name, self.is_file, self.is_dir, self.open = name, is_file, is_dir, open_


def archive_members(path: str | Path, url: str) -> Iterator[_Member]:
    """Entries of a zip or tar (any compression tarfile reads), in archive order."""
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
                    lambda info=info, archive=archive: archive.open(info),
                )
        return
    try:
        archive = tarfile.open(path, "r:*")
    except tarfile.TarError:
        raise DownloadError(f"{url} is not a zip or tar archive") from None
    with archive:
        for info in archive:
            yield _Member(
                info.name,
                info.isfile(),
                info.isdir(),
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
) -> dict[str, str]:
    """Write the archive members that ``layout`` maps into ``dest``; return
    ``{dataset path: sha256}`` of the written files.

    The whole archive is refused when any member name is unsafe (absolute, ``..``),
    before anything is written. With ``manifest``, only its files are written (others
    under a layout path are skipped and counted in the log), each must be in the
    archive and match its hash.
    """
    dest = Path(dest)
    where = "config key download.layout"
    mapping = {
        safe_relative(str(k), where): safe_relative(str(v), where) for k, v in layout.items()
    }
    if not mapping or any(not k.parts for k in mapping):
        raise DownloadError(f"{where} must map archive sub-paths (not the archive root) to folders")
    names = [m.name for m in archive_members(archive, url)]
    for name in names:
        safe_relative(name, f"archive {url}, member")
    written: dict[str, str] = {}
    used: set[PurePosixPath] = set()
    skipped: list[str] = []
    for member in archive_members(archive, url):
        found = _target(safe_relative(member.name, url), strip, mapping)
        if found is None:
            continue
        target, source = found
        used.add(source)
        if member.is_dir:
            continue
        key = target.as_posix()
        if not member.is_file:
            raise DownloadError(
                f"archive {url}: member {member.name!r} is a link or special file; refusing it"
            )
        if manifest is not None and key not in manifest:
            skipped.append(key)
            continue
        if key in written:
            raise DownloadError(f"archive {url}: two members are laid out at {key}")
        path = dest / target
        path.parent.mkdir(parents=True, exist_ok=True)
        digest = hashlib.sha256()
        with member.open() as src, open(path, "wb") as out:
            while chunk := src.read(CHUNK):
                out.write(chunk)
                digest.update(chunk)
        written[key] = digest.hexdigest()
        if manifest is not None:
            verify_sha256(f"{key} (member {member.name!r} of {url})", manifest[key], written[key])
    unused = [k.as_posix() for k in mapping if k not in used]
    if unused:
        tops = sorted(
            {PurePosixPath(*PurePosixPath(n).parts[: strip + 1]).as_posix() for n in names}
        )
        raise DownloadError(
            f"archive {url} has no member {unused} (after stripping {strip} leading "
            f"folder(s)); its top-level entries: {tops[:10]}"
        )
    if manifest is not None:
        missing = sorted(set(manifest) - set(written))
        if missing:
            raise DownloadError(
                f"archive {url} lacks {len(missing)} file(s) of the manifest, e.g. {missing[:5]}"
            )
    if skipped:
        log.info("skipped %d file(s) not in the manifest, e.g. %s", len(skipped), skipped[:5])
    if not written:
        raise DownloadError(f"archive {url}: the layout selects no files")
    return dict(sorted(written.items()))


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
    for leftover in folder.parent.glob(prefix + "*"):
        log.info("removing %s, left by an interrupted download", leftover)
        shutil.rmtree(leftover, ignore_errors=True)
    work = Path(tempfile.mkdtemp(prefix=prefix, dir=folder.parent))
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
        os.replace(staged, folder)
    except DownloadError as error:
        # The console shows this line: name the dataset and what to do, not only the URL.
        raise DownloadError(
            f"dataset {name!r}: {error}. Nothing was laid out at {folder}. Run this target "
            f"again once the URL is reachable, or put the dataset at {folder} yourself "
            "(or run with --config data_root=<folder holding it>)"
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


def write_record(record: dict, path: str | Path) -> None:
    """Write the record as JSON, atomically (temporary file, then rename)."""
    write_text_atomic(path, json.dumps(record, indent=1, sort_keys=True) + "\n")

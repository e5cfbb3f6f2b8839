"""Public datasets on demand (vprflow.data.download, the `download` rule), against an HTTP
server on 127.0.0.1: no test needs a network."""

from __future__ import annotations

import collections
import csv
import errno
import functools
import hashlib
import http.server
import io
import json
import os
import re
import subprocess
import sys
import tarfile
import threading
import zipfile
from pathlib import Path

import pytest
from synthetic import make_dataset
from workflow_helpers import dataset_spec, scheduled_stages, snakemake, toy_config, write_config

from vprflow.core.errors import DatasetError
from vprflow.data import download
from vprflow.data.datasets import list_dataset
from vprflow.data.download import (
    DownloadError,
    download_dataset,
    download_entry,
    extract_layout,
    read_manifest,
)

PREFIX = "toy-archive-0123abc"  # the single top folder, as in a GitHub archive
LAYOUT = {
    "images/db": "ref",
    "images/q": "query",
    "gt/ground_truth_new.npy": "ground_truth_new.npy",
}


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@pytest.fixture(autouse=True)
def no_proxy(monkeypatch):
    """A proxy in the environment must not intercept the loopback server."""
    for name in ("http_proxy", "HTTP_PROXY", "https_proxy", "HTTPS_PROXY"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("no_proxy", "127.0.0.1,localhost")


@pytest.fixture(scope="module")
def toy_files(tmp_path_factory) -> dict[str, bytes]:
    """A small synthetic dataset as ``{dataset path: bytes}``."""
    root = make_dataset(tmp_path_factory.mktemp("source") / "toy")
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def archive_name(path: str) -> str:
    """Where a dataset file sits in the archive (the inverse of LAYOUT)."""
    for source, dest in LAYOUT.items():
        if path == dest:
            return f"{PREFIX}/{source}"
        if path.startswith(dest + "/"):
            return f"{PREFIX}/{source}/{path[len(dest) + 1 :]}"
    raise AssertionError(path)


def make_archive(path: Path, files: dict[str, bytes], extra: dict[str, bytes] = ()) -> bytes:
    """A zip or tar.gz (by suffix) of ``files`` at their archive names, plus ``extra``
    members under their literal names (which may be unsafe); returns its bytes."""
    members = {archive_name(k): v for k, v in files.items()}
    members[f"{PREFIX}/README.md"] = b"not laid out\n"
    members.update(dict(extra))
    if path.suffix != ".zip":
        return make_tar_gz(path, members)
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return path.read_bytes()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """``(folder, base URL)``: files put in ``folder`` are served on 127.0.0.1."""
    folder = tmp_path_factory.mktemp("served")

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    handler = functools.partial(Quiet, directory=str(folder))
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield folder, f"http://127.0.0.1:{httpd.server_address[1]}"
    httpd.shutdown()
    httpd.server_close()


def spec_for(url: str, digest: str | None = None) -> dict:
    spec = {"url": url, "strip": 1, "layout": dict(LAYOUT)}
    if digest:
        spec["sha256"] = digest
    return spec


def write_manifest(path: Path, files: dict[str, bytes]) -> Path:
    lines = ["# test manifest"] + [f"{sha256(data)}  {name}" for name, data in files.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("suffix", [".zip", ".tar.gz"])
def test_download_verifies_and_lays_out_the_dataset(tmp_path, server, toy_files, suffix):
    folder, base = server
    data = make_archive(folder / f"toy{suffix}", toy_files)
    manifest = write_manifest(tmp_path / "toy.sha256", toy_files)
    target = tmp_path / "data" / "toy"
    record = download_dataset(
        "toy", spec_for(f"{base}/toy{suffix}", sha256(data)), target, manifest
    )
    laid_out = {
        p.relative_to(target).as_posix(): p.read_bytes() for p in target.rglob("*") if p.is_file()
    }
    assert laid_out == toy_files  # README.md outside the layout is not extracted
    assert record["downloaded"] and record["sha256_pinned"]
    assert record["sha256"] == sha256(data) and record["bytes"] == len(data)
    assert record["files"] == {name: sha256(b) for name, b in toy_files.items()}
    assert list(tmp_path.joinpath("data").iterdir()) == [target]  # no temporary leftovers
    spec = dataset_spec(path="toy", reference="ref", query="query")
    files = list_dataset(tmp_path / "data", "toy", spec)
    assert len(files.reference) == len(files.query) == 10
    # An existing folder is left alone: nothing is fetched.
    again = download_dataset("toy", spec_for(f"{base}/missing.zip"), target)
    assert again["downloaded"] is False


def test_missing_sha256_records_the_computed_hash(tmp_path, server, toy_files, caplog):
    folder, base = server
    data = make_archive(folder / "unpinned.zip", toy_files)
    record = download_dataset("toy", spec_for(f"{base}/unpinned.zip"), tmp_path / "toy")
    assert record["sha256"] == sha256(data) and record["sha256_pinned"] is False
    assert f"download.sha256: {sha256(data)}" in caplog.text


def test_wrong_sha256_names_url_and_both_hashes_and_leaves_no_folder(tmp_path, server, toy_files):
    folder, base = server
    data = make_archive(folder / "toy.zip", toy_files)
    url = f"{base}/toy.zip"
    wrong = "0" * 64
    with pytest.raises(DownloadError) as error:
        download_dataset("toy", spec_for(url, wrong), tmp_path / "data" / "toy")
    message = str(error.value)
    assert url in message and wrong in message and sha256(data) in message
    assert list((tmp_path / "data").iterdir()) == []  # no dataset folder, no leftovers


def test_manifest_mismatch_names_the_file_and_leaves_no_folder(tmp_path, server, toy_files):
    folder, base = server
    make_archive(folder / "toy.zip", toy_files)
    altered = dict(toy_files, **{"ref/0003.png": b"other bytes"})
    manifest = write_manifest(tmp_path / "toy.sha256", altered)
    with pytest.raises(DownloadError) as error:
        download_dataset("toy", spec_for(f"{base}/toy.zip"), tmp_path / "data" / "toy", manifest)
    message = str(error.value)
    assert "ref/0003.png" in message
    assert sha256(b"other bytes") in message and sha256(toy_files["ref/0003.png"]) in message
    assert list((tmp_path / "data").iterdir()) == []


def test_manifest_file_missing_from_the_archive_is_named(tmp_path, server, toy_files):
    folder, base = server
    make_archive(folder / "toy.zip", toy_files)
    manifest = write_manifest(tmp_path / "m.sha256", {**toy_files, "query/0099.jpg": b"x"})
    with pytest.raises(DownloadError, match=r"lacks 1 file\(s\) of the manifest.*query/0099.jpg"):
        download_dataset("toy", spec_for(f"{base}/toy.zip"), tmp_path / "data" / "toy", manifest)
    assert not (tmp_path / "data" / "toy").exists()


def test_layout_path_missing_from_the_archive_is_named(tmp_path, server, toy_files):
    folder, base = server
    make_archive(folder / "toy.zip", toy_files)
    spec = spec_for(f"{base}/toy.zip")
    spec["layout"]["images/night"] = "night"
    with pytest.raises(DownloadError, match=r"has no member \['images/night'\]"):
        download_dataset("toy", spec, tmp_path / "data" / "toy")
    assert not (tmp_path / "data" / "toy").exists()


def test_a_download_entry_without_its_strip_filled_fails_with_key_error(
    tmp_path, server, toy_files
):
    # The schema's default (0) is filled into every entry; none is restated here.
    assert dataset_spec(download={"url": "x", "layout": {}})["download"]["strip"] == 0
    folder, base = server
    make_archive(folder / "toy.zip", toy_files)
    spec = spec_for(f"{base}/toy.zip")
    del spec["strip"]
    with pytest.raises(KeyError, match="strip"):
        download_dataset("toy", spec, tmp_path / "data" / "toy")
    assert not (tmp_path / "data" / "toy").exists()


@pytest.mark.parametrize("suffix", [".zip", ".tar.gz"])
@pytest.mark.parametrize("evil", ["../../escaped.txt", "/tmp/escaped.txt", f"{PREFIX}/../x.txt"])
def test_path_traversal_member_is_rejected(tmp_path, toy_files, suffix, evil):
    archive = tmp_path / f"evil{suffix}"
    make_archive(archive, toy_files, {evil: b"owned"})
    dest = tmp_path / "out" / "toy"
    dest.mkdir(parents=True)
    with pytest.raises(DownloadError, match="leaves its folder"):
        extract_layout(archive, "file:///evil", LAYOUT, dest, strip=1)
    assert list(dest.iterdir()) == []  # refused before anything was written
    assert not (tmp_path / "escaped.txt").exists()


def test_link_member_in_the_layout_is_rejected(tmp_path):
    archive = tmp_path / "links.tar.gz"
    with tarfile.open(archive, "w:gz") as tar:
        info = tarfile.TarInfo(f"{PREFIX}/images/db/0000.png")
        info.type, info.linkname = tarfile.SYMTYPE, "/etc/passwd"
        tar.addfile(info)
    with pytest.raises(DownloadError, match="link or special file"):
        extract_layout(archive, "file:///links", LAYOUT, tmp_path / "out", strip=1)


def test_unsafe_layout_target_is_rejected(tmp_path, toy_files):
    archive = tmp_path / "toy.zip"
    make_archive(archive, toy_files)
    with pytest.raises(DownloadError, match="leaves its folder"):
        extract_layout(archive, "file:///toy", {"images/db": "../ref"}, tmp_path / "out", strip=1)


def test_http_404_names_the_url(tmp_path, server):
    _, base = server
    url = f"{base}/no-such-archive.zip"
    with pytest.raises(DownloadError, match=rf"{url} failed: HTTP 404"):
        download_dataset("toy", spec_for(url), tmp_path / "data" / "toy")
    assert list((tmp_path / "data").iterdir()) == []


def test_not_an_archive_is_named(tmp_path, server):
    folder, base = server
    (folder / "page.html").write_text("<html>sign in to download</html>")
    with pytest.raises(DownloadError, match=r"page.html is not a zip or tar archive"):
        download_dataset("toy", spec_for(f"{base}/page.html"), tmp_path / "data" / "toy")


def test_manifest_lines_are_checked(tmp_path):
    bad = tmp_path / "bad.sha256"
    bad.write_text("abc  ref/0.png\n")
    with pytest.raises(DownloadError, match="line 1"):
        read_manifest(bad)


def test_missing_folder_error_names_the_download_command(tmp_path):
    spec = {"path": "toy", "reference": "ref", "query": "query", "source": "somewhere"}
    with pytest.raises(DatasetError) as error:
        list_dataset(tmp_path, "toy", {**spec, "download": {"url": "x", "layout": {"a": "b"}}})
    assert "snakemake --cores 1 results/downloads/toy.json" in str(error.value)
    assert "Get it from somewhere" in str(error.value)
    with pytest.raises(DatasetError) as error:
        list_dataset(tmp_path, "toy", spec)
    assert "results/downloads" not in str(error.value)
    assert "Get it from somewhere" in str(error.value)


def test_dataset_without_download_entry_says_where_to_get_it():
    config = {"datasets": {"places": {"path": "p", "source": "the authors' page"}}}
    with pytest.raises(DownloadError, match="no `download` entry.*Get it from the authors' page"):
        download_entry(config, "places")
    with pytest.raises(DownloadError, match="unknown dataset 'other'"):
        download_entry(config, "other")


def test_shipped_manifests_are_readable_and_match_their_layouts():
    """The shipped per-file lists parse, and name only paths their dataset's layout
    produces (the reference and query folders, the ground truth)."""
    from workflow_helpers import REPO, repo_config

    config = repo_config()
    with_download = {n: d for n, d in config["datasets"].items() if "download" in d}
    assert sorted(with_download) == ["corridor", "roadscene"]
    for name, dataset in with_download.items():
        manifest = read_manifest(REPO / "workflow" / dataset["download"]["manifest"])
        folders = {Path(p).parts[0] for p in manifest if len(Path(p).parts) > 1}
        assert folders == {dataset["reference"], dataset["query"]}, name


# ------------------------------------------------------------------ faults named


def make_tar_gz(path: Path, members: dict[str, bytes]) -> bytes:
    """A tar.gz of ``members`` at their literal names, in order; returns its bytes."""
    with tarfile.open(path, "w:gz") as archive:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            archive.addfile(info, io.BytesIO(data))
    return path.read_bytes()


def test_a_truncated_tar_gz_names_the_dataset_url_and_archive(tmp_path, server, toy_files):
    folder, base = server
    whole = make_archive(tmp_path / "whole.tar.gz", toy_files)
    (folder / "cut.tar.gz").write_bytes(whole[: len(whole) // 2])  # a cut-off transfer
    url = f"{base}/cut.tar.gz"
    with pytest.raises(DownloadError) as error:
        download_dataset("toy", spec_for(url), tmp_path / "data" / "toy")
    message = str(error.value)  # before: EOFError: Compressed file ended before ...
    assert "dataset 'toy'" in message and f"archive {url} is truncated or damaged" in message
    assert "EOFError" in message and "/archive)" in message
    assert "run the download again" in message
    assert list((tmp_path / "data").iterdir()) == []


@pytest.mark.parametrize(
    "damage",
    ["truncated tar.gz", "tar.gz cut in its header", "zip with a bad CRC", "truncated zip"],
)
def test_a_damaged_archive_names_the_url_and_the_archive_file(tmp_path, toy_files, damage):
    suffix = ".zip" if "zip" in damage.split() else ".tar.gz"
    whole = make_archive(tmp_path / f"whole{suffix}", toy_files)
    if damage == "zip with a bad CRC":
        data = bytearray(whole)
        data[60:70] = bytes(b ^ 0xFF for b in data[60:70])  # inside the first member's data
    elif damage == "tar.gz cut in its header":
        data = whole[:30]
    else:
        data = whole[: len(whole) // 2]
    archive = tmp_path / f"damaged{suffix}"
    archive.write_bytes(bytes(data))
    with pytest.raises(DownloadError) as error:
        extract_layout(archive, "file:///damaged", LAYOUT, tmp_path / "out", strip=1)
    message = str(error.value)
    assert "archive file:///damaged is truncated or damaged" in message
    assert str(archive) in message and "run the download again" in message


def test_an_archive_unpacking_past_the_free_space_is_refused_before_writing(
    tmp_path, server, monkeypatch
):
    folder, base = server
    zeros = bytes(5_000_000)  # compresses to a few kB
    with zipfile.ZipFile(folder / "bomb.zip", "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr(f"{PREFIX}/images/db/0000.png", zeros)
        archive.writestr(f"{PREFIX}/images/q/0000.png", zeros)
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(download.shutil, "disk_usage", lambda _: usage(2_000_000, 0, 1_000_000))
    url = f"{base}/bomb.zip"
    spec = {"url": url, "strip": 1, "layout": {"images/db": "ref", "images/q": "query"}}
    with pytest.raises(DownloadError) as error:
        download_dataset("toy", spec, tmp_path / "data" / "toy")
    message = str(error.value)  # before: unpacked until the disk was full (ENOSPC)
    assert "dataset 'toy'" in message and url in message
    assert "unpack to 10.0 MB (10000000 bytes)" in message
    assert (
        "1.0 MB (1000000 bytes) free" in message and "100.0 kB (100000 bytes) kept free" in message
    )
    assert list((tmp_path / "data").iterdir()) == []


def test_a_download_larger_than_the_free_space_is_refused_before_fetching(
    tmp_path, server, toy_files, monkeypatch
):
    folder, base = server
    data = make_archive(folder / "toy.zip", toy_files)
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(download.shutil, "disk_usage", lambda _: usage(10_000, 0, 1_000))
    with pytest.raises(DownloadError) as error:
        download_dataset("toy", spec_for(f"{base}/toy.zip"), tmp_path / "data" / "toy")
    message = str(error.value)
    assert f"download of {base}/toy.zip is" in message and f"({len(data)} bytes)" in message
    assert "more than the file system can take" in message and "(1000 bytes) free" in message


def test_a_member_longer_than_its_header_declares_is_refused(tmp_path):
    lying = download._Member("p/a.png", True, False, 4, lambda: io.BytesIO(b"12345678"))
    with pytest.raises(DownloadError, match=r"'p/a.png' unpacks to more than the 4 bytes"):
        download._write_member(lying, tmp_path / "a.png", "file:///lying")


def test_a_disk_that_fills_while_unpacking_names_the_dataset_and_member(
    tmp_path, server, toy_files, monkeypatch
):
    folder, base = server
    make_archive(folder / "toy.zip", toy_files)

    class Full(io.RawIOBase):
        def writable(self):
            return True

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

    def full_open(path, mode="r", *args, **kwargs):
        if "w" in mode and Path(path).parent.name != Path(path).parent.parent.name:
            if Path(path).name != "archive":
                return Full()
        return open(path, mode, *args, **kwargs)

    monkeypatch.setattr(download, "open", full_open, raising=False)
    with pytest.raises(DownloadError) as error:
        download_dataset("toy", spec_for(f"{base}/toy.zip"), tmp_path / "data" / "toy")
    message = str(error.value)  # before: OSError: [Errno 28] No space left on device
    assert "dataset 'toy'" in message and "the disk filled up while unpacking member" in message
    assert f"{base}/toy.zip" in message and "No space left on device" in message
    assert list((tmp_path / "data").iterdir()) == []


@pytest.mark.parametrize("file_first", [True, False])
def test_a_member_that_is_both_a_file_and_a_folder_is_named(tmp_path, toy_files, file_first):
    archive = tmp_path / "both.tar.gz"
    members = [(f"{PREFIX}/images/db/a", b"a file"), (f"{PREFIX}/images/db/a/b.png", b"png")]
    make_tar_gz(archive, dict(members if file_first else members[::-1]))
    with pytest.raises(DownloadError) as error:
        extract_layout(archive, "file:///both", {"images/db": "ref"}, tmp_path / "out", strip=1)
    message = str(error.value)  # before: FileExistsError / IsADirectoryError on out/ref/a
    assert "archive file:///both" in message
    assert f"'{PREFIX}/images/db/a' is a file at ref/a" in message
    assert f"'{PREFIX}/images/db/a/b.png' needs a folder" in message
    assert not (tmp_path / "out").exists()  # refused before anything was written


def test_a_folder_member_where_another_is_a_file_is_named(tmp_path):
    archive = tmp_path / "both.zip"
    with zipfile.ZipFile(archive, "w") as zipped:
        zipped.writestr(f"{PREFIX}/images/db/a/", b"")
        zipped.writestr(f"{PREFIX}/images/db/a", b"a file")
    with pytest.raises(DownloadError, match=r"'toy-archive-0123abc/images/db/a/' is a folder"):
        extract_layout(archive, "file:///both", {"images/db": "ref"}, tmp_path / "out", strip=1)


def test_two_members_at_one_path_are_refused_before_anything_is_written(tmp_path):
    archive = tmp_path / "twice.tar.gz"
    with tarfile.open(archive, "w:gz") as tar:
        for data in (b"first", b"second"):
            info = tarfile.TarInfo(f"{PREFIX}/images/db/a.png")
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    with pytest.raises(DownloadError, match=r"two members are laid out at ref/a.png"):
        extract_layout(archive, "file:///twice", {"images/db": "ref"}, tmp_path / "out", strip=1)
    assert not (tmp_path / "out").exists()


def test_two_downloads_of_one_dataset_at_once_both_finish_with_one_folder(
    tmp_path, server, toy_files, monkeypatch, caplog
):
    """A second run (--nolock) starts and finishes while the first is fetching: before,
    it deleted the first's temporary folder as an interrupted download's."""
    folder, base = server
    data = make_archive(folder / "toy.zip", toy_files)
    spec = spec_for(f"{base}/toy.zip", sha256(data))
    target = tmp_path / "data" / "toy"
    real_fetch = download.fetch
    others = []

    def fetch_while_another_run_downloads(url, dest, timeout=60.0):
        digest = real_fetch(url, dest, timeout)
        if not others:  # the first run's fetch: the second run starts and finishes
            others.append(None)
            others[0] = download_dataset("toy", spec, target)
        return digest

    monkeypatch.setattr(download, "fetch", fetch_while_another_run_downloads)
    with caplog.at_level("INFO", logger="vprflow"):
        record = download_dataset("toy", spec, target)
    assert record["downloaded"] and others[0]["downloaded"]
    assert "is downloading the same dataset at this moment" in caplog.text
    assert "keeping it, discarding this run's copy" in caplog.text
    laid_out = {
        p.relative_to(target).as_posix(): p.read_bytes() for p in target.rglob("*") if p.is_file()
    }
    assert laid_out == toy_files
    assert list((tmp_path / "data").iterdir()) == [target]


def test_only_abandoned_download_folders_are_removed(tmp_path):
    from vprflow.core.files import host_name

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    prefix = ".toy.download-"
    live = tmp_path / f"{prefix}{host_name()}-{os.getppid()}-0123abcd-x1"
    gone = tmp_path / f"{prefix}{host_name()}-{dead.pid}-0123abcd-x2"
    untagged = tmp_path / f"{prefix}k3j4"  # from before writer tags
    for path in (live, gone, untagged):
        path.mkdir()
    download.remove_abandoned_work(tmp_path, prefix)
    assert sorted(p.name for p in tmp_path.iterdir()) == [live.name]


@pytest.mark.workflow
def test_download_rule_then_recall_through_the_snakefile(tmp_path, server, toy_files):
    """`snakemake results/downloads/toy.json` with the data folder missing, then
    `snakemake results/recall_toy.csv` on what it laid out."""
    folder, base = server
    data = make_archive(folder / "workflow-toy.tar.gz", toy_files)
    manifest = write_manifest(tmp_path / "toy.sha256", toy_files)
    workdir = tmp_path / "work"
    workdir.mkdir()
    download = {**spec_for(f"{base}/workflow-toy.tar.gz", sha256(data)), "manifest": str(manifest)}
    # One method: what is tested is the download, and the table that follows it.
    config = toy_config(workdir / "data", download=download, methods=["anyloc_vlad"])
    config_path = write_config(workdir, config)
    # Without the data a dry run shows the download job and fetches nothing.
    dry = snakemake(workdir, config_path, "-n", "results/recall_toy.csv")
    assert re.search(r"^download +1$", dry.stdout, re.M), dry.stdout
    assert not (workdir / "data" / "toy").exists()
    assert not (workdir / "results" / "downloads" / "toy.json").exists()
    snakemake(workdir, config_path, "results/downloads/toy.json")
    record = json.loads((workdir / "results" / "downloads" / "toy.json").read_text())
    assert record["downloaded"] and record["sha256"] == sha256(data)
    assert record["files"] == {name: sha256(b) for name, b in toy_files.items()}
    assert (workdir / "logs" / "download" / "toy.log").exists()
    snakemake(workdir, config_path, "results/recall_toy.csv")
    with open(workdir / "results" / "recall_toy.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(config["datasets"]["toy"]["methods"])
    assert all(row["n_queries"] == "10" for row in rows)
    # Pointed at an empty data_root, a run that needs the images fetches the sample there
    # first (it has a download entry) and reruns no stage, since the images are the same.
    # A dry run fetches nothing and shows the download.
    elsewhere = write_config(workdir, {**config, "data_root": str(tmp_path / "empty")}, "b.yaml")
    (workdir / "results" / "recall_toy.csv").unlink()
    dry = snakemake(workdir, elsewhere, "-n", "results/recall_toy.csv")
    assert re.search(r"^download +1$", dry.stdout, re.M) and not (tmp_path / "empty").exists()
    fetched = snakemake(workdir, elsewhere, "results/recall_toy.csv")
    assert "dataset toy: downloading into" in fetched.stdout + fetched.stderr
    assert "output: results/cache/" not in fetched.stdout + fetched.stderr
    assert (tmp_path / "empty" / "toy" / "ref").is_dir()
    assert scheduled_stages(workdir, elsewhere, "results/recall_toy.csv") == set()
    # A dataset without a download entry names itself and the folder, not a stage that
    # failed to find its files (no "Missing files after 5 seconds").
    manual = {**config, "data_root": str(tmp_path / "void")}
    manual["datasets"] = {
        "toy": {k: v for k, v in config["datasets"]["toy"].items() if k != "download"}
    }
    manual_path = write_config(workdir, manual, "c.yaml")
    for target in ("results/recall_toy.csv", "all"):
        failed = snakemake(
            workdir, manual_path, *([] if target == "all" else [target]), check=False
        )
        console = failed.stdout + failed.stderr
        assert failed.returncode != 0, target
        assert "dataset 'toy'" in console and "does not exist" in console, target
        assert "Missing files after" not in console, target


@pytest.mark.workflow
def test_a_failed_download_says_on_the_console_which_dataset_and_what_to_do(tmp_path, server):
    _, base = server
    workdir = tmp_path / "work"
    workdir.mkdir()
    config = toy_config(workdir / "data", download=spec_for(f"{base}/gone.tar.gz"))
    failed = snakemake(
        workdir, write_config(workdir, config), "results/downloads/toy.json", check=False
    )
    console = failed.stdout + failed.stderr
    assert failed.returncode != 0
    # Snakemake's job line says what ran (not "message: None"), the error why and what next.
    assert "dataset toy: downloading into" in console
    assert "dataset 'toy'" in console and "HTTP 404" in console
    assert "put the dataset at" in console and "data_root" in console
    # The message, then its log, and no traceback under it: that is in the log.
    log = Path("logs", "download", "toy.log")
    assert f"(log: {log})" in console and "Traceback" not in console, console
    assert "Traceback" in (workdir / log).read_text()
    assert not (workdir / "data" / "toy").exists()


# ------------------------------------------------------------------ fetched by the run


def test_a_run_asks_for_the_datasets_its_targets_name_or_else_the_configs_targets():
    config = {"targets": ["corridor"], "datasets": {"corridor": {}, "roadscene": {}, "x_y": {}}}
    assert download.requested_datasets(config, ()) == ["corridor"]
    assert download.requested_datasets(config, {"all"}) == ["corridor"]
    targets = ["results/recall_roadscene.csv", "results/pairs/x_y/a/pairs.txt"]
    assert download.requested_datasets(config, targets) == ["roadscene", "x_y"]
    assert download.requested_datasets(config, ["results/recall_x.csv"]) == []


def test_only_a_missing_sample_dataset_awaits_its_download(tmp_path):
    config = {
        "data_root": str(tmp_path / "data"),
        "datasets": {
            "toy": {"path": "toy", "download": spec_for("file:///toy.zip")},
            "preset_like": {"path": "preset_like"},  # no download entry: stays manual
            "present": {"path": "present", "download": spec_for("file:///none.zip")},
        },
    }
    (tmp_path / "data" / "present").mkdir(parents=True)
    assert download.awaiting_download(config) == ["toy"]
    (tmp_path / "data" / "toy").mkdir()
    assert download.awaiting_download(config) == []

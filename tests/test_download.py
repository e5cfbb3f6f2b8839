"""Public datasets on demand (vprflow.download, the `download` rule), against an HTTP
server on 127.0.0.1: no test needs a network."""

from __future__ import annotations

import csv
import functools
import hashlib
import http.server
import io
import json
import tarfile
import threading
import zipfile
from pathlib import Path

import pytest
from synthetic import make_dataset
from workflow_helpers import dataset_spec, snakemake, toy_config, write_config

from vprflow.datasets import DatasetError, list_dataset
from vprflow.download import (
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
    if path.suffix == ".zip":
        with zipfile.ZipFile(path, "w") as archive:
            for name, data in members.items():
                archive.writestr(name, data)
    else:
        with tarfile.open(path, "w:gz") as archive:
            for name, data in members.items():
                info = tarfile.TarInfo(name)
                info.size = len(data)
                archive.addfile(info, io.BytesIO(data))
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
    config = toy_config(workdir / "data", download=download)
    config_path = write_config(workdir, config)
    # Without the data the recall target fails at DAG time, naming the download command.
    failed = snakemake(workdir, config_path, "-n", "results/recall_toy.csv", check=False)
    assert failed.returncode != 0
    assert "results/downloads/toy.json" in failed.stdout + failed.stderr
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
    # After a complete run, the cached stores never stand in for a dataset that is not
    # there: a run pointed at an empty data_root names the dataset and the remedy, not a
    # stage that failed to find its files (no "Missing files after 5 seconds").
    elsewhere = write_config(workdir, {**config, "data_root": str(tmp_path / "empty")}, "b.yaml")
    for target in ("results/recall_toy.csv", "all"):
        failed = snakemake(workdir, elsewhere, *([] if target == "all" else [target]), check=False)
        console = failed.stdout + failed.stderr
        assert failed.returncode != 0, target
        assert "dataset 'toy'" in console and "does not exist" in console, target
        assert "snakemake --cores 1 results/downloads/toy.json" in console, target
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
    assert not (workdir / "data" / "toy").exists()

"""Cost of the crc32c checksum on every chunk, and where a store write's time goes:
writing and reading a descriptors store, before and after the write path changed.

    python benchmarks/bench_stores.py                 # ~1 GB of float32 rows (4096 floats)
    python benchmarks/bench_stores.py --mb 256 --repeats 3     # a quicker look
    python benchmarks/bench_stores.py --workdir /dev/shm       # without the disk

Writes one descriptors-like store four times per round, as the descriptors stage does
(``RowWriter``, chunks of ``rows_per_chunk(4 * dim)`` rows, zstd level 1), with the write
path of ``--before`` (``git show REV:src/vprflow/core/stores.py``, loaded into a module
here: one chunk per zarr write, zarr's own empty-chunk comparison) and the package's:
each once with vprflow's codecs (zstd, then crc32c; through ``atomic_store``, which also
records the chunk counts) and once with zstd alone (the codecs before checksums, the
anchor of each path's checksum cost; a plain zarr group, since ``atomic_store`` refuses
an array without the checksum). The four stores must read back equal and hold the same
chunk files (the checksummed ones byte for byte), or the script fails. Then reads each
whole array back, through plain ``zarr.open_group`` and, for the checksummed store,
through ``stores.open_store`` (which also reads every array's metadata and lists its
chunk files before the read), both with its row reader (the chunk files decoded without
zarr, ``stores._RowReader``) and through zarr (``.raw``). Reads are from the page cache
(the store was just written), so they measure decoding, not the disk.

Rows are VLAD-like: 32 blocks of ``dim / 32`` values, about half of them zero (clusters
a segment does not touch), L2-normalised, so they compress about as SegVLAD's do.
Wall and CPU seconds are each the best of ``--repeats``, the variants taking turns in
each round; MB/s counts uncompressed bytes per wall second. CPU seconds (the process's,
codec threads included) are the steadier measure on a busy machine.

The breakdown table times the pieces of each write inside zarr (wrappers around its
codecs and store calls, thread CPU of each call, summed; the fastest round's): zstd, the
CRC arithmetic (``google_crc32c.value``, the library zarr's ``Crc32cCodec`` calls), the
rest of ``Crc32cCodec``'s encode (``np.append`` of the 4 checksum bytes: a copy of the
compressed chunk), zarr's empty-chunk comparison (``NDBuffer.all_equal``), the
``zarr.json`` rewrites (one per zarr write: the append resizes the array), the chunk
files' writes, vprflow's ``check_finite`` and ``atomic_store``'s own steps; "the rest"
is the write's process CPU less these (numpy buffering, zarr's event loop, threads).
Each piece is also given as a share of the same path's write without checksum. Beside
them, google-crc32c and ``np.append`` alone over the chunk files' bytes.

``after: zstd, again`` repeats the anchor's write under another name: the difference
between two runs of the same work in the same run (in wall, CPU and each piece) is the
noise floor the other differences stand on. ``spread`` is the slowest round's wall over
the fastest's.
"""

from __future__ import annotations

import argparse
import functools
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
import types
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import zarr
import zarr.codecs.crc32c_
import zarr.codecs.zstd
import zarr.core.buffer.core
import zarr.storage._local

from vprflow.core import stores

ROOT = Path(__file__).resolve().parents[1]
# The last commit whose RowWriter gave zarr one chunk per write and let zarr compare
# every chunk with the fill value.
BEFORE = "7f80a7d"
BLOCKS = 32  # VLAD clusters per row


def vlad_like_rows(rng: np.random.Generator, n: int, dim: int) -> np.ndarray:
    rows = rng.standard_normal((n, BLOCKS, dim // BLOCKS)).astype(np.float32)
    rows *= rng.random((n, BLOCKS, 1)) < 0.5
    rows = rows.reshape(n, dim)
    rows /= np.maximum(np.linalg.norm(rows, axis=1, keepdims=True), 1e-12)
    return rows


def load_before(rev: str) -> types.ModuleType | None:
    """``src/vprflow/core/stores.py`` at ``rev`` as a module of its own; None (with a
    note) where git or that commit is not at hand (a shallow CI checkout)."""
    try:
        source = subprocess.run(
            ["git", "show", f"{rev}:src/vprflow/core/stores.py"],
            cwd=ROOT, capture_output=True, text=True, check=True,
        ).stdout  # fmt: skip
    except (OSError, subprocess.CalledProcessError) as error:
        print(f"note: no 'before' rows: git show {rev}:src/vprflow/core/stores.py failed ({error})")
        return None
    module = types.ModuleType("stores_before")
    exec(compile(source, f"{rev}:stores.py", "exec"), module.__dict__)
    return module


@contextmanager
def codecs(module: types.ModuleType, compressors: tuple):
    """RowWriter creates its array with ``COMPRESSORS``: swapped here for the store
    without checksums."""
    saved = module.COMPRESSORS
    module.COMPRESSORS = compressors
    try:
        yield
    finally:
        module.COMPRESSORS = saved


def write(module, path: Path, checksum: bool, n_rows: int, dim: int, seed: int) -> None:
    """Write ``n_rows`` rows with ``module``'s RowWriter, appended one image's worth (8
    rows) at a time; the rows are drawn beforehand (one chunk's worth, reused), so only
    the store is timed."""
    if path.exists():
        shutil.rmtree(path)
    chunk = module.rows_per_chunk(4 * dim)
    pool = vlad_like_rows(np.random.default_rng(seed), chunk, dim)
    if checksum:
        with module.atomic_store(path, {"stage": "descriptors"}) as group:
            append_all(module, group, pool, n_rows, dim, chunk)
    else:
        with codecs(module, (module.COMPRESSOR,)):
            append_all(module, zarr.open_group(str(path), mode="w"), pool, n_rows, dim, chunk)


def append_all(module, group, pool: np.ndarray, n_rows: int, dim: int, chunk: int) -> None:
    writer = module.RowWriter(group, "descriptors", (dim,), np.float32, chunk)
    for first in range(0, n_rows, 8):
        writer.append(pool[np.arange(first, min(first + 8, n_rows)) % len(pool)])
    writer.close()


class Pieces:
    """Thread CPU seconds and calls of named pieces of a write, from wrappers put around
    zarr's codecs and store calls (and vprflow's own steps) for the script's run."""

    def __init__(self, modules: list[types.ModuleType]):
        self.seconds: dict[str, list] = defaultdict(lambda: [0.0, 0])
        crc, zstd = zarr.codecs.crc32c_, zarr.codecs.zstd
        # The arithmetic alone: the library zarr's Crc32cCodec calls, seen from there.
        value = crc.google_crc32c.value
        crc.google_crc32c = types.SimpleNamespace(value=self.wrap("crc arithmetic", value))
        crc.Crc32cCodec._encode_sync = self.wrap("crc codec", crc.Crc32cCodec._encode_sync)
        zstd.ZstdCodec._encode_sync = self.wrap("zstd", zstd.ZstdCodec._encode_sync)
        buffer = zarr.core.buffer.core.NDBuffer
        buffer.all_equal = self.wrap("empty-chunk comparison", buffer.all_equal)
        local = zarr.storage._local
        put = local._put
        metadata, chunk = self.wrap("zarr.json", put), self.wrap("chunk files", put)
        local._put = lambda path, *a, **k: (metadata if path.name == "zarr.json" else chunk)(
            path, *a, **k
        )
        for module in modules:
            module.check_finite = self.wrap("check_finite", module.check_finite)
            for name in ("_seal", "replace_store", "remove_abandoned_temporaries"):
                setattr(module, name, self.wrap("atomic_store", getattr(module, name)))

    def wrap(self, name: str, function):
        @functools.wraps(function)
        def timed(*args, **kwargs):
            start = time.thread_time()
            try:
                return function(*args, **kwargs)
            finally:
                entry = self.seconds[name]
                entry[0] += time.thread_time() - start
                entry[1] += 1

        return timed

    def take(self) -> dict[str, tuple[float, int]]:
        taken = {name: (s, n) for name, (s, n) in self.seconds.items()}
        self.seconds.clear()
        return taken


def interleaved_best_of(cases: dict, repeats: int, pieces: Pieces | None = None) -> dict:
    """``{name: (wall s, CPU s, pieces of the fastest-CPU round, slowest wall s)}``, wall and
    CPU each the best of ``repeats``, the cases taking turns in every round (on a shared
    machine a slow spell then costs every case alike). CPU time is this process's, zarr's
    codec threads included: the work done, whatever else the machine runs."""
    best = {name: (float("inf"), float("inf"), {}, 0.0) for name in cases}
    for _ in range(repeats):
        for name, function in cases.items():
            if pieces:
                pieces.take()
            wall, cpu = time.perf_counter(), time.process_time()
            function()
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            taken = pieces.take() if pieces else {}
            old_wall, old_cpu, old_pieces, slowest = best[name]
            best[name] = (
                min(old_wall, wall),
                min(old_cpu, cpu),
                taken if cpu < old_cpu else old_pieces,
                max(slowest, wall),
            )
    return best


def size_on_disk(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def chunk_files(path: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(path)): p.read_bytes()
        for p in sorted(path.rglob("c/**/*"))
        if p.is_file()
    }


def alone(chunks: list[bytes]) -> tuple[float, float]:
    """Seconds of google-crc32c, and of ``np.append`` of 4 bytes (Crc32cCodec's copy),
    over the chunk files' bytes read beforehand, each the best of 3, without zarr."""
    import google_crc32c

    arrays = [np.frombuffer(data, np.uint8) for data in chunks]
    four = np.zeros(4, np.uint8)
    crc = copy = float("inf")
    for _ in range(3):
        start = time.perf_counter()
        for data in chunks:
            google_crc32c.value(data)
        crc = min(crc, time.perf_counter() - start)
        start = time.perf_counter()
        for data in arrays:
            np.append(data, four)
        copy = min(copy, time.perf_counter() - start)
    return crc, copy


def table(title: str, results: dict, anchors: dict, mb: float) -> None:
    """One row per case; ``vs anchor``: wall and CPU against the case's anchor; ``spread``:
    the slowest round's wall over the fastest's, the same code's run-to-run variation."""
    print(
        f"\n{title:<36} {'wall s':>7} {'spread':>7} {'MB/s':>6} {'vs anchor':>9} {'CPU s':>6} "
        f"{'vs anchor':>9}  anchor"
    )
    print("-" * 100)
    for name, (wall, cpu, _, slowest) in results.items():
        anchor = anchors[name]
        wall0, cpu0 = results[anchor][:2]
        print(
            f"{name:<36} {wall:>7.2f} {slowest / wall - 1:>+7.0%} {mb / wall:>6.0f} "
            f"{wall / wall0 - 1:>+9.1%} {cpu:>6.2f} {cpu / cpu0 - 1:>+9.1%}  "
            f"{anchor if anchor != name else '(itself)'}"
        )


PIECES = (
    ("zstd", "zstd compression (ZstdCodec)"),
    ("crc arithmetic", "crc32c arithmetic (google-crc32c)"),
    ("crc copy", "Crc32cCodec's copy (np.append +4 B)"),
    ("empty-chunk comparison", "empty-chunk comparison (all_equal)"),
    ("zarr.json", "zarr.json rewrites"),
    ("chunk files", "chunk file writes"),
    ("check_finite", "check_finite (vprflow)"),
    ("atomic_store", "atomic_store: seal, rename, cleanup"),
)


def breakdown(results: dict, anchors: dict) -> None:
    """Where each write's CPU goes: ms (calls) and % of its path's write without
    checksum."""
    names = list(results)
    print(
        "\nwhere the write's CPU goes (thread CPU ms, fastest round; % of the path's write "
        "without checksum)"
    )
    header = f"{'piece':<38}" + "".join(f" {name:>24}" for name in names)
    print(header)
    print("-" * len(header))
    rows = {}
    for name in names:
        _, cpu, pieces, _ = results[name]
        got = {key: pieces.get(key, (0.0, 0)) for key, _ in PIECES}
        codec, arithmetic = pieces.get("crc codec", (0.0, 0)), got["crc arithmetic"]
        got["crc copy"] = (codec[0] - arithmetic[0], codec[1])
        got["rest"] = (cpu - sum(s for s, _ in got.values()), 0)
        got["total"] = (cpu, 0)
        rows[name] = got
    for key, label in (*PIECES, ("rest", "the rest (buffers, event loop, threads)"),
                       ("total", "the write's process CPU")):  # fmt: skip
        cells = []
        for name in names:
            seconds, calls = rows[name][key]
            anchor_cpu = results[anchors[name]][1]
            if calls == 0 and key not in ("rest", "total"):
                cells.append(f"{'-':>24}")
                continue
            count = f" ({calls})" if calls else ""
            cells.append(f"{seconds * 1e3:>9.1f}{count:>7} {seconds / anchor_cpu:>7.1%}")
        print(f"{label:<38}" + "".join(f" {cell:>24}" for cell in cells))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mb", type=int, default=1024, help="uncompressed size of the array")
    parser.add_argument("--dim", type=int, default=4096, help="floats per row (49152: SegVLAD)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workdir", type=Path, default=None, help="default: a folder in /tmp")
    parser.add_argument("--before", default=BEFORE, help="git revision of the old write path")
    parser.add_argument("--smoke", action="store_true", help="8 MB, one repeat (CI: it runs)")
    args = parser.parse_args()
    if args.smoke:
        args.mb, args.repeats = 8, 1
    n_rows = max(1, (args.mb << 20) // (4 * args.dim))
    mb = n_rows * 4 * args.dim / 1e6
    chunk = stores.rows_per_chunk(4 * args.dim)
    paths = {"after": stores}
    before = load_before(args.before)
    if before is not None:
        paths = {"before": before, **paths}
    pieces = Pieces(list(paths.values()))
    workdir = Path(tempfile.mkdtemp(prefix="vprflow-bench-stores-", dir=args.workdir))
    try:
        writes, anchors, stored = {}, {}, {}
        for label, module in paths.items():
            for checksum in (False, True):
                name = f"{label}: zstd" + (" + crc32c" if checksum else "")
                stored[name] = workdir / f"{label}-{'crc' if checksum else 'zstd'}.zarr"
                writes[name] = functools.partial(
                    write, module, stored[name], checksum, n_rows, args.dim, args.seed
                )
                anchors[name] = f"{label}: zstd"
        # The same write again, under another name: how far two runs of identical work
        # differ in this run, the floor under every other difference in the table.
        again = "after: zstd, again"
        stored[again] = workdir / "after-zstd-again.zarr"
        writes[again] = functools.partial(
            write, stores, stored[again], False, n_rows, args.dim, args.seed
        )
        anchors[again] = "after: zstd"
        load = os.getloadavg()
        write_s = interleaved_best_of(writes, args.repeats, pieces)
        load = (load, os.getloadavg())

        # Every path stores the same chunks: the same values, and (with checksums) the
        # same bytes; a new write path that changed a file fails here.
        reference = np.asarray(zarr.open_group(str(stored["after: zstd"]), mode="r")["descriptors"])
        for name, path in stored.items():
            group = stores.open_store(path) if "crc32c" in name else zarr.open_group(str(path))
            np.testing.assert_array_equal(np.asarray(group["descriptors"][...]), reference)
        del reference
        crc_files = chunk_files(stored["after: zstd + crc32c"] / "descriptors")
        if before is not None:
            before_files = chunk_files(stored["before: zstd + crc32c"] / "descriptors")
            if before_files != crc_files:
                sys.exit("the before and after write paths stored different chunk files")
            del before_files
        crc_s, copy_s = alone(list(crc_files.values()))
        checked, plain = stored["after: zstd + crc32c"], stored["after: zstd"]

        def raw(path):
            return lambda: zarr.open_group(str(path), mode="r")["descriptors"][...]

        reads = {
            "zstd, zarr.open_group": raw(plain),
            "zstd + crc32c, zarr.open_group": raw(checked),
            # The checked store's array read through zarr, as before the row reader.
            "zstd + crc32c, open_store, zarr": lambda: stores.open_store(checked)[
                "descriptors"
            ].raw[...],
            "zstd + crc32c, stores.open_store": lambda: stores.open_store(checked)["descriptors"][
                ...
            ],
        }
        read_s = interleaved_best_of(reads, args.repeats)
        open_s = interleaved_best_of({"open": lambda: stores.open_store(checked)}, 5)["open"]
        disk = {"zstd": size_on_disk(plain) / 1e6, "crc": size_on_disk(checked) / 1e6}
    finally:
        shutil.rmtree(workdir)

    print(
        f"# {platform.machine()}, {os.cpu_count()} cores, zarr {zarr.__version__}, "
        f"workdir {workdir.parent}, before = {args.before if before else '(not loaded)'}; "
        f"load average {load[0][0]:.1f} before the writes, {load[1][0]:.1f} after"
    )
    print(
        f"{n_rows} rows x {args.dim} float32 = {mb:.0f} MB in {-(-n_rows // chunk)} chunks of "
        f"{chunk} rows; on disk {disk['zstd']:.0f} MB (zstd), {disk['crc']:.0f} MB (+ crc32c); "
        f"best of {args.repeats}"
    )
    table("write", write_s, anchors, mb)
    breakdown(write_s, anchors)
    table("read all back", read_s, dict.fromkeys(reads, "zstd, zarr.open_group"), mb)
    print(
        f"\nstores.open_store alone (metadata, chunk listing): {open_s[0] * 1e3:.1f} ms; "
        f"over the {disk['crc']:.0f} MB of chunk files, without zarr: google-crc32c "
        f"{crc_s * 1e3:.1f} ms ({disk['crc'] / crc_s:.0f} MB/s), np.append of 4 bytes "
        f"{copy_s * 1e3:.1f} ms ({disk['crc'] / copy_s:.0f} MB/s)"
    )


if __name__ == "__main__":
    main()

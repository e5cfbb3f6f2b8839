"""Cost of the crc32c checksum on every chunk: writing and reading a descriptors store.

    python benchmarks/bench_stores.py                 # ~1 GB of float32 rows (4096 floats)
    python benchmarks/bench_stores.py --mb 64 --repeats 1      # a quick look

Writes one descriptors-like store twice, as the descriptors stage does (``RowWriter``,
chunks of ``rows_per_chunk(4 * dim)`` rows, zstd level 1): once with vprflow's codecs
(zstd, then crc32c; through ``atomic_store``, which also records the chunk counts) and
once with zstd alone (the codecs before checksums; a plain zarr group, since
``atomic_store`` refuses an array without the checksum). Then reads each whole array
back, through plain ``zarr.open_group`` and, for the checksummed store, through
``stores.open_store`` (which also reads every array's metadata and lists its chunk files
before the read). Reads are from the page cache (the store was just written), so they
measure decoding, not the disk.

Rows are VLAD-like: 32 blocks of ``dim / 32`` values, about half of them zero (clusters
a segment does not touch), L2-normalised, so they compress about as SegVLAD's do.
Wall and CPU seconds are each the best of ``--repeats``, the variants taking turns in
each round; MB/s counts uncompressed bytes per wall second. CPU seconds (the process's,
codec threads included) are the steadier measure on a busy machine.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import zarr

from vprflow.core import stores

BLOCKS = 32  # VLAD clusters per row


def vlad_like_rows(rng: np.random.Generator, n: int, dim: int) -> np.ndarray:
    rows = rng.standard_normal((n, BLOCKS, dim // BLOCKS)).astype(np.float32)
    rows *= rng.random((n, BLOCKS, 1)) < 0.5
    rows = rows.reshape(n, dim)
    rows /= np.maximum(np.linalg.norm(rows, axis=1, keepdims=True), 1e-12)
    return rows


@contextmanager
def codecs(compressors: tuple):
    """RowWriter creates its array with ``stores.COMPRESSORS``: swapped here for the
    store without checksums."""
    saved = stores.COMPRESSORS
    stores.COMPRESSORS = compressors
    try:
        yield
    finally:
        stores.COMPRESSORS = saved


def write(path: Path, checksum: bool, n_rows: int, dim: int, seed: int) -> None:
    """Write ``n_rows`` rows, appended one image's worth (8 rows) at a time; the rows
    are drawn beforehand (one chunk's worth, reused), so only the store is timed."""
    if path.exists():
        shutil.rmtree(path)
    chunk = stores.rows_per_chunk(4 * dim)
    pool = vlad_like_rows(np.random.default_rng(seed), chunk, dim)
    if checksum:
        with stores.atomic_store(path, {"stage": "descriptors"}) as group:
            append_all(group, pool, n_rows, dim, chunk)
    else:
        with codecs((stores.COMPRESSOR,)):
            append_all(zarr.open_group(str(path), mode="w"), pool, n_rows, dim, chunk)


def append_all(group, pool: np.ndarray, n_rows: int, dim: int, chunk: int) -> None:
    writer = stores.RowWriter(group, "descriptors", (dim,), np.float32, chunk)
    for first in range(0, n_rows, 8):
        writer.append(pool[np.arange(first, min(first + 8, n_rows)) % len(pool)])
    writer.close()


def interleaved_best_of(cases: dict, repeats: int) -> dict:
    """``{name: (wall s, CPU s)}``, each the best of ``repeats``, the cases taking turns
    in every round (on a shared machine a slow spell then costs every case alike). CPU
    time is this process's, zarr's codec threads included: the work done, whatever
    else the machine runs."""
    best = {name: (float("inf"), float("inf")) for name in cases}
    for _ in range(repeats):
        for name, function in cases.items():
            wall, cpu = time.perf_counter(), time.process_time()
            function()
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            best[name] = (min(best[name][0], wall), min(best[name][1], cpu))
    return best


def size_on_disk(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def crc32c_alone(path: Path) -> float:
    """Seconds of google-crc32c over every chunk file's bytes, read beforehand: the
    checksum's own cost, without zarr."""
    import google_crc32c

    chunks = [p.read_bytes() for p in sorted(path.rglob("c/**/*")) if p.is_file()]
    start = time.perf_counter()
    for data in chunks:
        google_crc32c.value(data)
    return time.perf_counter() - start


def table(title: str, results: dict, base: str, mb: float, disk: dict | None = None) -> None:
    print(f"\n{title:<36} {'wall s':>7} {'MB/s':>6} {'overhead':>8} {'CPU s':>6} {'overhead':>8}")
    print("-" * 76)
    wall0, cpu0 = results[base]
    for name, (wall, cpu) in results.items():
        print(
            f"{name:<36} {wall:>7.2f} {mb / wall:>6.0f} {wall / wall0 - 1:>+8.1%} "
            f"{cpu:>6.2f} {cpu / cpu0 - 1:>+8.1%}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mb", type=int, default=1024, help="uncompressed size of the array")
    parser.add_argument("--dim", type=int, default=4096, help="floats per row (49152: SegVLAD)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workdir", type=Path, default=None, help="default: a folder in /tmp")
    parser.add_argument("--smoke", action="store_true", help="8 MB, one repeat (CI: it runs)")
    args = parser.parse_args()
    if args.smoke:
        args.mb, args.repeats = 8, 1
    n_rows = max(1, (args.mb << 20) // (4 * args.dim))
    mb = n_rows * 4 * args.dim / 1e6
    chunk = stores.rows_per_chunk(4 * args.dim)
    workdir = Path(tempfile.mkdtemp(prefix="vprflow-bench-stores-", dir=args.workdir))
    try:
        checked, plain = workdir / "crc32c.zarr", workdir / "zstd.zarr"
        writes = {
            "zstd (before checksums)": lambda: write(plain, False, n_rows, args.dim, args.seed),
            "zstd + crc32c (atomic_store)": lambda: write(
                checked, True, n_rows, args.dim, args.seed
            ),
        }
        write_s = interleaved_best_of(writes, args.repeats)
        reference = np.asarray(zarr.open_group(str(plain), mode="r")["descriptors"][...])
        np.testing.assert_array_equal(
            np.asarray(stores.open_store(checked)["descriptors"]), reference
        )
        del reference

        def raw(path):
            return lambda: zarr.open_group(str(path), mode="r")["descriptors"][...]

        reads = {
            "zstd, zarr.open_group": raw(plain),
            "zstd + crc32c, zarr.open_group": raw(checked),
            "zstd + crc32c, stores.open_store": lambda: stores.open_store(checked)["descriptors"][
                ...
            ],
        }
        read_s = interleaved_best_of(reads, args.repeats)
        open_s = interleaved_best_of({"open": lambda: stores.open_store(checked)}, 5)["open"]
        crc_s = crc32c_alone(checked)
        disk = {
            name: size_on_disk(path) / 1e6 for name, path in (("zstd", plain), ("crc", checked))
        }
    finally:
        shutil.rmtree(workdir)

    print(
        f"{n_rows} rows x {args.dim} float32 = {mb:.0f} MB in {-(-n_rows // chunk)} chunks of "
        f"{chunk} rows; on disk {disk['zstd']:.0f} MB (zstd), {disk['crc']:.0f} MB (+ crc32c); "
        f"best of {args.repeats}"
    )
    table("write", write_s, "zstd (before checksums)", mb)
    table("read all back", read_s, "zstd, zarr.open_group", mb)
    print(
        f"\nstores.open_store alone (metadata, chunk listing): {open_s[0] * 1e3:.1f} ms; "
        f"google-crc32c alone over the {disk['crc']:.0f} MB of chunks: {crc_s:.3f} s "
        f"({disk['crc'] / crc_s:.0f} MB/s)"
    )


if __name__ == "__main__":
    main()

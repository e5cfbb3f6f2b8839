"""What reading an image costs with the checks that keep a table honest.

    python benchmarks/bench_images.py                  # corridor (if found) and synthetic sizes
    python benchmarks/bench_images.py --repeat 3 --sizes 640x480

Per image, median over ``--repeat`` passes, milliseconds:

- ``decode``: ``images.read_image`` (PIL decode, EXIF orientation, float conversion);
- ``sha256``: hashing the file's bytes, the check ``Dataset.read_image`` adds before it
  decodes (a file changed during a run must fail, not be computed under its old key);
- ``checked``: ``Dataset.read_image`` as the stages call it (read, hash, decode);
- ``scan``: ``images.scan_images`` of the folder, per image (links, formats, order).

Images: the corridor dataset under ``$VPRFLOW_DATA`` when it is there, and synthetic
JPEGs of ``--sizes`` (textured noise, quality 90) written to a temporary folder.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

from vprflow.images import read_image, scan_images


def per_image_ms(function, paths: list[Path], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        for path in paths:
            function(path)
        times.append((time.perf_counter() - start) / len(paths) * 1e3)
    return statistics.median(times)


def synthetic(folder: Path, width: int, height: int, count: int) -> list[Path]:
    rng = np.random.default_rng(0)
    paths = []
    for i in range(count):
        noise = rng.integers(0, 256, (height // 8, width // 8, 3), dtype=np.uint8)
        image = Image.fromarray(noise).resize((width, height), Image.Resampling.BILINEAR)
        path = folder / f"{i:04d}.jpg"
        image.save(path, quality=90)
        paths.append(path)
    return paths


def measure(name: str, paths: list[Path], repeat: int) -> tuple:
    digests = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in paths}

    def checked(path: Path) -> np.ndarray:
        # What Dataset.read_image does: one read, a hash compared, a decode of the bytes.
        from vprflow.images import decode_image

        data = path.read_bytes()
        if hashlib.sha256(data).hexdigest() != digests[path]:
            raise AssertionError(path)
        return decode_image(data, path)

    decode = per_image_ms(read_image, paths, repeat)
    sha = per_image_ms(lambda p: hashlib.sha256(p.read_bytes()).hexdigest(), paths, repeat)
    full = per_image_ms(checked, paths, repeat)
    folder = paths[0].parent
    scan = per_image_ms(lambda _: scan_images(folder), [folder], repeat) / len(paths)
    size = np.mean([p.stat().st_size for p in paths]) / 1024
    return name, len(paths), size, decode, sha, full, 100 * (full - decode) / decode, scan


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--sizes", nargs="*", default=["160x120", "640x480", "4032x3024"])
    parser.add_argument("--count", type=int, default=20, help="synthetic images per size")
    args = parser.parse_args()
    rows = []
    data = os.environ.get("VPRFLOW_DATA")
    corridor = Path(data) / "corridor" / "query" if data else None
    if corridor and corridor.is_dir():
        rows.append(measure("corridor query", scan_images(corridor).paths, args.repeat))
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            width, height = (int(v) for v in size.split("x"))
            folder = Path(tmp) / size
            folder.mkdir()
            paths = synthetic(folder, width, height, args.count)
            rows.append(measure(f"jpeg {size}", paths, args.repeat))
    header = "images | n | KiB/file | decode ms | sha256 ms | checked ms | check cost | scan ms"
    print(header)
    print("|".join(["---"] * 8))
    for name, n, kib, decode, sha, full, cost, scan in rows:
        print(
            f"{name} | {n} | {kib:.1f} | {decode:.3f} | {sha:.3f} | {full:.3f} | "
            f"{cost:+.1f}% | {scan:.4f}"
        )


if __name__ == "__main__":
    main()

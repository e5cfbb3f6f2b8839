"""Reading and resizing images of any bit depth into one float RGB representation.

Every stage sees images as float32 arrays ``[H, W, 3]`` in ``[0, 1]``: grayscale
(thermal) images are repeated to three channels, 16-bit images are scaled by 65535,
alpha channels are dropped.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".ppm", ".pgm", ".webp")


class ImageReadError(ValueError):
    """An image file that cannot be decoded; the message names the file."""


def _to_float(array: np.ndarray, path: Path) -> np.ndarray:
    if array.dtype == np.uint8:
        return array.astype(np.float32) / 255.0
    if array.dtype in (np.uint16, np.int32) or array.dtype == np.dtype(">u2"):
        # PIL decodes 16-bit PNG/TIFF as int32 ("I") or uint16 ("I;16"): both hold 0..65535.
        return np.clip(array.astype(np.float32) / 65535.0, 0.0, 1.0)
    if array.dtype == bool:
        return array.astype(np.float32)
    if np.issubdtype(array.dtype, np.floating):
        return np.clip(array.astype(np.float32), 0.0, 1.0)
    raise ImageReadError(f"{path}: unsupported pixel type {array.dtype}")


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as float32 RGB ``[H, W, 3]`` in ``[0, 1]``.

    Accepts 8- and 16-bit, grayscale, palette, RGB and RGBA files. Raises
    :class:`ImageReadError` naming the file when it cannot be decoded.
    """
    path = Path(path)
    try:
        with Image.open(path) as image:
            image.load()
            if image.mode in ("P", "PA", "CMYK", "YCbCr", "LAB", "HSV", "1"):
                image = image.convert("RGBA" if "A" in image.mode else "RGB")
            array = np.asarray(image)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as error:
        raise ImageReadError(f"cannot read image {path}: {error}") from error
    pixels = _to_float(array, path)
    if pixels.ndim == 2:
        pixels = np.repeat(pixels[:, :, None], 3, axis=2)
    elif pixels.ndim == 3 and pixels.shape[2] in (2, 4):
        # Drop alpha; a grey+alpha image keeps its grey channel.
        pixels = pixels[:, :, :-1]
        if pixels.shape[2] == 1:
            pixels = np.repeat(pixels, 3, axis=2)
    if pixels.ndim != 3 or pixels.shape[2] != 3:
        raise ImageReadError(f"{path}: unexpected image shape {array.shape}")
    return np.ascontiguousarray(pixels)


def resize_image(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize a float image ``[H, W, C]`` to ``[height, width, C]`` with antialiased bilinear.

    Uses PIL's float mode per channel, so 16-bit inputs keep their precision.
    """
    if image.shape[0] == height and image.shape[1] == width:
        return image.astype(np.float32, copy=False)
    channels = [
        np.asarray(
            Image.fromarray(np.ascontiguousarray(image[:, :, c], dtype=np.float32)).resize(
                (width, height), Image.Resampling.BILINEAR
            )
        )
        for c in range(image.shape[2])
    ]
    return np.clip(np.stack(channels, axis=2), 0.0, 1.0).astype(np.float32)


def list_images(folder: str | Path) -> list[Path]:
    """Image files directly inside ``folder``, natural order (``2.jpg`` before ``10.jpg``)."""
    folder = Path(folder)
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    return sorted(files, key=lambda p: natural_key(p.name))


def natural_key(name: str) -> tuple:
    """Sort key that orders embedded integers numerically."""
    import re

    parts = re.split(r"(\d+)", name)
    return tuple((0, int(part), part) if part.isdigit() else (1, 0, part.lower()) for part in parts)

"""Reading and resizing images of any bit depth into one float RGB representation.

Every stage sees images as float32 arrays ``[H, W, 3]`` in ``[0, 1]``: grayscale
(thermal) images are repeated to three channels, 16-bit images are scaled by 65535,
alpha channels are dropped.

``resize_image`` resizes in one of two ways (``RESIZE_METHODS``):

- ``"linear"`` (default): OpenCV's ``cv2.resize(..., interpolation=cv2.INTER_LINEAR)``,
  which the published pipelines use for both the DINOv2 and the SAM input. Output pixel
  ``d`` samples the input at ``s = (d + 0.5) * in / out - 0.5`` with two-tap (bilinear)
  weights and no antialiasing, so shrinking by more than 2x skips input pixels. Borders
  follow OpenCV: ``s < 0`` takes pixel 0, ``floor(s) >= in - 1`` takes the last pixel
  (the same as clamping ``s`` to ``[0, in - 1]``), for enlarging and shrinking alike.
  Computed in float (source positions in float64), so it equals OpenCV's float-image
  result; OpenCV on 8-bit images rounds its weights to 11-bit fixed point and is
  within one grey level of it.
- ``"antialias"``: PIL's bilinear filter, which widens its support when shrinking
  (antialiasing); what vprflow used before it matched the published code.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
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
        # A float image has no declared range; guessing one per image (0-1, 0-255,
        # 0-65535) would scale two images of one dataset differently. Only [0, 1] is read.
        low, high = float(np.nanmin(array)), float(np.nanmax(array))
        if not (0.0 <= low and high <= 1.0):
            raise ImageReadError(
                f"{path}: floating-point image with values in [{low:g}, {high:g}]; only "
                "float images in [0, 1] are read. Convert it to 8- or 16-bit integers, or "
                "scale it to [0, 1]"
            )
        return array.astype(np.float32)
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


RESIZE_METHODS = ("linear", "antialias")


def resize_image(image: np.ndarray, width: int, height: int, method: str = "linear") -> np.ndarray:
    """Resize a float image ``[H, W, C]`` to float32 ``[height, width, C]`` in ``[0, 1]``.

    ``method`` is ``"linear"`` (OpenCV ``INTER_LINEAR``, the default) or ``"antialias"``
    (PIL bilinear); see the module docstring. Both keep the precision of 16-bit inputs.
    """
    if method not in RESIZE_METHODS:
        raise ValueError(f"unknown resize method {method!r}; expected one of {RESIZE_METHODS}")
    if image.ndim != 3:
        raise ValueError(f"expected an image [H, W, C], got shape {image.shape}")
    if width < 1 or height < 1:
        raise ValueError(f"cannot resize to {width}x{height}: both sides must be >= 1")
    if image.shape[0] == height and image.shape[1] == width:
        return image.astype(np.float32, copy=False)
    if method == "linear":
        resized = _resize_linear(np.asarray(image, dtype=np.float32), width, height)
    else:
        resized = _resize_antialias(image, width, height)
    return np.clip(resized, 0.0, 1.0).astype(np.float32, copy=False)


def _linear_taps(size_in: int, size_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OpenCV INTER_LINEAR along one axis: ``(low, high, weight_high)`` per output index."""
    position = (np.arange(size_out, dtype=np.float64) + 0.5) * (size_in / size_out) - 0.5
    low = np.floor(position)
    weight = position - low
    low = low.astype(np.intp)
    # OpenCV's border rule: before the first pixel centre take pixel 0, from the last
    # pixel centre on take the last pixel (one tap, weight 1).
    weight[low < 0] = 0.0
    low[low < 0] = 0
    last = low >= size_in - 1
    weight[last] = 0.0
    low[last] = size_in - 1
    high = np.minimum(low + 1, size_in - 1)
    return low, high, weight.astype(np.float32)


def _resize_linear(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Separable two-tap interpolation: rows first, then columns."""
    low, high, weight = _linear_taps(image.shape[0], height)
    weight = weight[:, None, None]
    rows = image[low] * (1.0 - weight) + image[high] * weight
    low, high, weight = _linear_taps(image.shape[1], width)
    weight = weight[None, :, None]
    return rows[:, low] * (1.0 - weight) + rows[:, high] * weight


def _resize_antialias(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """PIL bilinear in float mode, one channel at a time."""
    channels = [
        np.asarray(
            Image.fromarray(np.ascontiguousarray(image[:, :, c], dtype=np.float32)).resize(
                (width, height), Image.Resampling.BILINEAR
            )
        )
        for c in range(image.shape[2])
    ]
    return np.stack(channels, axis=2)


@dataclass(frozen=True)
class ImageScan:
    """Images found under a folder, natural order of their relative paths, and how
    many entries were passed over (hidden ones, and files that are not images)."""

    paths: list[Path]
    skipped_hidden: int = 0
    skipped_other: int = 0


def scan_images(folder: str | Path, recursive: bool = False) -> ImageScan:
    """Image files inside ``folder`` (and its subfolders when ``recursive``), in natural
    order of their path relative to ``folder`` (``2.jpg`` before ``10.jpg``, ``a/9.jpg``
    before ``b/1.jpg``). Hidden files and folders (``.name``) are skipped, as are files
    without an image suffix; both are counted.

    An entry with an image suffix that is not a readable file (a broken symbolic link,
    a folder named ``x.jpg``) is an error naming it: skipping it would shift every later
    index against the ground truth.
    """
    folder = Path(folder)
    candidates, hidden, other = [], 0, 0
    pending = [folder]
    while pending:
        current = pending.pop()
        for entry in current.iterdir():
            if entry.name.startswith("."):
                hidden += 1
            elif entry.suffix.lower() in IMAGE_SUFFIXES:
                candidates.append(entry)
            elif recursive and entry.is_dir():
                pending.append(entry)
            elif not entry.is_dir():
                other += 1
    unreadable = [p for p in candidates if not p.is_file() or not os.access(p, os.R_OK)]
    if unreadable:
        names = ", ".join(str(p) for p in sorted(unreadable)[:5])
        raise ImageReadError(
            f"{len(unreadable)} entr{'y' if len(unreadable) == 1 else 'ies'} in {folder} "
            f"look like images but are not readable files (broken link? folder?): {names}"
        )
    ordered = sorted(candidates, key=lambda p: natural_key(p.relative_to(folder).as_posix()))
    return ImageScan(ordered, hidden, other)


def list_images(folder: str | Path, recursive: bool = False) -> list[Path]:
    """The image paths of :func:`scan_images`."""
    return scan_images(folder, recursive).paths


def natural_key(name: str) -> tuple:
    """Sort key that orders embedded integers numerically."""
    import re

    parts = re.split(r"(\d+)", name)
    return tuple((0, int(part), part) if part.isdigit() else (1, 0, part.lower()) for part in parts)

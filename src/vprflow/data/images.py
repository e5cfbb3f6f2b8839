"""Finding, reading and resizing images of any bit depth into one float RGB representation.

Every stage sees images as float32 arrays ``[H, W, 3]`` in ``[0, 1]``: grayscale
(thermal) images are repeated to three channels, 16-bit images are scaled by 65535,
alpha channels are dropped. The EXIF Orientation tag is applied by default (as
``cv2.imread`` in SegVLAD's and AnyLoc's readers): phone photos store their pixels
rotated and say so in that tag (``EXIF_ORIENTATIONS``).

``resize_image`` resizes in one of three ways (``RESIZE_METHODS``):

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
  (antialiasing): SNSM's reader (torchvision ``Resize`` on a PIL image). An image whose
  values are all 8-bit levels (every 8-bit file) is resized as PIL resizes the 8-bit
  image, so the pixels equal the authors' bit for bit; others in float.
- ``"bicubic_antialias"``: torchvision's ``Resize(..., interpolation=BICUBIC,
  antialias=True)`` on the float tensor ``ToTensor`` makes, which is torch's
  ``interpolate(mode="bicubic", antialias=True, align_corners=False)``: Keys' cubic
  (a = -0.5), its support widened by the scale when shrinking, weights normalised; BoQ's
  reader. Computed by that torch call in float32, so it equals torchvision's bit for bit.
  Not clipped: the cubic's negative lobes overshoot [0, 1] at sharp edges (the shipped
  photos at 322 and 384 span -0.06 to 1.11), and torchvision leaves float tensors so.
"""

from __future__ import annotations

import functools
import io
import os
import re
import sys
import unicodedata
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from vprflow.core.files import link_loop
from vprflow.core.lazy import lazy_import

# Only the bicubic antialiased resize needs torch; the module stays importable without.
torch = lazy_import("torch")

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".ppm", ".pgm", ".webp")
# apply = rotate/flip the pixels as the EXIF Orientation tag says (cv2.imread, published
# SegVLAD/AnyLoc); ignore = the stored pixels (PIL without exif_transpose, SNSM's reader).
EXIF_ORIENTATIONS = ("apply", "ignore")


def dataset_orientation(setting: str) -> str:
    """The EXIF orientation of a dataset's own reads (its image sizes, a native
    resolution, the figures) for its ``exif_orientation`` setting: the setting, or for
    ``method`` (each method's stages read as its published reader: its aggregator's
    ``Aggregator.exif_orientation``) ``apply``, the image upright as people view it."""
    return "apply" if setting == "method" else setting


class ImageReadError(ValueError):
    """An image file that cannot be decoded; the message names the file."""


def _undeclared_integers(image: Image.Image) -> tuple[str, np.ndarray] | None:
    """``(what, values)`` of a decoded integer image whose type has no declared range
    that maps to ``[0, 1]``, else None. Read are unsigned 8- and 16-bit files (their
    range is ``[0, 2^bits - 1]``); PIL holds 16-bit PNG and PGM (scaled from their
    maxval to 65535) as 32-bit "I" too. Not read: 32-bit integer TIFFs (PIL holds
    unsigned ones as signed, 2^31 and above wrapped to negatives) and signed TIFFs of
    any width (PIL holds signed 8-bit ones as unsigned: -3 becomes 253)."""
    if image.format == "TIFF":
        bits = (image.tag_v2.get(258) or (1,))[0]
        signed = (image.tag_v2.get(339) or (1,))[0] == 2
        values = np.asarray(image)
        if signed and values.dtype.kind in "ui":
            if bits == 8:
                values = values.view(np.int8)  # PIL decodes them as unsigned
            return f"{bits}-bit signed integer", values
        if bits == 32 and values.dtype.kind in "ui":
            return "32-bit unsigned integer", values.view(np.uint32)
        return None
    if image.mode in ("I", "I;32", "I;32S") and image.format not in ("PNG", "PPM"):
        return "32-bit integer", np.asarray(image)
    return None


def _to_float(array: np.ndarray, path: Path) -> np.ndarray:
    if array.dtype == np.uint8:
        return array.astype(np.float32) / 255.0
    if array.dtype in (np.uint16, np.int32) or array.dtype == np.dtype(">u2"):
        # PIL decodes 16-bit files as uint16 ("I;16") or int32 ("I": PNG, PGM), both
        # in 0..65535 (decode_image refuses other integer files before this).
        low, high = int(array.min(initial=0)), int(array.max(initial=0))
        if low < 0 or high > 65535:
            raise ImageReadError(
                f"{path}: 16-bit image decoded with values in [{low}, {high}], outside "
                "[0, 65535]. Convert it to 8- or 16-bit unsigned integers"
            )
        return array.astype(np.float32) / 65535.0
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


def read_image(path: str | Path, exif_orientation: str = "apply") -> np.ndarray:
    """Read an image file as float32 RGB ``[H, W, 3]`` in ``[0, 1]``.

    Accepts 8- and 16-bit, grayscale, palette, RGB and RGBA files. Raises
    :class:`ImageReadError` naming the file when it cannot be decoded.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise ImageReadError(f"cannot read image {path}: {error}") from error
    return decode_image(data, path, exif_orientation)


def decode_image(data: bytes, path: str | Path, exif_orientation: str = "apply") -> np.ndarray:
    """:func:`read_image` of a file's bytes ``data`` (``path`` names it in errors)."""
    if exif_orientation not in EXIF_ORIENTATIONS:
        raise ValueError(f"exif_orientation must be one of {EXIF_ORIENTATIONS}")
    path = Path(path)
    try:
        with Image.open(io.BytesIO(data)) as image:
            image.load()
            undeclared = _undeclared_integers(image)
            if undeclared is not None:
                what, values = undeclared
                raise ImageReadError(
                    f"{path}: {what} image with values in [{values.min()}, {values.max()}]; "
                    "only unsigned 8- and 16-bit integer images (and floating-point "
                    "images in [0, 1]) have a range that maps to [0, 1], and guessing one "
                    "per image (clipping at 65535, or at 0) would scale two images of one "
                    "dataset differently. Convert the dataset to 16-bit unsigned integers "
                    "with one scale for every image"
                )
            if exif_orientation == "apply":
                image = ImageOps.exif_transpose(image)
            if image.mode in ("P", "PA", "CMYK", "YCbCr", "LAB", "HSV", "1"):
                image = image.convert("RGBA" if "A" in image.mode else "RGB")
            array = np.asarray(image)
    except ImageReadError:
        raise
    except Image.DecompressionBombError as error:
        raise ImageReadError(
            f"{path}: {error} Pillow refuses it as a possible decompression bomb; if the "
            "file is genuine, downscale it (every image is resized to the dataset's "
            "resolution anyway)"
        ) from error
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


RESIZE_METHODS = ("linear", "antialias", "bicubic_antialias")


# EXIF Orientation values that turn the stored pixels by 90 degrees (swap width and height).
_TRANSPOSING_ORIENTATIONS = (5, 6, 7, 8)


def image_size(path: str | Path, exif_orientation: str = "apply") -> tuple[int, int]:
    """``(width, height)`` of an image as :func:`read_image` returns it, from its header
    alone (no pixels decoded)."""
    if exif_orientation not in EXIF_ORIENTATIONS:
        raise ValueError(f"exif_orientation must be one of {EXIF_ORIENTATIONS}")
    try:
        with Image.open(path) as image:
            width, height = image.size
            orientation = image.getexif().get(0x0112) if exif_orientation == "apply" else None
    except (OSError, UnidentifiedImageError) as error:
        raise ImageReadError(f"cannot read image {path}: {error}") from error
    if orientation in _TRANSPOSING_ORIENTATIONS:
        return height, width
    return width, height


def resize_image(image: np.ndarray, width: int, height: int, method: str = "linear") -> np.ndarray:
    """Resize a float image ``[H, W, C]`` to float32 ``[height, width, C]`` in ``[0, 1]``
    (``"bicubic_antialias"``: as its cubic overshoots, unclipped).

    ``method`` is ``"linear"`` (OpenCV ``INTER_LINEAR``, the default), ``"antialias"``
    (PIL bilinear) or ``"bicubic_antialias"`` (torchvision's bicubic on a float tensor);
    see the module docstring. All keep the precision of 16-bit inputs.
    """
    if method not in RESIZE_METHODS:
        raise ValueError(f"unknown resize method {method!r}; expected one of {RESIZE_METHODS}")
    if image.ndim != 3:
        raise ValueError(f"expected an image [H, W, C], got shape {image.shape}")
    if width < 1 or height < 1:
        raise ValueError(f"cannot resize to {width}x{height}: both sides must be >= 1")
    if image.shape[0] == height and image.shape[1] == width:
        return image.astype(np.float32, copy=False)
    if method == "bicubic_antialias":
        return _resize_bicubic_antialias(image, width, height)
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
    """PIL bilinear: on the 8-bit image when every value is an 8-bit level (as SNSM
    resizes the decoded 8-bit file, with PIL's fixed-point arithmetic), else in float
    mode one channel at a time."""
    levels = np.rint(np.asarray(image, dtype=np.float32) * 255.0)
    if image.shape[2] == 3 and np.array_equal(levels / np.float32(255.0), image):
        resized = Image.fromarray(levels.astype(np.uint8), "RGB").resize(
            (width, height), Image.Resampling.BILINEAR
        )
        return np.asarray(resized, dtype=np.float32) / np.float32(255.0)
    channels = [
        np.asarray(
            Image.fromarray(np.ascontiguousarray(image[:, :, c], dtype=np.float32)).resize(
                (width, height), Image.Resampling.BILINEAR
            )
        )
        for c in range(image.shape[2])
    ]
    return np.stack(channels, axis=2)


def _resize_bicubic_antialias(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """torchvision's tensor ``Resize`` (bicubic, antialiased): the same torch call on the
    same contiguous float32 ``[1, C, H, W]`` tensor that ``ToTensor`` gives."""
    pixels = torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1), dtype=np.float32))
    resized = torch.nn.functional.interpolate(
        pixels[None], size=(height, width), mode="bicubic", align_corners=False, antialias=True
    )
    return np.ascontiguousarray(resized[0].permute(1, 2, 0).numpy())


@dataclass(frozen=True)
class ImageScan:
    """Images found under a folder, natural order of their relative paths, and how
    many entries were passed over (hidden ones, and files that are not images)."""

    paths: list[Path]
    skipped_hidden: int = 0
    skipped_other: int = 0
    real_paths: list[str] | None = None  # os.path.realpath of each path, when known


# Leading bytes of image formats, to tell an image with an unread suffix (a .gif, a
# .heic, a .jpg renamed .dat) from a file that is not an image.
_SIGNATURES = (
    (b"\xff\xd8\xff", "JPEG"),
    (b"\x89PNG\r\n\x1a\n", "PNG"),
    (b"GIF87a", "GIF"),
    (b"GIF89a", "GIF"),
    (b"II*\x00", "TIFF"),
    (b"MM\x00*", "TIFF"),
    (b"II+\x00", "BigTIFF"),
    (b"\x00\x00\x00\x0cjP  \r\n\x87\n", "JPEG 2000"),
    (b"\xffO\xffQ", "JPEG 2000"),
    (b"8BPS", "Photoshop"),
    (b"v/1\x01", "OpenEXR"),
    (b"\x00\x00\x01\x00", "ICO"),
)
_HEIF_BRANDS = {b"heic", b"heix", b"heim", b"heis", b"mif1", b"msf1", b"avif", b"avis"}


def image_format(head: bytes) -> str | None:
    """The image format the leading bytes of a file announce, or None."""
    for signature, name in _SIGNATURES:
        if head.startswith(signature):
            return name
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return "WebP"
    if head[:2] == b"BM" and head[6:10] == b"\x00\x00\x00\x00":
        return "BMP"
    if re.match(rb"P[1-7][ \t\r\n]", head):
        return "Netpbm"
    if head[4:8] == b"ftyp" and head[8:12] in _HEIF_BRANDS:
        return "HEIF/AVIF"
    return None


def _sniff(path: Path) -> str | None:
    try:
        with open(path, "rb") as f:
            return image_format(f.read(16))
    except OSError:
        return None


def _utf8(name: str) -> bool:
    """Whether a file name decoded from UTF-8 (Python keeps undecodable bytes as
    lone surrogates, which no UTF-8 text can hold)."""
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def _inside(path: str, folder: str) -> bool:
    return path == folder or path.startswith(folder.rstrip(os.sep) + os.sep)


def scan_images(
    folder: str | Path, recursive: bool = False, follow_links: bool = False
) -> ImageScan:
    """Image files inside ``folder`` (and its subfolders when ``recursive``), in the
    :func:`natural_key` order of their path relative to ``folder`` (``2.jpg`` before
    ``10.jpg``, ``a/9.jpg`` before ``b/1.jpg``). Hidden entries (``.name``) are skipped,
    as are files that are not images; both are counted.

    Never skipped, since skipping shifts every later index against the ground truth;
    each is an :class:`ImageReadError` naming it:

    - an entry with an image suffix that is not a readable file (a broken link, a
      link in a loop, a folder named ``x.jpg``);
    - a file whose content is an image in a format not read here (a ``.gif``), or an
      image under another suffix;
    - a symbolic link to a folder out of ``folder`` (unless ``follow_links``), and a
      folder or file reached twice (a link to a parent, or to a sibling, two links to
      one file): each real folder is visited and each real file read once, so
      discovery stays linear in the number of entries. A link to an image file is
      read wherever the file lies (datasets assembled from links: a subset, a split);
      a file that is both a reference and a query is refused by
      :func:`vprflow.data.datasets.check_disjoint`;
    - an image (or, when ``recursive``, a folder) whose name is not UTF-8 (bytes
      that do not decode, which Python keeps as surrogates): no store, table or log
      could hold its name. Named as ``repr``, with its folder.
    """
    folder = Path(folder)
    top = os.path.realpath(folder)
    # (sort key of the relative path, path, real path) of each image. DirEntry's cached
    # file types spare a stat per entry, and a file that is not a link is its folder's
    # real path plus its name, so only links are resolved (10^5 files in seconds).
    candidates: list[tuple[str, Path, str]] = []
    hidden = other = 0
    seen_dirs = {top: folder}
    seen_files: dict[str, Path] = {}
    refused: list[str] = []
    pending = [(folder, top, "")]
    while pending:
        current, current_real, prefix = pending.pop()
        with os.scandir(current) as listing:
            keyed = sorted((natural_key(e.name), e) for e in listing)
        for key, entry in keyed:
            name = entry.name
            if name.startswith("."):
                hidden += 1
                continue
            path = current / name
            is_image = os.path.splitext(name)[1].lower() in IMAGE_SUFFIXES
            is_link = entry.is_symlink()
            loop = link_loop(path) if is_link else None
            if loop:
                # Leads to no file (and os.stat raises ELOOP): an image name is refused
                # as a broken link is; another name is passed over, as one is.
                if is_image:
                    refused.append(
                        f"{path} is a link in a loop ({loop}), which leads to no file: "
                        "remove the links, or point one at the image"
                    )
                else:
                    other += 1
                continue
            followed = is_image or (recursive and entry.is_dir())
            if not _utf8(name) and (followed or _sniff(path)):
                refused.append(
                    f"in {current}, the name {name!r} is not UTF-8 (bytes "
                    f"{os.fsencode(name)!r}), so it cannot be stored or shown: rename it "
                    "(convmv -f <its encoding> -t utf8)"
                )
                continue
            real = os.path.realpath(path) if is_link else os.path.join(current_real, name)
            if followed and is_link and not follow_links and entry.is_dir():
                # A link to a file is read where the file lies; a broken link is
                # reported below, as unreadable.
                if not _inside(real, top):
                    refused.append(
                        f"{path} is a link to the folder {real}, outside {folder} (set "
                        "the dataset's follow_links: true to read the images in it)"
                    )
                    continue
            if is_image:
                if entry.is_file() and real in seen_files:
                    refused.append(
                        f"{path} is the file {seen_files[real]} again (a link): it "
                        "would count as two images; remove the link"
                    )
                    continue
                seen_files.setdefault(real, path)
                # In the top folder the relative path is the name: its key is known.
                candidates.append((key if not prefix else natural_key(prefix + name), path, real))
                continue
            if entry.is_dir():
                if not recursive:
                    continue
                if real in seen_dirs:
                    refused.append(
                        f"{path} is the folder {seen_dirs[real]} again (a link): its "
                        "images would be read twice; remove the link"
                    )
                    continue
                seen_dirs[real] = path
                pending.append((path, real, prefix + name + "/"))
                continue
            found = _sniff(path) if entry.is_file() else None
            if found:
                refused.append(
                    f"{path} is a {found} image, but only {', '.join(IMAGE_SUFFIXES)} "
                    "files are read: convert it to one of them, or move it out of the folder"
                )
            else:
                other += 1
    unreadable = [p for _, p, _ in candidates if not p.is_file() or not os.access(p, os.R_OK)]
    if unreadable:
        names = ", ".join(str(p) for p in sorted(unreadable)[:5])
        raise ImageReadError(
            f"{len(unreadable)} entr{'y' if len(unreadable) == 1 else 'ies'} in {folder} "
            f"look like images but are not readable files (broken link? folder?): {names}"
        )
    if refused:
        more = f" (and {len(refused) - 5} more)" if len(refused) > 5 else ""
        raise ImageReadError(
            f"{len(refused)} entr{'y' if len(refused) == 1 else 'ies'} in {folder} cannot "
            f"be read as the dataset's images: " + "; ".join(refused[:5]) + more
        )
    candidates.sort(key=lambda c: c[0])
    return ImageScan(
        [p for _, p, _ in candidates], hidden, other, real_paths=[r for _, _, r in candidates]
    )


_ASCII_NUMBER = re.compile(r"([0-9]+)")


@functools.cache
def _unicode_number() -> re.Pattern:
    """natsort's number pattern: a run of decimal digits of any script (``\\d``, such as
    ``٣٤``), or one digit that is no decimal (``²``, ``①``), from this Python's
    Unicode tables; built once, on the first name that is not ASCII."""
    lone = "".join(
        c
        for c in map(chr, range(sys.maxunicode + 1))
        if unicodedata.digit(c, None) is not None and unicodedata.decimal(c, None) is None
    )
    return re.compile(r"(\d+|[" + re.escape(lone) + "])")


def natural_key(name: str) -> tuple:
    """Sort key of ``natsort.natsorted``'s default order (``ns.INT``), the order in which
    the published readers (Revisit-Anything, AnyLoc) list images: a total order of the
    names alone, the same on every machine and file system.

    As natsort: the name is decomposed (Unicode NFD, so a macOS decomposed name sorts
    as its composed spelling); runs of decimal digits of any script compare as integers
    (``2.jpg`` before ``10.jpg``; ``٣`` is 3), a lone non-decimal digit (``²``) as its
    value; text by code point, case kept (``A.jpg``, ``B.jpg``, ``a.jpg``); a name that
    starts with a number sorts before one that starts with text (``1.png`` before
    ``a.png``). Names natsort calls equal (``01`` and ``1``, composed and decomposed
    spellings) are ordered by the exact name, where natsort keeps the listing's order:
    ``sorted(names, key=natural_key) == natsort.natsorted(sorted(names))``.
    """
    if name.isascii():
        parts = _ASCII_NUMBER.split(name)
    else:
        parts = _unicode_number().split(unicodedata.normalize("NFD", name))
    key: list = []
    for i, part in enumerate(parts):
        if not i % 2:
            if part:
                key.append(part)
            continue
        try:
            number = int(part)
        except ValueError:  # a lone digit that int() does not read: "²"
            number = unicodedata.digit(part)
        if not key or not isinstance(key[-1], str):
            key.append("")  # text and numbers alternate, as in natsort's key
        key.append(number)
    return (tuple(key), name)

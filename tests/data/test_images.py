"""Reading, finding and resizing images.

``resize_image``: OpenCV INTER_LINEAR ("linear"), PIL bilinear ("antialias", equal to
PIL's 8-bit result on 8-bit images) and torchvision's antialiased bicubic on a float
tensor ("bicubic_antialias", against a float64 formula); resizing a linear ramp must
reproduce the ramp at the output pixel centres within 1e-5. ``read_image``: 8-bit
values must equal v / 255 and 16-bit values v / 65535 within 1e-7 (float32 rounding),
the EXIF orientation as ``cv2.imread`` applies it. ``scan_images``: links, unread
formats and the order of names.

The reference for "linear" is a slow float64 double loop over output pixels written
from OpenCV's documented rule (``resize.cpp``): source position
``s = (d + 0.5) * in / out - 0.5``, ``s < 0`` takes pixel 0 and ``floor(s) >= in - 1``
takes the last pixel, otherwise two taps ``floor(s)``, ``floor(s) + 1`` with weights
``1 - frac(s)``, ``frac(s)``.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from vprflow.data.images import (
    EXIF_ORIENTATIONS,
    RESIZE_METHODS,
    ImageReadError,
    image_size,
    natural_key,
    read_image,
    resize_image,
    scan_images,
)

# (in_height, in_width, out_height, out_width)
SHAPES = {
    "down 2x": (120, 160, 60, 80),
    "down non-integer": (120, 160, 61, 97),
    "down more than 2x": (90, 70, 17, 23),
    "up": (30, 40, 77, 53),
    "rows up, columns down": (20, 90, 47, 31),
    "rows down, columns up": (64, 12, 9, 29),
    "to a single pixel": (5, 7, 1, 1),
}


def _taps(dst: int, size_in: int, size_out: int) -> tuple[int, int, float]:
    source = (dst + 0.5) * size_in / size_out - 0.5
    low = math.floor(source)
    frac = source - low
    if low < 0:
        return 0, 0, 0.0
    if low >= size_in - 1:
        return size_in - 1, size_in - 1, 0.0
    return low, low + 1, frac


def _opencv_linear_loop(image: np.ndarray, width: int, height: int) -> np.ndarray:
    image = image.astype(np.float64)
    out = np.empty((height, width, image.shape[2]))
    for y in range(height):
        y0, y1, fy = _taps(y, image.shape[0], height)
        for x in range(width):
            x0, x1, fx = _taps(x, image.shape[1], width)
            top = (1 - fx) * image[y0, x0] + fx * image[y0, x1]
            bottom = (1 - fx) * image[y1, x0] + fx * image[y1, x1]
            out[y, x] = (1 - fy) * top + fy * bottom
    return out


@pytest.mark.parametrize("shape", list(SHAPES.values()), ids=list(SHAPES))
def test_linear_matches_the_opencv_formula(shape):
    in_h, in_w, out_h, out_w = shape
    image = np.random.default_rng(in_h * out_w).random((in_h, in_w, 3), dtype=np.float32)
    out = resize_image(image, out_w, out_h)
    assert out.shape == (out_h, out_w, 3) and out.dtype == np.float32
    expected = _opencv_linear_loop(image, out_w, out_h)
    # float32 arithmetic on values in [0, 1]: rounding errors are ~1e-7.
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-5)


def test_linear_is_the_default_and_has_no_antialiasing():
    # Shrinking 4x with two taps reads only columns 1, 2 of each group of 4 (the source
    # position falls half-way between them); antialiasing would blend all four.
    image = np.zeros((4, 16, 3), np.float32)
    image[:, 1::4] = 1.0
    image[:, 2::4] = 0.5
    linear = resize_image(image, 4, 4)
    np.testing.assert_allclose(linear, 0.75, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(resize_image(image, 4, 4, method="linear"), linear)
    assert np.abs(resize_image(image, 4, 4, method="antialias") - 0.75).max() > 0.1


@pytest.mark.parametrize("shape", list(SHAPES.values()), ids=list(SHAPES))
def test_linear_within_one_grey_level_of_cv2_on_8bit(shape):
    cv2 = pytest.importorskip("cv2")
    in_h, in_w, out_h, out_w = shape
    pixels = np.random.default_rng(in_w * out_h).integers(0, 256, (in_h, in_w, 3), np.uint8)
    expected = cv2.resize(pixels, (out_w, out_h), interpolation=cv2.INTER_LINEAR)
    out = resize_image(pixels.astype(np.float32) / 255, out_w, out_h)
    # OpenCV rounds its 8-bit weights to 11-bit fixed point and its result to integers.
    assert np.abs(out * 255 - expected).max() <= 1.0


def test_linear_matches_cv2_on_float_images():
    cv2 = pytest.importorskip("cv2")
    image = np.random.default_rng(5).random((45, 38, 3), dtype=np.float32)
    for out_w, out_h in ((17, 29), (83, 61), (19, 90)):
        expected = cv2.resize(image, (out_w, out_h), interpolation=cv2.INTER_LINEAR)
        out = resize_image(image, out_w, out_h)
        np.testing.assert_allclose(out, expected, rtol=0, atol=1e-5)  # both float32


@pytest.mark.parametrize("shape", list(SHAPES.values()), ids=list(SHAPES))
def test_antialias_is_pil_bilinear(shape):
    in_h, in_w, out_h, out_w = shape
    image = np.random.default_rng(in_h + out_h).random((in_h, in_w, 3), dtype=np.float32)
    out = resize_image(image, out_w, out_h, method="antialias")
    assert out.shape == (out_h, out_w, 3) and out.dtype == np.float32
    for c in range(3):
        channel = Image.fromarray(image[:, :, c].copy()).resize(
            (out_w, out_h), Image.Resampling.BILINEAR
        )
        np.testing.assert_array_equal(out[:, :, c], np.clip(np.asarray(channel), 0, 1))


@pytest.mark.parametrize("method", RESIZE_METHODS)
def test_same_size_is_unchanged(method):
    image = np.random.default_rng(6).random((9, 11, 3), dtype=np.float32)
    np.testing.assert_array_equal(resize_image(image, 11, 9, method=method), image)


def test_unknown_method_is_refused():
    image = np.zeros((4, 4, 3), np.float32)
    with pytest.raises(ValueError, match=r"'cubic'.*'linear', 'antialias'"):
        resize_image(image, 2, 2, method="cubic")


def test_antialias_on_8bit_images_equals_pil_on_the_8bit_image_bit_for_bit():
    # SNSM's reader: PIL.Image.open(...).convert("RGB"), then torchvision Resize on the
    # PIL image, which is Image.resize(..., BILINEAR) in PIL's 8-bit arithmetic.
    rng = np.random.default_rng(7)
    for in_h, in_w, out_h, out_w in SHAPES.values():
        pixels = rng.integers(0, 256, (in_h, in_w, 3), dtype=np.uint8)
        published = Image.fromarray(pixels, "RGB").resize((out_w, out_h), Image.Resampling.BILINEAR)
        ours = resize_image(pixels.astype(np.float32) / 255.0, out_w, out_h, method="antialias")
        np.testing.assert_array_equal(ours * 255.0, np.asarray(published, dtype=np.float32))


def _keys_cubic(x: float) -> float:
    """Keys' cubic convolution kernel with a = -0.5."""
    a, x = -0.5, abs(x)
    if x < 1:
        return (a + 2) * x**3 - (a + 3) * x**2 + 1
    if x < 2:
        return a * x**3 - 5 * a * x**2 + 8 * a * x - 4 * a
    return 0.0


def _antialiased_bicubic_weights(size_in: int, size_out: int) -> np.ndarray:
    """float64 ``[size_out, size_in]``: output pixel ``d`` is centred at input coordinate
    ``c = (d + 0.5) * scale`` (``scale = in / out``, pixel ``j`` covering ``[j, j + 1)``);
    when shrinking the kernel is stretched by ``scale`` (support ``2 * scale`` pixels each
    side), taps are the pixels whose centres lie within the support (cut at the borders)
    and the weights are divided by their sum."""
    scale = size_in / size_out
    stretch = max(scale, 1.0)
    weights = np.zeros((size_out, size_in))
    for d in range(size_out):
        centre = (d + 0.5) * scale
        first = max(int(centre - 2 * stretch + 0.5), 0)
        stop = min(int(centre + 2 * stretch + 0.5), size_in)
        for j in range(first, stop):
            weights[d, j] = _keys_cubic((j + 0.5 - centre) / stretch)
        weights[d] /= weights[d].sum()
    return weights


BICUBIC_SHAPES = {**SHAPES, "corridor to BoQ-DINOv2's 322 x 322": (120, 160, 322, 322)}


@pytest.mark.parametrize("shape", BICUBIC_SHAPES.values(), ids=BICUBIC_SHAPES.keys())
def test_bicubic_antialias_equals_the_antialiased_keys_cubic_formula(shape):
    in_h, in_w, out_h, out_w = shape
    image = np.random.default_rng(in_w + out_w).random((in_h, in_w, 3), dtype=np.float32)
    out = resize_image(image, out_w, out_h, method="bicubic_antialias")
    assert out.shape == (out_h, out_w, 3) and out.dtype == np.float32
    rows = _antialiased_bicubic_weights(in_h, out_h)
    columns = _antialiased_bicubic_weights(in_w, out_w)
    expected = np.einsum("yi,ijc,xj->yxc", rows, image.astype(np.float64), columns, optimize=True)
    # torch computes in float32, tap positions too: a centre near coordinate n is off by
    # up to n * 2^-24 pixels, which moves the result by that times the kernel's slope
    # (< 1.5) summed over the taps of random [0, 1] values; measured: 1.4e-5 at 322 px.
    size = max(shape)
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-6 + 2.0**-23 * size * 2)


def test_bicubic_antialias_keeps_the_overshoot_torchvision_keeps():
    # A sharp edge: the cubic's negative lobes ring below 0 and above 1, and torchvision's
    # tensor Resize does not clamp float images.
    image = np.zeros((8, 8, 3), np.float32)
    image[:, 4:] = 1.0
    out = resize_image(image, 19, 8, method="bicubic_antialias")
    assert out.min() < -0.01 and out.max() > 1.01


def test_resize_image_reproduces_a_linear_ramp():
    height, width = 6, 40
    ramp = np.tile(np.linspace(0.1, 0.9, width, dtype=np.float32), (height, 1))
    image = np.stack([ramp, 1 - ramp, np.full_like(ramp, 0.25)], axis=2)
    step = 0.8 / (width - 1)

    def value_at(x):  # the ramp at input column coordinate x (pixel centres at integers)
        return 0.1 + step * x

    for new_width in (20, 13, 80):
        out = resize_image(image, new_width, height)
        assert out.shape == (height, new_width, 3) and out.dtype == np.float32
        scale = width / new_width
        centres = (np.arange(new_width) + 0.5) * scale - 0.5
        # Away from the borders (where the filter is truncated) a linear ramp stays exact.
        margin = int(math.ceil(2 * max(scale, 1.0)))
        inner = slice(margin, new_width - margin)
        expected = np.broadcast_to(value_at(centres[inner]), (height, len(centres[inner])))
        np.testing.assert_allclose(out[:, inner, 0], expected, rtol=0, atol=1e-5)
        np.testing.assert_allclose(out[:, inner, 1], 1 - expected, rtol=0, atol=1e-5)
        np.testing.assert_allclose(out[:, :, 2], 0.25, atol=1e-6)  # constants stay constant
        assert out.min() >= 0.0 and out.max() <= 1.0
    same = resize_image(image, width, height)
    np.testing.assert_array_equal(same, image)


def test_resize_keeps_16bit_precision():
    image = np.full((8, 8, 3), 1000 / 65535, dtype=np.float32)
    image[:, 4:] = 1001 / 65535
    out = resize_image(image, 4, 4)
    assert out[0, 0, 0] == pytest.approx(1000 / 65535, abs=1e-8)
    assert out[0, 3, 0] == pytest.approx(1001 / 65535, abs=1e-8)


# ------------------------------------------------------------------ reading


def exif_rotated(pixels: np.ndarray, path, orientation: int = 6) -> None:
    """Save ``pixels`` as a phone does for a portrait photo: the pixels turned 90 degrees
    (stored as a landscape image) and an EXIF Orientation tag saying how to turn back."""
    stored = np.rot90(pixels, k=1)  # orientation 6 = rotate 90 degrees clockwise to view
    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(np.ascontiguousarray(stored)).save(path, exif=exif.tobytes())


def test_exif_orientation_is_applied_by_default_and_ignored_on_request(tmp_path):
    pixels = np.random.default_rng(3).integers(0, 256, (6, 10, 3), dtype=np.uint8)
    exif_rotated(pixels, tmp_path / "photo.png")
    upright = read_image(tmp_path / "photo.png")
    np.testing.assert_array_equal(upright, pixels.astype(np.float32) / 255.0)
    stored = read_image(tmp_path / "photo.png", exif_orientation="ignore")
    np.testing.assert_array_equal(stored, np.rot90(pixels, k=1).astype(np.float32) / 255.0)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_image_size_from_the_header_is_the_read_images_size(tmp_path, orientation):
    pixels = np.zeros((6, 10, 3), dtype=np.uint8)
    exif_rotated(pixels, tmp_path / "photo.png", orientation)
    for exif in EXIF_ORIENTATIONS:
        height, width = read_image(tmp_path / "photo.png", exif_orientation=exif).shape[:2]
        assert image_size(tmp_path / "photo.png", exif) == (width, height)


def test_image_size_of_a_file_that_is_not_an_image_names_it(tmp_path):
    (tmp_path / "a.jpg").write_text("not an image")
    with pytest.raises(ImageReadError, match="a.jpg"):
        image_size(tmp_path / "a.jpg")


def test_exif_orientation_matches_cv2_imread(tmp_path):
    cv2 = pytest.importorskip("cv2")
    pixels = np.random.default_rng(4).integers(0, 256, (16, 24, 3), dtype=np.uint8)
    for orientation in range(1, 9):
        path = tmp_path / f"o{orientation}.jpg"
        exif = Image.Exif()
        exif[0x0112] = orientation
        Image.fromarray(pixels).save(path, exif=exif.tobytes(), quality=95)
        published = cv2.imread(str(path))[:, :, ::-1]  # BGR -> RGB, EXIF applied
        np.testing.assert_array_equal(read_image(path) * 255.0, published.astype(np.float32))


def test_a_decompression_bomb_names_the_file_and_the_remedy(tmp_path, monkeypatch):
    Image.fromarray(np.zeros((40, 40, 3), np.uint8)).save(tmp_path / "huge.png")
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 100)  # 40 x 40 > 2 x 100
    with pytest.raises(ImageReadError, match=r"huge\.png: .*decompression bomb.*downscale it"):
        read_image(tmp_path / "huge.png")


def test_read_8bit_rgb(tmp_path):
    pixels = np.random.default_rng(0).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    Image.fromarray(pixels, "RGB").save(tmp_path / "rgb.png")
    image = read_image(tmp_path / "rgb.png")
    assert image.shape == (5, 7, 3) and image.dtype == np.float32
    np.testing.assert_allclose(image, pixels / 255.0, rtol=0, atol=1e-7)


@pytest.mark.parametrize(("low", "high"), [(0.0, 255.0), (-0.5, 0.5)])
def test_float_image_outside_unit_range_is_refused_naming_file_and_range(tmp_path, low, high):
    # A 0-255 float TIFF used to be clipped to [0, 1]: 98% white, no error.
    pixels = np.linspace(low, high, 20, dtype=np.float32).reshape(4, 5)
    Image.fromarray(pixels, "F").save(tmp_path / "float.tif")
    with pytest.raises(ImageReadError, match=rf"float\.tif.*\[{low:g}, {high:g}\]"):
        read_image(tmp_path / "float.tif")


def test_float_image_in_unit_range_is_read_as_is(tmp_path):
    pixels = np.random.default_rng(3).uniform(0, 1, (4, 5)).astype(np.float32)
    Image.fromarray(pixels, "F").save(tmp_path / "float.tif")
    np.testing.assert_array_equal(read_image(tmp_path / "float.tif")[:, :, 1], pixels)


def test_read_grayscale_is_repeated(tmp_path):
    pixels = np.random.default_rng(1).integers(0, 256, (4, 6), dtype=np.uint8)
    Image.fromarray(pixels, "L").save(tmp_path / "grey.png")
    image = read_image(tmp_path / "grey.png")
    assert image.shape == (4, 6, 3)
    for c in range(3):
        np.testing.assert_allclose(image[:, :, c], pixels / 255.0, rtol=0, atol=1e-7)


def test_read_16bit_grayscale(tmp_path):
    pixels = np.random.default_rng(2).integers(0, 65536, (6, 5), dtype=np.uint16)
    pixels[0, 0], pixels[0, 1] = 0, 65535
    Image.fromarray(pixels).save(tmp_path / "thermal.png")
    assert Image.open(tmp_path / "thermal.png").mode.startswith("I")
    image = read_image(tmp_path / "thermal.png")
    assert image.shape == (6, 5, 3)
    for c in range(3):
        np.testing.assert_allclose(image[:, :, c], pixels / 65535.0, rtol=0, atol=1e-7)
    # 16-bit precision survives: neighbouring levels stay distinct (8-bit would merge them).
    assert image[0, 1, 0] == 1.0 and image[0, 0, 0] == 0.0


@pytest.mark.parametrize(
    "dtype, values, what",
    [
        # A thermal image in raw counts: 80% of it above 65535, which used to read white.
        (np.int32, (0, 70000, 300000), "32-bit signed integer"),
        (np.uint32, (0, 70000, 3_000_000_000), "32-bit unsigned integer"),
        (np.uint32, (0, 100, 65535), "32-bit unsigned integer"),  # the type decides
        (np.int16, (-40, 0, 120), "16-bit signed integer"),  # negatives used to read 0
        (np.int16, (0, 1, 2), "16-bit signed integer"),
        (np.int8, (-3, 0, 100), "8-bit signed integer"),  # -3 used to read as 253
    ],
)
def test_integer_images_without_a_declared_range_are_refused_naming_type_and_values(
    tmp_path, dtype, values, what
):
    tifffile = pytest.importorskip("tifffile")
    pixels = np.array([values, values[::-1]], dtype=dtype)
    tifffile.imwrite(tmp_path / "thermal.tif", pixels)
    low, high = min(values), max(values)
    message = rf"thermal\.tif: {what} image with values in \[{low}, {high}\]; only unsigned"
    with pytest.raises(ImageReadError, match=message):
        read_image(tmp_path / "thermal.tif")


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_unsigned_8_and_16bit_tiffs_are_read_over_their_declared_range(tmp_path, dtype):
    tifffile = pytest.importorskip("tifffile")
    top = np.iinfo(dtype).max
    pixels = np.array([[0, 1, top // 2, top]], dtype=dtype)
    tifffile.imwrite(tmp_path / "image.tif", pixels)
    image = read_image(tmp_path / "image.tif")
    np.testing.assert_allclose(image[:, :, 0], pixels / top, rtol=0, atol=1e-7)


def test_a_16bit_pgm_is_read_over_its_maxval(tmp_path):
    # Netpbm declares its range in the header (here 10-bit); PIL scales it to 65535.
    (tmp_path / "ten.pgm").write_bytes(
        b"P5\n3 1\n1023\n" + np.array([0, 512, 1023], ">u2").tobytes()
    )
    np.testing.assert_allclose(
        read_image(tmp_path / "ten.pgm")[0, :, 0], [0, 512 / 1023, 1], rtol=0, atol=1e-4
    )


def test_read_rgba_drops_alpha(tmp_path):
    pixels = np.random.default_rng(3).integers(0, 256, (3, 4, 4), dtype=np.uint8)
    pixels[..., 3] = 0  # fully transparent: colours must still come through unchanged
    Image.fromarray(pixels, "RGBA").save(tmp_path / "rgba.png")
    np.testing.assert_allclose(
        read_image(tmp_path / "rgba.png"), pixels[..., :3] / 255.0, rtol=0, atol=1e-7
    )


def test_read_palette_image(tmp_path):
    palette = np.array([[255, 0, 0], [0, 128, 255], [10, 20, 30]], dtype=np.uint8)
    index = np.random.default_rng(4).integers(0, 3, (5, 6), dtype=np.uint8)
    image = Image.fromarray(index, "P")
    image.putpalette(palette.ravel().tolist())
    image.save(tmp_path / "palette.png")
    np.testing.assert_allclose(
        read_image(tmp_path / "palette.png"), palette[index] / 255.0, rtol=0, atol=1e-7
    )


def test_read_corrupt_image_names_the_file(tmp_path):
    garbage = tmp_path / "broken.jpg"
    garbage.write_bytes(b"\xff\xd8 definitely not a jpeg")
    with pytest.raises(ImageReadError, match="broken.jpg"):
        read_image(garbage)
    Image.fromarray(np.zeros((64, 64, 3), np.uint8) + 7).save(tmp_path / "whole.png")
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes((tmp_path / "whole.png").read_bytes()[:60])
    with pytest.raises(ImageReadError, match="truncated.png"):
        read_image(truncated)
    with pytest.raises(ImageReadError, match="missing.png"):
        read_image(tmp_path / "missing.png")


# ------------------------------------------------------------------ discovery


def write_pngs(folder: Path, names: list[str]) -> None:
    for name in names:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(folder / name)


def test_a_link_to_a_folder_out_of_the_folder_is_refused_unless_links_are_followed(tmp_path):
    write_pngs(tmp_path / "ds", ["ref/1.png", "query/1.png", "query/2.png"])
    (tmp_path / "ds/ref/loop").symlink_to("..")  # would read every query as a reference
    with pytest.raises(
        ImageReadError, match=r"ref/loop is a link to the folder .*outside .*follow_links"
    ):
        scan_images(tmp_path / "ds/ref", recursive=True)
    # Followed, the dataset folder is read once: its ref/ is the folder itself again.
    with pytest.raises(ImageReadError, match=r"ref/loop/ref is the folder .*ref again"):
        scan_images(tmp_path / "ds/ref", recursive=True, follow_links=True)


def test_links_to_image_files_elsewhere_are_read_by_default_each_real_file_once(tmp_path):
    # A subset assembled from links into shared storage: read without follow_links.
    write_pngs(tmp_path / "shared", ["1.png", "2.png", "3.png"])
    (tmp_path / "subset").mkdir()
    for name in ("2.png", "3.png"):
        (tmp_path / "subset" / name).symlink_to(tmp_path / "shared" / name)
    scan = scan_images(tmp_path / "subset")
    assert [p.name for p in scan.paths] == ["2.png", "3.png"]
    assert scan.real_paths == [str(tmp_path / "shared" / n) for n in ("2.png", "3.png")]
    # The same real file through a second link would be two images: refused.
    (tmp_path / "subset/4.png").symlink_to(tmp_path / "shared/3.png")
    with pytest.raises(ImageReadError, match=r"subset/4\.png is the file .*subset/3\.png again"):
        scan_images(tmp_path / "subset")


def test_a_link_to_an_image_folder_elsewhere_is_read_when_asked(tmp_path):
    write_pngs(tmp_path / "elsewhere", ["1.png", "2.png"])
    (tmp_path / "ref").mkdir()
    (tmp_path / "ref/run1").symlink_to(tmp_path / "elsewhere")
    scan = scan_images(tmp_path / "ref", recursive=True, follow_links=True)
    assert [p.relative_to(tmp_path / "ref").as_posix() for p in scan.paths] == [
        "run1/1.png",
        "run1/2.png",
    ]
    # A linked role folder is the folder itself: nothing inside leaves it.
    (tmp_path / "linked").symlink_to(tmp_path / "elsewhere")
    assert len(scan_images(tmp_path / "linked", recursive=True).paths) == 2


def test_discovery_knows_each_images_real_path_without_resolving_every_file(tmp_path):
    # Real paths come from the folder's real path plus the name, links resolved alone:
    # they must equal os.path.realpath through linked folders, linked files and a
    # linked role folder.
    write_pngs(tmp_path / "elsewhere", ["1.png", "sub/2.png"])
    write_pngs(tmp_path / "ref", ["a/3.png"])
    write_pngs(tmp_path / "other", ["5.png"])
    (tmp_path / "ref/run1").symlink_to(tmp_path / "elsewhere")
    (tmp_path / "ref/4.png").symlink_to(tmp_path / "other/5.png")
    (tmp_path / "linked").symlink_to(tmp_path / "ref")
    scan = scan_images(tmp_path / "linked", recursive=True, follow_links=True)
    assert len(scan.paths) == 4
    assert scan.real_paths == [os.path.realpath(p) for p in scan.paths]


def test_links_to_the_folder_itself_stay_linear_and_are_named(tmp_path):
    # Two links to "." used to multiply the paths at every level until memory ran out.
    write_pngs(tmp_path / "q", ["1.png"])
    (tmp_path / "q/a").symlink_to(".")
    (tmp_path / "q/b").symlink_to(".")
    with pytest.raises(ImageReadError, match=r"q/a is the folder .*q again.*q/b is the folder"):
        scan_images(tmp_path / "q", recursive=True)


def test_an_image_linked_twice_in_one_folder_is_refused(tmp_path):
    write_pngs(tmp_path / "ref", ["1.png"])
    (tmp_path / "ref/2.png").symlink_to("1.png")
    with pytest.raises(ImageReadError, match=r"ref/2\.png is the file .*ref/1\.png again"):
        scan_images(tmp_path / "ref")


def test_an_image_whose_name_is_not_utf8_is_named_with_its_folder(tmp_path):
    write_pngs(tmp_path / "q", ["1.png"])
    raw = os.path.join(os.fsencode(tmp_path / "q"), b"caf\xe9.png")  # a Latin-1 name
    with open(raw, "wb") as f:
        f.write((tmp_path / "q/1.png").read_bytes())
    with open(os.path.join(os.fsencode(tmp_path / "q"), b"notes\xe9.txt"), "wb") as f:
        f.write(b"not an image: skipped")
    with pytest.raises(ImageReadError) as error:
        scan_images(tmp_path / "q")
    message = str(error.value)
    assert f"in {tmp_path / 'q'}, the name 'caf\\udce9.png' is not UTF-8" in message
    assert "b'caf\\xe9.png'" in message and "notes" not in message
    message.encode("utf-8")  # the message itself can be printed and logged


@pytest.mark.parametrize(
    "name, content, found",
    [
        ("0003.gif", b"GIF89a\x01\x00\x01\x00", "GIF"),
        ("0003.heic", b"\x00\x00\x00\x18ftypheic\x00\x00", "HEIF/AVIF"),
        ("0003.jpg.bak", b"\xff\xd8\xff\xe0\x00\x10JFIF", "JPEG"),
        ("0003", b"\x89PNG\r\n\x1a\n\x00\x00", "PNG"),
    ],
)
def test_an_image_in_a_format_not_read_is_named_never_skipped(tmp_path, name, content, found):
    # Skipped, it would shift every later query against the ground truth.
    write_pngs(tmp_path / "query", ["0001.png", "0002.png", "0004.png"])
    (tmp_path / "query" / name).write_bytes(content)
    (tmp_path / "query/notes.txt").write_text("GIF89a is a format")  # text: skipped
    with pytest.raises(ImageReadError, match=rf"query/{re.escape(name)} is a {found} image"):
        scan_images(tmp_path / "query")


def test_the_order_is_a_total_order_of_names_whatever_the_file_system_lists_first(tmp_path):
    names = ["B.png", "a.png", "A.png", "b.png", "01.png", "1.png", "x²1.png", "x٣.png"]
    orders = []
    for trial, listing in enumerate((names, names[::-1])):
        folder = tmp_path / str(trial)
        write_pngs(folder, listing)  # creation order differs between the two copies
        orders.append([p.name for p in scan_images(folder).paths])
    assert orders[0] == orders[1]
    # natsort's: numbers first, equal numbers by name, then text by code point, case kept.
    assert orders[0] == ["01.png", "1.png", "A.png", "B.png", "a.png", "b.png", "x²1.png", "x٣.png"]
    # Decomposed (macOS) and composed spellings of a name sort alike.
    assert natural_key("e\u0301.png")[0] == natural_key("\u00e9.png")[0]


# Names on which a home-made natural order and natsort's part ways.
ADVERSARIAL_NAMES = [
    # case: natsort compares code points ("A" < "B" < "a"), never case-folded
    *("A.jpg", "a.jpg", "B.jpg", "b.jpg", "Img3.jpg", "img1.jpg", "x.JPG", "x.jpg", "_a.jpg"),
    # a leading number sorts before text; leading zeros and digit runs
    *("1.png", "a.png", "01.png", "001.png", "10.png", "9.png", "0.png", "00.png"),
    *("img2.jpg", "img02.jpg", "img10.jpg", "a1b2.jpg", "a1b02.jpg", "a01b2.jpg", "a10b.jpg"),
    *("2024-01-05_7.jpg", "2024-1-5_10.jpg", "v1.10.jpg", "v1.9.jpg", "-1.jpg", "+1.jpg"),
    *("a 1.jpg", "a_1.jpg", "a-1.jpg", "a1.jpg", "a.jpg.jpg", "12345678901234567890.jpg"),
    # Unicode digits: Arabic-Indic and full-width runs are numbers, "²" and "①" lone digits
    *("x٣.png", "x٣٤.png", "x34.png", "x1٣.png", "x²1.png", "x².png", "x①.png", "x３.png"),
    *("²", "2", "٢", "½.png", "Ⅻ.png"),
    # Unicode text: composed and decomposed spellings, ligatures, other scripts
    *("é.png", "e\u0301.png", "f.png", "Ä.png", "ä.png", "ß.png", "ss.png", "ﬁ.png", "fi.png"),
    *("日本2.png", "日本10.png", "Ω.png", "ω.png", "🙂1.png", "🙂01.png"),
]


@pytest.mark.parametrize("seed", range(5))
def test_names_are_ordered_as_natsort_natsorted_orders_them(seed):
    natsort = pytest.importorskip("natsort")
    names = list(ADVERSARIAL_NAMES)
    np.random.default_rng(seed).shuffle(names)
    # natsort keeps the listing's order among names it calls equal (01 and 1): a sorted
    # listing is the total order that natural_key breaks those ties by.
    assert sorted(names, key=natural_key) == natsort.natsorted(sorted(names))
    # Paths relative to the role folder too (recursive discovery).
    paths = [f"{a}/{b}" for a, b in zip(names, reversed(names), strict=True)]
    assert sorted(paths, key=natural_key) == natsort.natsorted(sorted(paths))


def test_a_mixed_case_folder_is_listed_in_the_published_readers_order(tmp_path):
    # A Nardo-Air variant: position-given ground truth only holds in natsort's order.
    names = ["img_b.png", "IMG_A.png", "img_a.png", "IMG_B.png", "3.png", "a.png"]
    write_pngs(tmp_path, names)
    listed = [p.name for p in scan_images(tmp_path).paths]
    assert listed == ["3.png", "IMG_A.png", "IMG_B.png", "a.png", "img_a.png", "img_b.png"]


def test_recursive_discovery_orders_relative_paths_naturally_and_counts_skips(tmp_path):
    write_pngs(tmp_path, ["b/2.png", "b/10.png", "a/x/1.png", "3.png", ".hidden.png"])
    (tmp_path / ".cache").mkdir()
    write_pngs(tmp_path / ".cache", ["9.png"])
    (tmp_path / "notes.txt").write_text("not an image")
    scan = scan_images(tmp_path, recursive=True)
    assert [p.relative_to(tmp_path).as_posix() for p in scan.paths] == [
        "3.png",
        "a/x/1.png",
        "b/2.png",
        "b/10.png",
    ]
    assert (scan.skipped_hidden, scan.skipped_other) == (2, 1)
    flat = scan_images(tmp_path, recursive=False)
    assert [p.name for p in flat.paths] == ["3.png"]

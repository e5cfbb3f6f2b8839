"""``resize_image``: OpenCV INTER_LINEAR ("linear") and PIL bilinear ("antialias").

The reference for "linear" is a slow float64 double loop over output pixels written
from OpenCV's documented rule (``resize.cpp``): source position
``s = (d + 0.5) * in / out - 0.5``, ``s < 0`` takes pixel 0 and ``floor(s) >= in - 1``
takes the last pixel, otherwise two taps ``floor(s)``, ``floor(s) + 1`` with weights
``1 - frac(s)``, ``frac(s)``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import Image

from vprflow.images import RESIZE_METHODS, resize_image

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

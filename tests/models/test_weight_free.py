"""The weight-free models' own arithmetic (DAISY's grey image, SLIC's Lab conversion)
against direct float64 formulas: both are taken elementwise, so that they round alike on
every CPU (tests/workflow/test_code_paths.py runs them under the code paths).

Tolerances: the grey image equals the formula bit for bit (the same float64 operations
in the same order); the Lab image is float32, within 2e-4 of skimage's float64 rgb2lab
(Lab values up to ~100: a few float32 ulps).
"""

from __future__ import annotations

import numpy as np
from skimage.color import rgb2gray, rgb2lab
from skimage.segmentation import slic, slic_superpixels

from vprflow.models.backbones import GREY_WEIGHTS, grey_image
from vprflow.models.segmenters import SlicSegmenter, labels_to_masks, rgb_to_lab


def random_image(seed: int, height: int = 23, width: int = 31) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, 1, (height, width, 3)).astype(np.float32)


def test_the_grey_image_is_rgb2grays_weighted_sum_in_float64():
    image = random_image(0)
    expected = np.empty(image.shape[:2])
    r, g, b = GREY_WEIGHTS
    for i in range(image.shape[0]):
        for j in range(image.shape[1]):
            red, green, blue = (float(v) for v in image[i, j])
            expected[i, j] = r * red + g * green + b * blue
    grey = grey_image(image)
    assert grey.dtype == np.float64
    np.testing.assert_array_equal(grey, expected)
    np.testing.assert_allclose(grey, rgb2gray(image.astype(np.float64)), rtol=0, atol=1e-15)


def test_slics_lab_conversion_is_rgb2lab_within_float32():
    image = random_image(1)
    lab = rgb_to_lab(image)
    assert lab.dtype == np.float32 and lab.shape == image.shape
    np.testing.assert_allclose(lab, rgb2lab(image.astype(np.float64)), rtol=0, atol=2e-4)


def test_slic_converts_with_it_and_leaves_skimages_own_conversion_in_place(monkeypatch):
    """The segmenter's SLIC converts with rgb_to_lab (its masks here are skimage's own:
    the two conversions differ by float32 rounding, which moves no pixel of this image),
    and scikit-image's module keeps its rgb2lab after the call."""
    from vprflow.models import segmenters

    image = random_image(2, 48, 64)
    calls = []
    monkeypatch.setattr(
        segmenters, "rgb_to_lab", lambda rgb: calls.append(rgb.shape) or rgb_to_lab(rgb)
    )
    published = slic_superpixels.rgb2lab
    masks = SlicSegmenter(n_segments=12, compactness=10.0, sigma=1.0).masks(image)
    assert calls == [(1, 48, 64, 3)]
    assert slic_superpixels.rgb2lab is published
    labels = slic(image, n_segments=12, compactness=10.0, sigma=1.0, start_label=0, channel_axis=-1)
    np.testing.assert_array_equal(masks, labels_to_masks(labels))
    assert masks.sum(axis=0).max() == 1 and masks.any(axis=0).all()

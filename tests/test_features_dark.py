"""A target in deep shadow is still a target: the image's noise estimate and the SNR black-space test.

``noise_sigma_grey`` is pinned to the standard deviation of the noise added to synthetic images
(flat, and with a smooth texture it must not mistake for noise); ``bright_pixels`` with
``black_snr`` to a dark textured square on a noisy black sky, which the absolute ``black_level``
misses; ``target_mask`` uses it only when ``black_level`` leaves nothing selectable.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from trackmeter.core.features import FeatureParams, bright_pixels, noise_sigma_grey, target_mask


def _quantise(img: np.ndarray) -> np.ndarray:
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("sigma", [2.0, 3.2, 6.0])
def test_noise_estimate_on_a_flat_image(sigma: float) -> None:
    rng = np.random.default_rng(0)
    img = _quantise(80.0 + rng.normal(0.0, sigma, (512, 726)))
    # Rounding to integers adds 1/12 grey² of variance.
    assert noise_sigma_grey(img) == pytest.approx(np.sqrt(sigma**2 + 1 / 12), rel=0.03)


def test_noise_estimate_ignores_a_smooth_texture() -> None:
    rng = np.random.default_rng(1)
    texture = cv2.GaussianBlur(rng.normal(0.0, 1.0, (512, 726)), (0, 0), 4.0)
    texture *= 40.0 / texture.std()  # a strong texture, smooth on the pixel scale
    img = _quantise(100.0 + texture + rng.normal(0.0, 3.2, texture.shape))
    assert noise_sigma_grey(img) == pytest.approx(np.sqrt(3.2**2 + 1 / 12), rel=0.1)
    assert img.std() > 10 * noise_sigma_grey(img)


def test_a_target_in_deep_shadow_is_found_by_its_signal_to_noise() -> None:
    """Sky at grey 4 with noise 3.2 (the harsh_light camera); a textured square at grey ~10."""
    rng = np.random.default_rng(2)
    img = np.full((300, 400), 4.0)
    tex = cv2.GaussianBlur(rng.normal(0.0, 1.0, (120, 160)), (0, 0), 2.0)
    img[90:210, 120:280] = 10.0 + 3.0 * tex / tex.std()
    img = _quantise(img + rng.normal(0.0, 3.2, img.shape))
    inner = np.zeros(img.shape, bool)
    inner[95:205, 125:275] = True
    sky = np.ones(img.shape, bool)
    sky[80:220, 110:290] = False
    absolute = bright_pixels(img, FeatureParams()).astype(bool)
    snr = bright_pixels(img, FeatureParams(black_snr=5.0), snr=True).astype(bool)
    assert absolute[inner].mean() < 0.1  # below black_level 16: black space
    assert snr[inner].mean() > 0.9  # the darkest texture cells sit at the sky level
    assert snr[sky].mean() < 0.001
    # A selectable patch there (8x8 plus the margin, clear of the darkest cells): none before.
    assert target_mask(img, FeatureParams(black_snr=0.0)).sum() == 0
    assert (target_mask(img, FeatureParams(black_snr=5.0)) > 0)[inner].mean() > 0.2


def test_the_signal_to_noise_test_is_only_the_fallback_of_a_dark_image() -> None:
    """With a bright patch anywhere (black_level finds a target), the shadowed square stays out."""
    rng = np.random.default_rng(4)
    img = np.full((300, 400), 4.0)
    img[90:210, 120:280] = 10.0
    img[20:80, 300:380] = 120.0 + 20.0 * rng.random((60, 80))
    img = _quantise(img + rng.normal(0.0, 3.2, img.shape))
    params = FeatureParams(black_snr=5.0)
    np.testing.assert_array_equal(target_mask(img, params), target_mask(img, FeatureParams(black_snr=0.0)))
    assert target_mask(img, params)[20:80, 300:380].any()


def test_black_snr_off_is_the_absolute_level() -> None:
    rng = np.random.default_rng(3)
    img = rng.integers(0, 255, (64, 64), dtype=np.uint8)
    np.testing.assert_array_equal(bright_pixels(img, FeatureParams(black_level=40)), (img > 40).astype(np.uint8))
    off = FeatureParams(black_level=40, black_snr=0.0)
    np.testing.assert_array_equal(bright_pixels(img, off, snr=True), (img > 40).astype(np.uint8))

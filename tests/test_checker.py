"""ccdn.checker: the Sampler's box means, cropped or not, and the image noise estimate."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ccdn.checker import Sampler, image_noise


def test_cropped_sampler_means_equal_the_whole_frames(examples):
    """A Sampler integrating only around a few corners of a large frame gives the whole frame's
    means, near them and (once a box reaches past its window, which then grows) anywhere else,
    off the image included."""
    gray = cv2.imread(str(examples["board"]["path"]), cv2.IMREAD_GRAYSCALE)
    big = cv2.resize(gray, (2560, 1920), interpolation=cv2.INTER_CUBIC)  # 4.9 Mpx
    corners = (examples["board"]["corners"] + 0.5) * 4 - 0.5
    few = corners[np.argsort(corners.sum(1))[:4]]  # the board's four top-left corners
    whole, cropped = Sampler(big), Sampler(big, (few, 40.0))
    top, bottom, left, right = cropped._window
    assert (bottom - top) * (right - left) < big.size / 4  # it did crop

    near = few[:, None] + np.array([[-15.0, -10.0], [0.0, 0.0], [12.0, 18.0]])  # (4, 3, 2) inside the window
    radius = np.array([[1], [3], [6], [12]])
    np.testing.assert_array_equal(cropped.mean(near, radius), whole.mean(near, radius))
    assert cropped._window == (top, bottom, left, right)  # nothing reached past it

    mid_x, mid_y = (left + right) // 2, (top + bottom) // 2
    for past in ([left + 4, mid_y], [right - 5, mid_y], [mid_x, top + 4], [mid_x, bottom - 5]):
        point = np.array([past], np.float64)  # a box of radius 5 around it is one pixel past a side of the window
        once = Sampler(big, (few, 40.0))
        np.testing.assert_array_equal(once.mean(point, 5), whole.mean(point, 5))
        assert once._window != (top, bottom, left, right)  # it grew

    everywhere = np.concatenate([corners, [[2559.4, 1919.4], [-3.0, 50.0], [1300.0, 2000.0]]])
    np.testing.assert_array_equal(cropped.mean(everywhere, 5), whole.mean(everywhere, 5))
    assert np.isnan(cropped.mean(everywhere, 5)[-2:]).all()  # centres off the image


def test_image_noise_reads_the_added_noise(examples):
    gray = cv2.imread(str(examples["board"]["path"]), cv2.IMREAD_GRAYSCALE)
    assert image_noise(gray) < 2.0
    noisy = np.clip(gray + np.random.default_rng(0).normal(0, 12, gray.shape), 0, 255).astype(np.uint8)
    assert image_noise(noisy) == pytest.approx(12, rel=0.15)
    assert image_noise(np.zeros((2, 2), np.uint8)) == 0.0


def test_a_sampler_estimates_its_images_noise_once(examples):
    gray = cv2.imread(str(examples["board"]["path"]), cv2.IMREAD_GRAYSCALE)
    noisy = np.clip(gray + np.random.default_rng(1).normal(0, 8, gray.shape), 0, 255).astype(np.uint8)
    sampler = Sampler(noisy, (np.array([[100.0, 100.0]]), 20.0))
    assert sampler.noise() == image_noise(noisy) == pytest.approx(8, rel=0.15)

"""Exposure changes measured at tracked points and undone before tracking (estimation.exposure)."""

from __future__ import annotations

import cv2
import numpy as np

from estimation.exposure import _box_mean, exposure_gain, integral, match_exposure


def _texture(seed: int = 0, shape: tuple[int, int] = (480, 640)) -> np.ndarray:
    """A smooth random texture in 40..200 (no saturation), float32."""
    rng = np.random.default_rng(seed)
    noise = rng.uniform(0.0, 1.0, (shape[0] // 8, shape[1] // 8)).astype(np.float32)
    img = cv2.resize(noise, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    img = cv2.GaussianBlur(img, (0, 0), 3.0)
    img = (img - img.min()) / (img.max() - img.min())
    return 40.0 + 160.0 * img


def _points(n: int = 200, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).uniform([20.0, 20.0], [620.0, 460.0], (n, 2)).astype(np.float32)


def test_gain_is_measured_through_a_motion_and_a_rough_prediction() -> None:
    """The scene moves 6 px right and the exposure drops to 0.7 (then rises to 1.3); the points'
    predicted positions are 3 px off the truth. The gain comes back within 2 %."""
    tex = _texture()
    prev = np.clip(np.rint(tex), 0, 255).astype(np.uint8)
    shifted = np.roll(tex, 6, axis=1)
    px = _points()
    guess = px + np.float32([6.0 + 3.0, -3.0])
    for gain in (0.7, 1.3):
        cur = np.clip(np.rint(shifted * gain), 0, 255).astype(np.uint8)
        assert abs(exposure_gain(integral(prev), integral(cur), px, guess, 35) - gain) < 0.02 * gain


def test_steady_exposure_is_left_alone() -> None:
    """No gain change: exactly 1.0 (the images untouched), also when half the scene is new."""
    tex = _texture()
    prev = np.clip(np.rint(tex), 0, 255).astype(np.uint8)
    cur_same = np.clip(np.rint(np.roll(tex, 6, axis=1)), 0, 255).astype(np.uint8)
    px = _points()
    assert exposure_gain(integral(prev), integral(cur_same), px, px + np.float32([6.0, 0.0]), 35) == 1.0
    other = np.clip(np.rint(_texture(seed=5)), 0, 255).astype(np.uint8)
    mixed = cur_same.copy()
    mixed[:, 320:] = other[:, 320:]  # half of the scene replaced: its ratios spread both ways
    assert exposure_gain(integral(prev), integral(mixed), px, px + np.float32([6.0, 0.0]), 35) == 1.0
    assert exposure_gain(integral(prev), integral(cur_same), px[:10], px[:10], 35) == 1.0  # too few points to tell


def test_match_exposure_scales_the_brighter_image_down() -> None:
    tex = _texture()
    dark = np.clip(np.rint(tex * 0.8), 0, 255).astype(np.uint8)
    bright = np.clip(np.rint(tex), 0, 255).astype(np.uint8)
    a, b = match_exposure(dark, bright, 1.25)
    assert a is dark and np.abs(b.astype(int) - dark.astype(int)).max() <= 1
    a, b = match_exposure(bright, dark, 0.8)
    assert b is dark and np.abs(a.astype(int) - dark.astype(int)).max() <= 1
    a, b = match_exposure(dark, bright, 1.0)
    assert a is dark and b is bright


def test_half_size_integral_gives_the_square_means_of_the_full_image() -> None:
    """The integral is of the image halved (an odd size loses its last row and column): a square's
    mean read from it is the full image's own within a grey level, and a brighter copy (x1.2) of
    an odd-sized image measures 1.2."""
    img = np.clip(np.rint(_texture(shape=(371, 641))), 0, 255).astype(np.uint8)
    integ = integral(img)
    assert integ.dtype == np.int32 and integ.shape == (185 + 1, 320 + 1)
    halved = cv2.resize(img[:370, :640], (320, 185), interpolation=cv2.INTER_AREA)
    assert integ[-1, -1] == int(halved.astype(np.int64).sum())
    px = np.random.default_rng(2).uniform([0.0, 0.0], [641.0, 371.0], (200, 2)).astype(np.float32)
    for x, y in px[:40]:
        cx, cy = 2 * int(x * 0.5), 2 * int(y * 0.5)  # the square: 8 half-size pixels each side (cell 35)
        direct = img[max(cy - 16, 0) : min(cy + 18, 370), max(cx - 16, 0) : min(cx + 18, 640)].mean()
        assert abs(_box_mean(integ, float(x), float(y), 35 // 4) - direct) < 1.0
    brighter = np.clip(np.rint(img.astype(np.float64) * 1.2), 0, 255).astype(np.uint8)
    assert abs(exposure_gain(integral(img), integral(brighter), px, px, 35) - 1.2) < 0.01

"""The LK tracker on shared pyramids (estimation.lk) against OpenCV's calcOpticalFlowPyrLK."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from estimation.lk import ImagePyramid, PyramidCache, lk_track, pyramid_of
from flightkit.datasets.registry import open_sequence
from flightkit.errors import EstimationError


def _opencv(a: np.ndarray, b: np.ndarray, pts: np.ndarray, win: int, levels: int) -> tuple[np.ndarray, np.ndarray]:
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 10, 0.03)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(
        a, b, pts.reshape(-1, 1, 2), None, winSize=(win, win), maxLevel=levels, criteria=crit
    )  # type: ignore[call-overload]
    return p1.reshape(-1, 2), st.ravel() == 1


@pytest.mark.parametrize(
    ("name", "win", "levels"), [("tum_fr1rpy_000_199", 11, 3), ("kitti06_stereo", 9, 3), ("tum_fr1rpy_000_199", 15, 1)]
)
def test_tracks_real_frames_as_opencv_does(shared_data: Path, name: str, win: int, levels: int) -> None:
    """On real consecutive frames (corners up to the image edges, a few that get lost) the status
    agrees with OpenCV's on >= 99 % of points and nearly all positions to 0.05 px (OpenCV rounds
    to fixed point, so on an ambiguous patch the two may settle on different answers)."""
    frames = list(open_sequence(shared_data / name).frames(10, 12))
    a, b = frames[0].gray, frames[1].gray
    pts = cv2.goodFeaturesToTrack(a, 300, 0.01, 6).reshape(-1, 2).astype(np.float32)
    ref, st = _opencv(a, b, pts, win, levels)
    p1, ok = lk_track(ImagePyramid.build(a, 3), ImagePyramid.build(b, 3), pts, None, levels, win, 10, 0.03)
    assert np.mean(ok == st) >= 0.99
    both = ok & st
    assert both.sum() > 0.8 * len(pts)
    d = np.linalg.norm(p1[both] - ref[both], axis=1)
    assert np.median(d) < 1e-3
    assert np.mean(d < 0.05) > 0.94  # (the rest: windows whose steps oscillate until the iteration cap)
    assert np.mean(d > 0.5) < 0.01


def test_start_position_is_used_and_lost_windows_fail() -> None:
    """A start near the answer is refined to it with no pyramid; a window that starts outside
    the image, or on a flat patch, is not ok."""
    rng = np.random.default_rng(0)
    big = cv2.GaussianBlur(rng.integers(0, 256, (300, 400)).astype(np.uint8), (0, 0), 2.0)
    a = np.ascontiguousarray(big[20:260, 20:340])
    b = np.ascontiguousarray(big[27:267, 8:328])  # content moves by (+12, -7) px
    a[:, :60] = 100  # a flat strip: nothing to track there
    pts = np.array([[150.0, 120.0], [200.0, 80.0], [-50.0, 10.0], [30.0, 100.0]], np.float32)
    start = pts + np.float32([11.0, -6.0])
    p1, ok = lk_track(ImagePyramid.build(a, 3), ImagePyramid.build(b, 3), pts, start, 0, 11, 20, 0.01)
    np.testing.assert_allclose(p1[:2] - pts[:2], [[12.0, -7.0], [12.0, -7.0]], atol=0.05)
    assert ok.tolist() == [True, True, False, False]


def test_pyramid_cache_builds_each_image_once_and_checks_the_window() -> None:
    img = np.zeros((120, 160), np.uint8)
    other = np.zeros((120, 160), np.uint8)
    cache = PyramidCache(levels=3, max_win_px=15, size=2)
    first = cache(img)
    assert cache(img) is first  # found again
    assert first.levels == 2  # 160x120 -> 80x60 -> 40x30; a third (20x15) is not taller than the window
    cache(other)
    cache(np.zeros((120, 160), np.uint8))  # a third image pushes the least recently used out
    assert cache(img) is not first
    assert pyramid_of(first, 3, 15) is first  # as many levels as this window allows
    assert pyramid_of(first, 3, 21).pad_px == 23  # a larger window needs a wider border: built again
    with pytest.raises(EstimationError, match="does not fit the pyramids"):
        lk_track(first, first, np.zeros((1, 2), np.float32), win_px=21)
    with pytest.raises(EstimationError, match="one start per point"):
        lk_track(first, first, np.zeros((3, 2), np.float32), np.zeros((2, 2), np.float32), win_px=11)
    with pytest.raises(EstimationError, match="8-bit grey"):
        ImagePyramid.build(np.zeros((10, 10), np.float32))


def test_non_finite_points_and_tiny_images_fail_cleanly() -> None:
    """NaN or infinite positions and starts are not ok (and read nothing outside the image); an
    image smaller than the window tracks nothing but does not fail."""
    rng = np.random.default_rng(1)
    img = cv2.GaussianBlur(rng.integers(0, 256, (120, 160)).astype(np.uint8), (0, 0), 1.5)
    pyr = ImagePyramid.build(img, 3)
    nan, inf = np.float32(np.nan), np.float32(np.inf)
    pts = np.array([[nan, 50.0], [60.0, inf], [80.0, 60.0], [80.0, 60.0], [-inf, -inf]], np.float32)
    start = pts.copy()
    start[3] = (nan, nan)
    p1, ok = lk_track(pyr, pyr, pts, start, 3, 11)
    assert ok.tolist() == [False, False, True, False, False]
    np.testing.assert_allclose(p1[2], [80.0, 60.0], atol=0.01)
    tiny = ImagePyramid.build(np.full((6, 8), 90, np.uint8), 3)
    assert tiny.levels == 0
    p1, ok = lk_track(tiny, tiny, np.array([[3.0, 3.0]], np.float32), win_px=11)
    assert not ok.any()


@pytest.mark.parametrize("shape", [(480, 640), (481, 641), (370, 1226), (37, 53), (12, 9)])
@pytest.mark.parametrize("win", [5, 11, 21])
def test_pyramid_levels_are_pyrdown_padded_by_reflection(shape: tuple[int, int], win: int) -> None:
    rng = np.random.default_rng(shape[0] + win)
    image = rng.integers(0, 256, shape, dtype=np.uint8)
    pyr = ImagePyramid.build(image, 4, win)
    pad = win + 2
    level = image
    for k in range(pyr.levels + 1):
        if k:
            level = cv2.pyrDown(level)
        h, w = level.shape
        assert tuple(pyr.sizes[k]) == (w, h)
        got = pyr.flat[pyr.offsets[k] : pyr.offsets[k] + (h + 2 * pad) * (w + 2 * pad)].reshape(h + 2 * pad, -1)
        assert np.array_equal(got, cv2.copyMakeBorder(level, pad, pad, pad, pad, cv2.BORDER_REFLECT_101))
    # as OpenCV: no level whose next one is not larger than the window
    assert pyr.levels == 4 or not ((level.shape[1] + 1) // 2 > win and (level.shape[0] + 1) // 2 > win)
    assert pyr.offsets[-1] + (h + 2 * pad) * (w + 2 * pad) == len(pyr.flat)

"""The row stereo matcher (``estimation.stereo.row_disparity``) on synthetic rectified pairs: a
slanted plane seen by a right camera with another gain and offset, repeated texture, flat
patches; and the keyframe stereo of the front end (``VoOptions.stereo_matcher``) on that plane."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from estimation.camera_geometry import CameraGeometry
from estimation.features import GridDetector
from estimation.stereo import row_disparity, sparse_disparity
from estimation.vo_options import VoOptions
from flightkit.datasets.base import CameraIntrinsics
from flightkit.errors import EstimationError

H, W = 240, 400
A_PX, B, C = 14.0, 0.04, 0.03
"""The plane's disparity at a right pixel (x, y): ``A_PX + B x + C y``."""


def texture(seed: int = 0, cell_px: int = 4) -> np.ndarray:
    """Blurred noise (float32) of ``cell_px`` grains: corners everywhere."""
    rng = np.random.default_rng(seed)
    img = rng.uniform(0, 255, (H // cell_px, W // cell_px)).astype(np.float32)
    img = cv2.resize(img, (W, H), interpolation=cv2.INTER_CUBIC)
    return cv2.GaussianBlur(img, (0, 0), 1.0)


def slanted_pair(gain: float, offset: float) -> tuple[np.ndarray, np.ndarray]:
    """Left texture and the right view of it as a slanted plane: right(x, y) = gain left(x + d, y) + offset."""
    left = texture()
    xr, yr = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    d = A_PX + B * xr + C * yr
    right = cv2.remap(left, xr + d, yr, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    to8 = lambda a: np.clip(np.rint(a), 0, 255).astype(np.uint8)  # noqa: E731
    return to8(left), to8(gain * right + offset)


def true_disparity(pts: np.ndarray) -> np.ndarray:
    """The plane's disparity at left pixels: x_r + A + B x_r + C y = u."""
    u, v = pts[:, 0].astype(np.float64), pts[:, 1].astype(np.float64)
    xr = (u - A_PX - C * v) / (1.0 + B)
    return u - xr


def corners(left: np.ndarray) -> np.ndarray:
    """Grid corners whose match lies well inside the right image."""
    pts = GridDetector(300, 20).detect(left)
    return pts[pts[:, 0] > 60]


def test_row_disparity_is_subpixel_under_a_gain_and_offset() -> None:
    left, right = slanted_pair(gain=0.75, offset=25.0)
    pts = corners(left)
    # Off-grid points too (tracked corners are not on whole pixels).
    pts = np.concatenate([pts, pts[:40] + np.float32([0.37, 0.61])])
    disp, ok = row_disparity(left, right, pts, 0.0, 120.0, win_px=11)
    assert ok.mean() > 0.9
    err = np.abs(disp[ok] - true_disparity(pts[ok]))
    # The bound is the pair's own: 8-bit rounding and the 4 % slant (LK started at the truth
    # with no gain change does as well: median 0.031 px, 95th percentile 0.09 px).
    assert np.median(err) < 0.05
    assert np.percentile(err, 95) < 0.1
    # LK (plain SSD) on the same pair, started at 0 as for a first keyframe, keeps far fewer.
    _, ok_lk = sparse_disparity(left, right, pts, 0.0, win_px=11)
    assert ok.sum() > ok_lk.sum()


def test_row_disparity_rejects_repeated_texture_and_flat_patches() -> None:
    x = np.arange(W, dtype=np.float32)
    stripes = 128 + 80 * np.sin(2 * np.pi * x / 9.0)
    left = np.tile(stripes, (H, 1)).astype(np.uint8)
    right = np.roll(left, -12, axis=1)
    pts = np.array([[u, 120.0] for u in range(80, 360, 20)], np.float32)
    _, ok = row_disparity(left, right, pts, 0.0, 60.0)
    assert not ok.any()  # every period matches as well as the true one: ambiguous
    flat = np.full((H, W), 90, np.uint8)
    _, ok_flat = row_disparity(flat, flat, pts, 0.0, 60.0)
    assert not ok_flat.any()


def test_row_disparity_rejects_a_pair_that_does_not_match() -> None:
    left = texture(cell_px=2).astype(np.uint8)
    other = texture(seed=5, cell_px=2).astype(np.uint8)
    pts = corners(left)
    _, ok = row_disparity(left, other, pts, 0.0, 120.0)
    assert ok.mean() < 0.05


def test_row_disparity_refuses_images_of_different_sizes() -> None:
    left, right = slanted_pair(1.0, 0.0)
    with pytest.raises(EstimationError, match="one size"):
        row_disparity(left, right[:, :-1], corners(left), 0.0, 50.0)


@pytest.mark.parametrize(
    ("matcher", "min_kept", "max_err_px"), [("lk", 0.0, None), ("row", 0.9, 0.15), ("row+lk", 0.9, 1.0)]
)
def test_keyframe_stereo_of_each_matcher_on_a_darker_right_camera(
    matcher: str, min_kept: float, max_err_px: float | None
) -> None:
    """A new keyframe's corners on the slanted plane, the right camera 25 % darker and offset (as
    EuRoC's pair differs). Measured: LK alone from the keyframe's guess (0 px) keeps 53 %, some of
    them 25 px off; the row search keeps all, within 0.14 px; ``row+lk`` keeps all with LK's
    measurement where the two agree (LK's gain bias: median 0.11 px, at most 0.54 px)."""
    left, right = slanted_pair(gain=0.75, offset=25.0)
    intr = CameraIntrinsics(300.0, 300.0, W / 2, H / 2, W, H)
    opts = VoOptions(stereo_matcher=matcher, far_points="drop").for_camera(intr.fx, intr.width)
    geo = CameraGeometry(intr, 0.1, None, opts, use_depth_images=False)
    pts = corners(left)
    X, ok = geo.points_3d(pts, right, left, None, 0.0)
    err = np.abs(intr.fx * 0.1 / X[ok, 2] - true_disparity(pts[ok]))
    if max_err_px is None:
        assert ok.mean() < 0.6
    else:
        assert ok.mean() >= min_kept
        assert err.max() < max_err_px


def test_stereo_matcher_option_is_checked() -> None:
    with pytest.raises(EstimationError, match="stereo_matcher"):
        VoOptions(stereo_matcher="sgbm")


def test_row_disparity_takes_unbounded_ranges_flat_patches_and_one_point() -> None:
    left, right = slanted_pair(1.0, 0.0)
    pts = corners(left)[:20]
    d_inf, ok_inf = row_disparity(left, right, pts, 0.0, np.inf)  # no upper limit: the image's width
    d_wide, ok_wide = row_disparity(left, right, pts, 0.0, float(W))
    np.testing.assert_array_equal(ok_inf, ok_wide)
    assert ok_inf.mean() > 0.9
    np.testing.assert_allclose(d_inf[ok_inf], d_wide[ok_wide])
    flat = np.full((H, W), 90, np.uint8)
    _, ok_flat = row_disparity(flat, flat, pts, 0.0, 40.0, min_std=0.0)  # no division by a zero norm
    assert not ok_flat.any()
    d_one, ok_one = row_disparity(left, right, pts[0], 0.0, 60.0)  # a single (2,) point
    assert d_one.shape == (1,) and ok_one[0] == ok_inf[0]


def test_row_match_below_the_minimum_disparity_overrules_a_wrong_lk_match() -> None:
    """``row+lk``: the row search finds the true 1.5 px, below the 3 px minimum (far points dropped);
    an LK match one texture period off (forced here) must not stand: the points are dropped."""
    rng = np.random.default_rng(3)
    grain = cv2.resize(rng.uniform(-1, 1, (H // 3, W // 3)).astype(np.float32), (W, H), interpolation=cv2.INTER_CUBIC)
    xs, ys = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))

    def scene(shift_px: float) -> np.ndarray:
        x = xs + shift_px
        grains = cv2.remap(grain, x, ys, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        img = 128 + 30 * np.sin(2 * np.pi * x / 9.0) + 110 * grains
        return np.clip(img, 0, 255).astype(np.uint8)

    left, right = scene(0.0), scene(1.5)
    pts = np.array([[u, v] for u in range(60, 340, 14) for v in range(20, 220, 14)], np.float32)
    intr = CameraIntrinsics(300.0, 300.0, W / 2, H / 2, W, H)
    opts = VoOptions(stereo_matcher="row+lk", far_points="drop").for_camera(intr.fx, intr.width)
    geo = CameraGeometry(intr, 0.1, None, opts, use_depth_images=False)
    real_lk = geo._lk_disparity

    def lk_one_period_off(*args: object, levels: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        if levels is None:  # the first pass (a keyframe's LK from its guess)
            n = len(args[2])  # type: ignore[arg-type]
            return np.full(n, 10.5, np.float32), np.ones(n, bool)
        return real_lk(*args, levels=levels)  # type: ignore[arg-type]

    geo._lk_disparity = lk_one_period_off  # type: ignore[method-assign]
    _, ok = geo.points_3d(pts, right, left, None, 0.0)
    assert ok.mean() < 0.05

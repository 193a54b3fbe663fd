"""Stereo: sparse disparity along rows, SGBM, ORB row matching and triangulation, on a
synthetic rectified pair whose right image is the left one shifted by a known disparity."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from estimation.features import DescriptorExtractor, Features, GridDetector
from estimation.matching import match_descriptors, match_stereo_rows
from estimation.stereo import DenseDisparity, StereoRig, sparse_disparity, triangulate
from flightkit.errors import EstimationError

RIG = StereoRig(fx=300.0, fy=300.0, cx=159.5, cy=119.5, baseline_m=0.12)


def texture(h: int = 240, w: int = 400, seed: int = 0) -> np.ndarray:
    """Blurred noise with corners: trackable everywhere."""
    rng = np.random.default_rng(seed)
    img = rng.uniform(0, 255, (h // 4, w // 4)).astype(np.float32)
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(cv2.GaussianBlur(img, (0, 0), 1.0), 0, 255).astype(np.uint8)


def pair(disparity_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Left 320x240 and right = left content shifted left by the disparity (a plane at Z = fB/d)."""
    big = texture()
    left = np.ascontiguousarray(big[:, 40:360])
    right = np.ascontiguousarray(big[:, 40 + disparity_px : 360 + disparity_px])
    return left, right


def test_rig_rejects_zero_baseline() -> None:
    with pytest.raises(EstimationError, match="baseline"):
        StereoRig(300.0, 300.0, 160.0, 120.0, 0.0)


@pytest.mark.parametrize("d", [4, 12, 30])
def test_sparse_disparity_finds_the_shift(d: int) -> None:
    left, right = pair(d)
    pts = GridDetector(200, 24).detect(left)
    pts = pts[(pts[:, 0] > 40)]  # points whose match is inside the right image
    disp, ok = sparse_disparity(left, right, pts, init_disparity_px=float(d) * 0.7)
    assert ok.mean() > 0.9
    np.testing.assert_allclose(disp[ok], d, atol=0.1)


def test_sparse_disparity_rejects_rows_that_do_not_match() -> None:
    left, right = pair(10)
    right = np.roll(right, 6, axis=0)  # vertical misalignment: not a rectified pair any more
    pts = GridDetector(200, 24).detect(left)
    pts = pts[(pts[:, 0] > 40) & (pts[:, 1] > 20) & (pts[:, 1] < 220)]
    _, ok = sparse_disparity(left, right, pts, init_disparity_px=10.0, max_dy_px=1.0)
    assert ok.mean() < 0.05


def test_triangulate_depth_and_range_checks() -> None:
    pts = np.array([[159.5, 119.5], [259.5, 19.5], [10.0, 10.0], [50.0, 50.0]], np.float32)
    disp = np.array([18.0, 36.0, 0.0, 0.1], np.float32)
    X, ok = triangulate(pts, disp, RIG, min_depth_m=0.1, max_depth_m=50.0)
    np.testing.assert_array_equal(ok, [True, True, False, False])  # d = 0: infinite; d = 0.1: 360 m
    assert X[0] == pytest.approx([0.0, 0.0, 2.0])  # fB/d = 300 * 0.12 / 18
    assert X[1] == pytest.approx([100 / 300 * 1.0, -100 / 300 * 1.0, 1.0])
    reproj_u = RIG.fx * X[1, 0] / X[1, 2] + RIG.cx
    assert reproj_u == pytest.approx(259.5)


def test_dense_sgbm_recovers_constant_disparity_and_reuses_its_buffer() -> None:
    left, right = pair(14)
    sgbm = DenseDisparity(num_disparities=32, block_size=5)
    disp = sgbm.compute(left, right)
    valid = disp[:, 60:] > 0
    assert valid.mean() > 0.9
    assert np.median(disp[:, 60:][valid]) == pytest.approx(14.0, abs=0.25)
    again = sgbm.compute(left, right)
    assert again is disp  # same buffer, no per-frame allocation
    pts = np.array([[200.0, 100.0], [-5.0, 3.0]], np.float32)
    looked = DenseDisparity.lookup(disp, pts)
    assert looked[0] == pytest.approx(14.0, abs=0.5) and np.isnan(looked[1])


def test_orb_row_matching_gives_the_disparity() -> None:
    left, right = pair(20)
    ex = DescriptorExtractor("orb", 500)
    fl, fr = ex.extract(left), ex.extract(right)
    il, ir, disp = match_stereo_rows(fl, fr, max_dy_px=1.0, max_disparity_px=64)
    assert len(il) > 50
    assert np.median(disp) == pytest.approx(20.0, abs=0.5)
    assert np.all(np.abs(fl.pts_px[il, 1] - fr.pts_px[ir, 1]) <= 1.0)


def _masked_bf_reference(
    fl: Features, fr: Features, max_dy_px: float, min_d: float, max_d: float, ratio: float
) -> list[tuple[int, int]]:
    """The same matching by OpenCV's brute-force matcher with a full N x M row mask (the
    independent oracle): k=2, ratio test, lone candidates kept, ambiguous right features out."""
    dy = np.abs(fl.pts_px[:, None, 1] - fr.pts_px[None, :, 1])
    disp = fl.pts_px[:, None, 0] - fr.pts_px[None, :, 0]
    mask = ((dy <= max_dy_px) & (disp >= min_d) & (disp <= max_d)).astype(np.uint8)
    pairs = []
    for knn in cv2.BFMatcher(fl.norm).knnMatch(fl.descriptors, fr.descriptors, k=2, mask=mask):
        if len(knn) == 1 or (len(knn) == 2 and knn[0].distance < ratio * knn[1].distance):
            pairs.append((knn[0].queryIdx, knn[0].trainIdx))
    right_ids = [r for _, r in pairs]
    return [(q, r) for q, r in pairs if right_ids.count(r) == 1]


@pytest.mark.parametrize("kind", ["orb", "sift"])
def test_row_matching_equals_the_masked_brute_force_matcher(kind: str) -> None:
    # Real features of a stereo pair, plus features moved onto a few shared rows (many
    # candidates per band, ties in y, lone candidates and right features claimed twice).
    left, right = pair(12)
    ex = DescriptorExtractor(kind, 400)
    fl, fr = ex.extract(left), ex.extract(right)
    rng = np.random.default_rng(3)
    fl.pts_px[::3, 1] = rng.choice([50.0, 50.5, 51.75], size=len(fl.pts_px[::3]))
    fr.pts_px[::2, 1] = rng.choice([50.0, 51.0, 52.0], size=len(fr.pts_px[::2]))
    for max_dy, min_d, max_d, ratio in [(1.5, 0.5, 256.0, 0.8), (1.0, 2.0, 40.0, 0.9), (0.0, -500.0, 500.0, 1.0)]:
        il, ir, disp = match_stereo_rows(fl, fr, max_dy, min_d, max_d, ratio)
        expected = _masked_bf_reference(fl, fr, max_dy, min_d, max_d, ratio)
        assert len(expected) > 20
        assert list(zip(il.tolist(), ir.tolist(), strict=True)) == expected
        np.testing.assert_array_equal(disp, (fl.pts_px[il, 0] - fr.pts_px[ir, 0]).astype(np.float32))
    # No candidate anywhere: empty, typed results.
    far = Features(fr.pts_px + np.float32(1000.0), fr.descriptors, fr.norm)
    il, ir, disp = match_stereo_rows(fl, far)
    assert len(il) == len(ir) == len(disp) == 0 and disp.dtype == np.float32


def test_descriptor_matching_uses_the_right_norm() -> None:
    left, right = pair(8)
    orb, sift = DescriptorExtractor("orb", 300), DescriptorExtractor("sift", 300)
    fo, fs = orb.extract(left), sift.extract(left)
    assert fo.norm == cv2.NORM_HAMMING and fs.norm == cv2.NORM_L2
    with pytest.raises(EstimationError, match="norms"):
        match_descriptors(fo, fs)
    # SIFT matched with L2 and the ratio test: matches agree with the true shift.
    fr = sift.extract(right)
    ia, ib = match_descriptors(fs, fr, ratio=0.8)
    assert len(ia) > 30
    shift = fs.pts_px[ia] - fr.pts_px[ib]
    assert np.mean(np.abs(shift[:, 0] - 8.0) < 0.5) > 0.95


def test_grid_detector_spreads_corners_and_respects_existing() -> None:
    img = texture()[:, :320].copy()
    img[:, :160] = cv2.GaussianBlur(img[:, :160], (0, 0), 0.6)  # left half: a bit less contrast
    det = GridDetector(max_features=100, cell_px=40)
    pts = det.detect(img)
    assert 80 <= len(pts) <= 100
    cells = set(zip((pts[:, 0] // 40).astype(int), (pts[:, 1] // 40).astype(int), strict=True))
    assert len(cells) >= 40  # 48 cells; nearly all used, not clustered in the sharp half
    existing = np.array([[20.0, 20.0]], np.float32)
    more = det.detect(img, existing=existing, budget=30)
    assert len(more) <= 30
    assert not np.any((more[:, 0] < 40) & (more[:, 1] < 40))

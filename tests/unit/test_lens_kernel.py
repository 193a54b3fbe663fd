"""The compiled lens model (estimation._lens_kernel) against OpenCV's undistortPoints and projectPoints.

The kernels follow OpenCV's arithmetic operation by operation and give the same bits on this
project's machines; the comparisons allow a few units in the last place (a build of OpenCV that
fuses multiply-adds rounds differently), masks are compared exactly.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from estimation import _lens_kernel
from estimation.camera_geometry import CameraGeometry
from estimation.vo_options import VoOptions
from flightkit.datasets.base import CameraIntrinsics

FX, FY, CX, CY, W, H = 517.3, 516.5, 318.6, 255.3, 640, 480
K = np.array([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]])
MODELS = {
    "4 (k1 k2 p1 p2)": (0.05, -0.12, 0.001, -0.002),
    "5 (TUM fr1)": (0.262383, -0.953104, -0.005358, 0.002628, 1.163314),
    "8 (rational)": (0.3, -0.2, 0.001, 0.002, 0.05, 0.25, -0.1, 0.03),
}


def _close(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and bool(np.allclose(a, b, rtol=1e-12, atol=1e-9))


def _pixels(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    px = rng.random((n, 2)) * [W + 40, H + 40] - 20  # a margin beyond the image too
    return px.astype(np.float32)


@pytest.mark.parametrize("name", list(MODELS))
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_undistort_equals_opencv(name: str, dtype: type) -> None:
    dist = np.array(MODELS[name])
    px = _pixels(5000, 1).astype(dtype)
    k = _lens_kernel.coefficients(dist)
    assert k is not None
    ours = _lens_kernel.undistort(px, FX, FY, CX, CY, k)
    ref = cv2.undistortPoints(px.reshape(-1, 1, 2).astype(np.float64), K, dist, P=K).reshape(-1, 2)
    assert _close(ours, ref)
    # the model moves the pixels (the comparison is not of identities)
    assert np.abs(ref - px).max() > 1.0


def test_undistort_beyond_the_models_radius_equals_opencv() -> None:
    # a strong barrel term: far pixels leave the model's valid radius (OpenCV keeps them as they are)
    dist = np.array([-0.9, 0.0, 0.0, 0.0, 0.0])
    px = np.array([[0.0, 0.0], [639.0, 479.0], [320.0, 240.0], [5000.0, 4000.0]], np.float32)
    k = _lens_kernel.coefficients(dist)
    assert k is not None
    ours = _lens_kernel.undistort(px, FX, FY, CX, CY, k)
    ref = cv2.undistortPoints(px.reshape(-1, 1, 2).astype(np.float64), K, dist, P=K).reshape(-1, 2)
    assert _close(ours, ref)


@pytest.mark.parametrize("name", list(MODELS))
def test_project_equals_opencv(name: str) -> None:
    dist = np.array(MODELS[name])
    rng = np.random.default_rng(2)
    X = np.c_[rng.normal(0.0, 1.0, (4000, 2)), rng.uniform(-0.5, 5.0, 4000)]  # some behind the camera
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.array([0.05, -0.1, 0.03]))[0]
    T[:3, 3] = [0.1, -0.05, 0.2]
    k = _lens_kernel.coefficients(dist)
    assert k is not None
    margin = 20.0
    uv, inside = _lens_kernel.project(X, T, FX, FY, CX, CY, k, float(W), float(H), margin)
    Xc = X @ T[:3, :3].T + T[:3, 3]
    ref, _ = cv2.projectPoints(Xc[:, None, :], np.zeros(3), np.zeros(3), K, dist)
    ref = ref.reshape(-1, 2)
    front = Xc[:, 2] > 0.05
    u, v = ref[:, 0], ref[:, 1]
    ref_inside = front & (u > -margin) & (u < W + margin) & (v > -margin) & (v < H + margin)
    assert uv.dtype == np.float32
    assert _close(uv[front].astype(np.float64), ref[front].astype(np.float32).astype(np.float64))
    assert np.array_equal(inside, ref_inside)
    assert 0 < np.count_nonzero(inside) < len(X)


def test_thin_prism_terms_stay_with_opencv() -> None:
    dist = np.array([0.1, -0.05, 0.001, 0.001, 0.0, 0.0, 0.0, 0.0, 0.002, 0.0, 0.0, 0.0])
    assert _lens_kernel.coefficients(dist) is None
    assert _lens_kernel.coefficients(np.r_[dist[:8], np.zeros(6)]) is not None
    geo = CameraGeometry(
        CameraIntrinsics(FX, FY, CX, CY, W, H, tuple(dist)), None, None, VoOptions(), use_depth_images=True
    )
    px = _pixels(300, 3)
    ref = cv2.undistortPoints(px.reshape(-1, 1, 2).astype(np.float64), K, dist, P=K).reshape(-1, 2)
    assert np.array_equal(geo.undistort(px), ref)


def test_geometry_undistorts_and_projects_through_the_kernels() -> None:
    dist = np.array(MODELS["5 (TUM fr1)"])
    geo = CameraGeometry(CameraIntrinsics(FX, FY, CX, CY, W, H, tuple(dist)), None, None, VoOptions(), True)
    assert geo._lens is not None  # the kernels, not OpenCV
    px = _pixels(300, 4)
    und = geo.undistort(px)
    assert _close(und, cv2.undistortPoints(px.reshape(-1, 1, 2).astype(np.float64), K, dist, P=K).reshape(-1, 2))
    # projecting the undistorted pixels' rays at 2 m lands back on the image pixels
    z = 2.0
    X = np.c_[(und[:, 0] - CX) / FX * z, (und[:, 1] - CY) / FY * z, np.full(len(und), z)]
    uv, _ = geo.project(np.eye(4), X)
    inner = (px[:, 0] > 40) & (px[:, 0] < W - 40) & (px[:, 1] > 40) & (px[:, 1] < H - 40)
    assert np.abs(uv[inner] - px[inner]).max() < 1e-3

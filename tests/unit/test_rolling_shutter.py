"""Rolling-shutter row timing (``estimation.rolling_shutter``) against exact projections, and the
RGB-D methods on rendered rolling-shutter images of a textured plane with a known motion."""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from estimation.pipeline import VisualOdometry, VoOptions
from estimation.rolling_shutter import CameraRate, RollingShutter
from flightkit.datasets.base import CameraIntrinsics
from flightkit.errors import DatasetError, EstimationError
from flightkit.frames import Transform

F64 = npt.NDArray[np.float64]

FX, CX, CY, W, H = 500.0, 319.5, 239.5, 640, 480
READOUT_S = 0.02


def _rot(rvec: F64) -> F64:
    return np.asarray(cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0])


def test_pixels_and_points_are_moved_to_the_stamp() -> None:
    """A camera turning at 1.5 rad/s and moving at 1 m/s: each point is seen at the row where it
    is when that row is exposed (solved exactly); moved to the stamp it lands where the camera at
    the stamp sees it, to the first-order model's accuracy."""
    rng = np.random.default_rng(3)
    omega = np.array([0.9, -1.1, 0.4])  # rad/s, camera frame
    vel = np.array([0.6, 0.3, -0.7])  # m/s, camera frame
    X_mid = np.c_[rng.uniform(-1.2, 1.2, 200), rng.uniform(-0.9, 0.9, 200), rng.uniform(1.5, 3.0, 200)]
    shutter = RollingShutter(READOUT_S, H, FX, FX, CX, CY)

    def at(dt: F64) -> F64:
        # The point in the camera at stamp + dt (exact for a constant rate: X(dt) = R(-w dt) X - v dt).
        out = np.empty_like(X_mid)
        for i, d in enumerate(dt):
            out[i] = _rot(-omega * d) @ X_mid[i] - vel * d
        return out

    def project(X: F64) -> F64:
        return np.c_[FX * X[:, 0] / X[:, 2] + CX, FX * X[:, 1] / X[:, 2] + CY]

    px_mid = project(X_mid)
    rows = px_mid[:, 1].copy()
    for _ in range(10):  # the row a point is seen on depends on when that row is exposed
        rows = project(at(shutter.row_dt_s(rows)))[:, 1]
    X_row = at(shutter.row_dt_s(rows))
    px_row = project(X_row)
    assert np.max(np.abs(px_row - px_mid)) > 4.0  # what the correction has to undo

    rate = CameraRate(omega, vel)
    moved = shutter.pixels(px_row, px_row[:, 1], rate, X_row[:, 2])
    assert np.max(np.linalg.norm(moved - px_mid, axis=1)) < 0.1
    rot_only = shutter.pixels(px_row, px_row[:, 1], CameraRate(omega, np.zeros(3)))
    assert np.max(np.linalg.norm(rot_only - px_mid, axis=1)) > 0.5  # the velocity's part matters
    assert np.max(np.linalg.norm(X_row - X_mid, axis=1)) > 5e-3
    # second order: about (|w| dt)^2 |X| / 2 = 0.3 mm at the first and last rows
    assert np.max(np.linalg.norm(shutter.points(X_row, px_row[:, 1], rate) - X_mid, axis=1)) < 5e-4


def test_rate_from_a_step_and_the_shift_it_makes() -> None:
    omega, vel, dt = np.array([0.3, -2.0, 0.5]), np.array([0.0, 0.4, 1.2]), 1.0 / 30
    T = np.eye(4)
    T[:3, :3] = _rot(-omega * dt)
    T[:3, 3] = -vel * dt
    rate = CameraRate.from_step(T, dt)
    np.testing.assert_allclose(rate.omega_rad_s, omega, atol=1e-9)
    np.testing.assert_allclose(rate.velocity_m_s, vel, atol=1e-9)
    shutter = RollingShutter(READOUT_S, H, FX, FX, CX, CY)
    # 2 rad/s about y over half the readout: about 0.5 * 0.02 * 500 * 2 = 10 px at the top row.
    assert shutter.max_shift_px(rate) == pytest.approx(10.2, abs=0.2)
    assert shutter.max_shift_px(rate.minus(rate)) == 0.0


def test_readout_must_be_zero_or_more() -> None:
    with pytest.raises(DatasetError, match="readout_s"):
        CameraIntrinsics(FX, FX, CX, CY, W, H, (), -0.01)
    assert CameraIntrinsics(FX, FX, CX, CY, W, H, (), READOUT_S).scaled(0.5).readout_s == READOUT_S
    with pytest.raises(EstimationError, match="readout_s"):
        VoOptions(readout_s=-1.0).validate()


# --------------------------------------------------------------------------- rendered sequence
PLANE_Z_M = 2.0
TEX_PX_PER_M = 400.0


def _texture() -> npt.NDArray[np.uint8]:
    rng = np.random.default_rng(11)
    noise = rng.integers(0, 256, (1600, 1600), dtype=np.uint8)
    tex = cv2.GaussianBlur(noise, (0, 0), 2.0)
    return np.asarray(cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX), dtype=np.uint8)


def _pose(t: float) -> tuple[F64, F64]:
    """R_world_camera, p_world_camera at time t: a hand-held sway (up to 1.4 rad/s) and drift."""
    ang = 0.15 * math.sin(2 * math.pi * 1.5 * t)
    R = _rot(np.array([0.6, 0.8, 0.0]) * ang)
    p = np.array([0.15 * math.sin(2 * math.pi * 0.7 * t), 0.05 * t, 0.0])
    return R, p


def _render(t: float, tex: npt.NDArray[np.uint8], readout_s: float) -> tuple[npt.NDArray[np.uint8], F64]:
    """The grey image (rows exposed over ``readout_s``, centred on t) and the depth image at t
    (a global-shutter depth camera registered to it) of the plane Z = PLANE_Z_M."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays = np.stack([(u - CX) / FX, (v - CY) / FX, np.ones_like(u)], axis=-1)  # (H, W, 3)
    maps = np.empty((H, W, 2), np.float32)
    for row in range(H):
        R, p = _pose(t + (row - (H - 1) / 2) * readout_s / H)
        d = rays[row] @ R.T
        lam = (PLANE_Z_M - p[2]) / d[:, 2]
        Pw = p + lam[:, None] * d
        maps[row, :, 0] = Pw[:, 0] * TEX_PX_PER_M + tex.shape[1] / 2
        maps[row, :, 1] = Pw[:, 1] * TEX_PX_PER_M + tex.shape[0] / 2
    gray = cv2.remap(tex, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR)
    R, p = _pose(t)
    d = rays @ R.T
    depth = ((PLANE_Z_M - p[2]) / d[..., 2]).astype(np.float32)  # the ray's z in the camera is 1
    return np.asarray(gray, dtype=np.uint8), depth


def _run(method: str, frames: list[tuple[float, npt.NDArray[np.uint8], F64]], readout_s: float) -> tuple[float, float]:
    """RMS position (m) and rotation (deg) error of the run against the rendered motion."""
    intr = CameraIntrinsics(FX, FX, CX, CY, W, H, (), READOUT_S)
    R0, p0 = _pose(frames[0][0])
    T0 = np.eye(4)
    T0[:3, :3], T0[:3, 3] = R0, p0
    vo = VisualOdometry(
        method,
        intr,
        depth_intrinsics=intr,
        T_world_camera0=Transform.from_matrix(T0),
        options=VoOptions(readout_s=readout_s),
    )
    pos, rot = [], []
    for t, gray, depth in frames:
        T = vo.process(round(t * 1e9), gray, depth_m=depth).T_world_camera
        R, p = _pose(t)
        pos.append(np.linalg.norm(T[:3, 3] - p))
        rot.append(math.degrees(np.linalg.norm(cv2.Rodrigues(R.T @ T[:3, :3])[0])))
    return math.sqrt(np.mean(np.square(pos))), math.sqrt(np.mean(np.square(rot)))


@pytest.fixture(scope="module")
def rolling_frames() -> list[tuple[float, npt.NDArray[np.uint8], F64]]:
    tex = _texture()
    return [(i / 30.0, *_render(i / 30.0, tex, READOUT_S)) for i in range(24)]


@pytest.mark.parametrize("method", ["rgbd-kabsch", "rgbd-pnp", "rgbd-essential"])
def test_rgbd_methods_undo_a_known_rolling_shutter(
    method: str, rolling_frames: list[tuple[float, npt.NDArray[np.uint8], F64]]
) -> None:
    """Rendered with a 20 ms readout: told the readout, the method follows the sway closely
    (measured 1.6-1.7 mm, 0.07 deg RMS); treating the rows as exposed at once, it does not
    (56-132 mm, 2.2-4.1 deg)."""
    pos_rs, rot_rs = _run(method, rolling_frames, READOUT_S)
    pos_gs, rot_gs = _run(method, rolling_frames, 0.0)
    assert pos_rs < 0.1 * pos_gs
    assert rot_rs < 0.1 * rot_gs
    assert pos_rs < 0.004 and rot_rs < 0.15


def test_a_measured_guess_asks_the_prior_check_for_its_own_share_of_inliers() -> None:
    """The second measurement starts from the first, whose outliers stay outliers: the prior
    check then needs the options' share of those inliers, not of every track."""
    from estimation.estimators import Tracks

    n = 100
    px = np.zeros((n, 2), np.float32)
    gray = np.zeros((4, 4), np.uint8)

    def tracks(guess_inliers: int | None) -> Tracks:
        return Tracks(
            np.ones((n, 3)),
            px,
            px.astype(np.float64),
            px,
            px.astype(np.float64),
            px.astype(np.float64),
            np.eye(4),
            True,
            gray,
            None,
            None,
            guess_inliers=guess_inliers,
        )

    assert tracks(None).prior_fraction(0.9) == 0.9  # a prediction: the options' share
    assert tracks(80).prior_fraction(0.9) == pytest.approx(0.72)  # 90 % of the 80 inliers
    assert tracks(100).prior_fraction(0.9) == 0.9  # never more than the options ask


@pytest.mark.parametrize("readout_s", [0.0, READOUT_S])
def test_depth_points_take_the_callers_lens_undistortion_bit_for_bit(readout_s: float) -> None:
    """``CameraGeometry.depth_points`` given ``undistort(px)`` (what the odometry computed once for
    both measurements) returns what it computes by itself, bit for bit."""
    from estimation.camera_geometry import CameraGeometry

    intr = CameraIntrinsics(FX, FX, CX, CY, W, H, dist=(0.25, -0.5, 0.001, -0.002, 0.2), readout_s=readout_s)
    geo = CameraGeometry(intr, None, intr, VoOptions().for_camera(FX, W), use_depth_images=True)
    rng = np.random.default_rng(9)
    depth = rng.uniform(1.0, 3.0, (H // 40, W // 40)).astype(np.float32).repeat(40, axis=0).repeat(40, axis=1)
    px = np.c_[rng.uniform(5, W - 5, 300), rng.uniform(5, H - 5, 300)].astype(np.float32)
    und = geo.undistort(px)
    assert np.abs(und - px).max() > 1.0  # the lens moves them
    for rate in (None, CameraRate(np.array([0.9, -1.1, 0.4]), np.array([0.6, 0.3, -0.7]))):
        X, ok = geo.depth_points(depth, px, rate)
        X2, ok2 = geo.depth_points(depth, px, rate, und)
        assert np.count_nonzero(ok) > 100
        np.testing.assert_array_equal(ok2, ok)
        np.testing.assert_array_equal(X2, X)


@pytest.mark.parametrize("own_depth_camera", [False, True])
def test_depth_points_with_a_rate_equal_the_numpy_steps_bit_for_bit(own_depth_camera: bool) -> None:
    """With a rolling shutter, ``CameraGeometry.depth_points`` (one compiled call) is its numpy
    steps: the depth at the pixels, the pixels moved to the stamp with it, the depth again there
    (in the depth camera's pixels when it has its own intrinsics), the back-projection."""
    from estimation import _kernels
    from estimation.camera_geometry import CameraGeometry

    intr = CameraIntrinsics(FX, FX, CX, CY, W, H, readout_s=READOUT_S)
    d_intr = CameraIntrinsics(FX * 1.02, FX * 1.01, CX + 3.0, CY - 2.0, W, H) if own_depth_camera else intr
    geo = CameraGeometry(intr, None, d_intr, VoOptions().for_camera(FX, W), use_depth_images=True)
    assert geo.shutter is not None
    rng = np.random.default_rng(21)
    depth = rng.uniform(0.5, 3.0, (H // 20, W // 20)).astype(np.float32).repeat(20, axis=0).repeat(20, axis=1)
    depth[rng.uniform(size=depth.shape) < 0.02] = np.nan  # holes and depth edges
    px = np.c_[rng.uniform(-2, W + 2, 400), rng.uniform(-2, H + 2, 400)].astype(np.float32)
    und = geo.undistort(px)
    rate = CameraRate(np.array([0.9, -1.1, 0.4]), np.array([0.6, 0.3, -0.7]))

    def depth_at(p: npt.NDArray[np.float32]) -> F64:
        # the lookup in the depth image's own pixels, written out
        uv = p.astype(np.float64)
        if own_depth_camera:
            uv = np.c_[(uv[:, 0] - CX) * d_intr.fx / FX + d_intr.cx, (uv[:, 1] - CY) * d_intr.fy / FX + d_intr.cy]
        lo, hi = geo.opts.min_depth_m, geo.opts.max_depth_m
        return np.asarray(_kernels.depth_at(depth, uv[:, 0].copy(), uv[:, 1].copy(), lo, hi))

    z = depth_at(px)
    np.testing.assert_array_equal(geo.depth_at(depth, px), z)
    und_mid = geo.shutter.pixels(und, px[:, 1], rate, z)
    z_mid = depth_at((px + (und_mid - und)).astype(np.float32))
    ok_ref = np.isfinite(z_mid)
    X_ref = geo.backproject(und_mid, np.where(ok_ref, z_mid, 1.0))

    X, ok = geo.depth_points(depth, px, rate, und)
    assert 100 < np.count_nonzero(ok) < len(px)  # some with depth, some without
    assert np.count_nonzero(np.isfinite(z) != ok_ref) > 0  # the move changes which have depth
    np.testing.assert_array_equal(ok, ok_ref)
    np.testing.assert_array_equal(X, X_ref)


def test_pixels_equal_the_numpy_formula_bit_for_bit() -> None:
    """:meth:`RollingShutter.pixels` (one compiled loop, row times and missing depths inside it) is
    the first-order model written in numpy, operation by operation."""
    rng = np.random.default_rng(12)
    shutter = RollingShutter(READOUT_S, H, FX, FX + 1.0, CX, CY)
    rate = CameraRate(np.array([0.9, -1.1, 0.4]), np.array([0.6, 0.3, -0.7]))
    und = np.c_[rng.uniform(0, W, 300), rng.uniform(0, H, 300)]
    px = (und + rng.normal(scale=2.0, size=und.shape)).astype(np.float32)
    z = rng.uniform(0.5, 4.0, 300)
    z[::7], z[::11] = np.nan, np.inf
    w, v = rate.omega_rad_s, rate.velocity_m_s
    for z_m in (None, z, np.c_[z, z][:, 1]):  # none, contiguous, strided
        dt = (px[:, 1].astype(np.float64) - 0.5 * (H - 1)) * (READOUT_S / H)
        zz = np.full(300, np.inf) if z_m is None else np.where(np.isfinite(z_m), z_m, 1e9)
        x, y, inv_z = (und[:, 0] - CX) / FX, (und[:, 1] - CY) / (FX + 1.0), 1.0 / zz
        bx = x + dt * (w[1] - w[2] * y + v[0] * inv_z)
        by = y + dt * (w[2] * x - w[0] + v[1] * inv_z)
        bz = 1.0 + dt * (w[0] * y - w[1] * x + v[2] * inv_z)
        ref = np.c_[FX * bx / bz + CX, (FX + 1.0) * by / bz + CY]
        np.testing.assert_array_equal(shutter.pixels(und, px[:, 1], rate, z_m), ref)

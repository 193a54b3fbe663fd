"""Returning to a kept keyframe (``VoOptions.revisit_keyframes``, ``estimation.revisit``): which
kept keyframe the store offers, and the front end tracking its points into the current image."""

from __future__ import annotations

import cv2
import numpy as np

from estimation.camera_geometry import CameraGeometry
from estimation.frontend import FrontEnd
from estimation.motion import make_T
from estimation.revisit import KeyframeStore, StoredKeyframe
from estimation.vo_options import VoOptions
from flightkit.datasets.base import CameraIntrinsics

INTR = CameraIntrinsics(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)
DEPTH_M = 2.0  # a wall facing the camera


def _geometry() -> tuple[CameraGeometry, VoOptions]:
    o = VoOptions().for_camera(INTR.fx, INTR.width)
    return CameraGeometry(INTR, None, INTR, o, use_depth_images=True), o


def _yaw(deg: float, t: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    return make_T(cv2.Rodrigues(np.array([0.0, np.radians(deg), 0.0]))[0], np.array(t))


def _kept(T_world_kf: np.ndarray, n: int = 200) -> StoredKeyframe:
    """A keyframe at ``T_world_kf`` with ``n`` points on a grid of its image, on the wall."""
    u, v = np.meshgrid(np.linspace(60, 580, 20), np.linspace(60, 420, n // 20))
    px = np.c_[u.ravel(), v.ravel()].astype(np.float32)
    X = np.c_[(px[:, 0] - INTR.cx) / INTR.fx, (px[:, 1] - INTR.cy) / INTR.fy, np.ones(len(px))] * DEPTH_M
    img = np.zeros((INTR.height, INTR.width), np.uint8)
    return StoredKeyframe(T_world_kf, X, px, np.arange(len(px)), np.ones(len(px)), img, None, None)


def test_store_offers_the_kept_keyframe_the_policy_would_keep() -> None:
    geo, o = _geometry()
    policy = o.keyframes
    store = KeyframeStore(3)
    a, b, c = _kept(_yaw(0.0)), _kept(_yaw(4.0)), _kept(_yaw(30.0))
    for kf in (a, b, c):
        store.add(kf)
    # 1 deg from a, 3 from b (about 9 and 27 px of image motion; the policy's limit is 25 px):
    assert store.best(_yaw(1.0), geo, policy, None) is a
    # the current keyframe is not offered; b is beyond the parallax limit from here, c beyond the turn:
    assert store.best(_yaw(1.0), geo, policy, a) is None
    assert store.best(_yaw(3.0), geo, policy, a) is b
    # nothing near: a camera 60 deg away, or 0.5 m to the side (a quarter of the wall's depth)
    assert store.best(_yaw(60.0), geo, policy, None) is None
    assert store.best(_yaw(0.0, (0.5, 0.0, 0.0)), geo, policy, None) is None
    # the store keeps the newest: a fourth keyframe pushes a out (b is 30 px away from here)
    assert store.best(_yaw(0.5), geo, policy, None) is a
    store.add(_kept(_yaw(-20.0)))
    assert len(store) == 3 and store.best(_yaw(0.5), geo, policy, None) is None


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (INTR.height + 40, INTR.width + 40)).astype(np.float32), (0, 0), 2.0)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def _front_back_near_a_kept_keyframe() -> tuple[FrontEnd, StoredKeyframe, np.ndarray]:
    """A front end that kept a keyframe of a textured wall (``big``'s middle), then made another of
    a different view; the camera is to come back near the kept one."""
    geo, o = _geometry()
    front = FrontEnd(geo, o, stereo=False)
    big = _texture(1)
    depth = np.full((INTR.height, INTR.width), DEPTH_M, np.float32)
    front.make_keyframe(np.ascontiguousarray(big[20:-20, 20:-20]), None, depth, np.eye(4), None)
    kept = front.snapshot()
    assert len(kept.X) > 100
    front.make_keyframe(_texture(2)[20:-20, 20:-20], None, depth, _yaw(10.0), None)
    return front, kept, big


def test_restore_tracks_the_kept_points_into_the_current_image() -> None:
    front, kept, big = _front_back_near_a_kept_keyframe()
    # Back near the kept keyframe: moved 6 px worth to the right and 4 px down (the wall's content
    # moves left and up).
    shift = np.array([6.0, 4.0])
    cur = np.ascontiguousarray(big[24:-16, 26:-14])
    T_world_cam = make_T(np.eye(3), np.r_[shift * DEPTH_M / INTR.fx, 0.0])
    # The pose it is handed is 2 px off (drift): LK still finds the points where they are.
    T_drifted = make_T(np.eye(3), np.r_[(shift + 2.0) * DEPTH_M / INTR.fx, 0.0])
    assert front.restore(kept, cur, T_drifted)
    np.testing.assert_array_equal(front.T_world_kf, kept.T_world_kf)
    assert len(front.kf_X) >= 0.9 * len(kept.X)
    inside = np.isin(kept.ids, front.kf_ids)
    np.testing.assert_allclose(front.kf_X, kept.X[inside])
    err = np.linalg.norm(front.trk_px - (front.kf_px - shift.astype(np.float32)), axis=1)
    assert np.median(err) < 0.05 and np.max(err) < 0.5
    # An image of something else: too few points tracked, and the front end is left as it was.
    before = front.kf_ids.copy()
    assert not front.restore(kept, _texture(3)[20:-20, 20:-20], T_world_cam)
    np.testing.assert_array_equal(front.kf_ids, before)


def test_restore_keeps_only_tracks_that_agree_on_one_pose() -> None:
    """LK from the kept image lands on texture that moved on its own (an object, or look-alike
    texture from another viewpoint): those tracks are dropped, and when they are too many for
    the keyframe policy the return is refused and the front end left as it was."""
    front, kept, big = _front_back_near_a_kept_keyframe()
    shift = np.array([6.0, 4.0])
    T_world_cam = make_T(np.eye(3), np.r_[shift * DEPTH_M / INTR.fx, 0.0])

    def view(moved_cols: int) -> np.ndarray:
        """The kept view after the camera's shift, with its ``moved_cols`` left columns shifted 8 px
        further (the same texture, so LK tracks them, but at a motion no pose explains)."""
        cur = np.ascontiguousarray(big[24:-16, 26:-14])
        cur[:, :moved_cols] = big[24:-16, 34 : 34 + moved_cols]
        return cur

    # A fifth of the image moved: the return is taken, without the points there.
    assert front.restore(kept, view(128), T_world_cam)
    assert 0.7 * len(kept.X) <= len(front.kf_X) < 0.9 * len(kept.X)
    assert np.all(front.kf_px[:, 0] > 128 + shift[0] - 12)
    err = np.linalg.norm(front.trk_px - (front.kf_px - shift.astype(np.float32)), axis=1)
    assert np.max(err) < 0.5
    # Half of it moved: LK tracks nearly every point, but only half agree; refused, nothing changed.
    front, kept, big = _front_back_near_a_kept_keyframe()
    before = front.kf_ids.copy()
    assert not front.restore(kept, view(320), T_world_cam)
    np.testing.assert_array_equal(front.kf_ids, before)


def test_front_end_keeps_the_keyframe_pixels_lens_undistorted() -> None:
    """``kf_und_lens`` is ``CameraGeometry.undistort`` of ``kf_px`` (no rate), bit for bit, after a
    new keyframe, ``keep`` and ``restore``: the estimators move it to the stamp instead of
    undistorting the keyframe's pixels again every frame."""
    intr = CameraIntrinsics(
        fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480, dist=(0.2, -0.4, 0.001, -0.002, 0.1)
    )
    o = VoOptions().for_camera(intr.fx, intr.width)
    geo = CameraGeometry(intr, None, intr, o, use_depth_images=True)
    front = FrontEnd(geo, o, stereo=False)
    big = _texture(1)
    depth = np.full((intr.height, intr.width), DEPTH_M, np.float32)
    front.make_keyframe(np.ascontiguousarray(big[20:-20, 20:-20]), None, depth, np.eye(4), None)
    kept = front.snapshot()

    def check() -> None:
        assert len(front.kf_und_lens) == len(front.kf_px) > 50
        np.testing.assert_array_equal(front.kf_und_lens, geo.undistort(front.kf_px))
        assert np.abs(front.kf_und_lens - front.kf_px).max() > 1.0  # the lens moved them

    check()
    keep = np.arange(len(front.kf_px)) % 3 > 0
    front.keep(keep, front.trk_px)
    check()
    front.make_keyframe(_texture(2)[20:-20, 20:-20], None, depth, _yaw(10.0), front.kf_X.copy())
    check()
    assert front.restore(kept, np.ascontiguousarray(big[20:-20, 20:-20]), np.eye(4))
    check()

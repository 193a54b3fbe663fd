"""Synthetic camera sequences: the simulated camera flown along a path, with exact ground truth.

A :class:`SimSequence` is a :class:`~flightkit.datasets.base.Sequence` like a TUM or EuRoC
folder, except that its frames are rendered on demand by :class:`~flightkit.sim.camera.SimCamera`
from a list of body poses. Everything a VO method reads is there: colour, 16-bit depth in
millimetres (registered to colour), the rectified right image of a stereo pair, intrinsics and
baseline, and the ground truth ``T_world_camera = T_world_body @ T_body_camera``, exact because
it is the pose the image was rendered from.

::

    from flightkit.config import CameraConfig
    from flightkit.sim.sequence import SimSequence, body_poses_along

    poses = body_poses_along(pattern, rate_hz=15.0, start_s=0.0, duration_s=12.0)
    seq = SimSequence.from_config(CameraConfig(width_px=320, height_px=240), poses, name="circle")
    for frame in seq.frames():          # renders one frame at a time (~25 ms per view at 320x240)
        frame.gray, frame.depth_m, frame.right_gray, frame.T_world_camera
    seq.groundtruth()                   # camera trajectory at the frame stamps, no rendering

``body_poses_along`` takes anything with ``.reference(t_s)`` (returning an object with
``pos_m`` and ``yaw_rad``) and ``.duration_s`` -- the trajectory patterns fit, without this
core module importing them -- or a plain callable ``t_s -> (pos_m, yaw_rad)``. It adds the
attitude a quadrotor needs to follow the path: the thrust axis (body z) points along
``a + g`` (so the tilt is ``atan(a / g)``, the acceleration smoothed over ``accel_window_s``
as a real vehicle's attitude loop would), with the heading from the path's yaw.

Imaging effects are off by default and, when on, deterministic per frame (seeded by the
sequence seed and the frame index, so rendering a frame twice gives the same image):
Gaussian intensity noise, depth noise growing with the square of the range, and motion blur
(several renders across the exposure, averaged).

World ENU (z up), body FLU, camera OpenCV (x right, y down, z forward).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator
from collections.abc import Sequence as SequenceABC
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation, Slerp

from flightkit.datasets.base import CameraIntrinsics, Frame, StereoRectification
from flightkit.datasets.trajectory import Trajectory
from flightkit.errors import DatasetError, SimError
from flightkit.frames import Transform
from flightkit.sim.camera import Scene, SimCamera

__all__ = [
    "SIM_KIND",
    "BodyPose",
    "ImagingOptions",
    "SimSequence",
    "body_poses_along",
    "quadrotor_attitude",
]

logger = logging.getLogger(__name__)

SIM_KIND = "sim"
"""The ``Sequence.kind`` of simulated sequences."""

GRAVITY_M_S2 = 9.80665

BodyPose = tuple[int, Transform]
"""``(stamp_ns, T_world_body)``."""

PathFn = Callable[[float], tuple[Any, float]]
"""``t_s -> (pos_m (3,), yaw_rad)``: a path as a plain function of time."""


# ----------------------------------------------------------------------------- body poses
def quadrotor_attitude(accel_world_m_s2: npt.ArrayLike, yaw_rad: float, gravity_m_s2: float = GRAVITY_M_S2) -> Rotation:
    """``R_world_body`` of a quadrotor accelerating at ``accel_world_m_s2`` with heading ``yaw_rad``.

    The thrust axis (body z, FLU) points along ``a + g e_z``; the body x axis is the heading
    direction projected onto the plane normal to it (the usual differential-flatness
    construction). At rest it is a pure yaw rotation; accelerating forward pitches the nose
    down by ``atan(a / g)``.

    Raises:
        SimError: the acceleration cancels gravity (free fall has no attitude).
    """
    a = np.asarray(accel_world_m_s2, dtype=np.float64).reshape(3)
    thrust = a + np.array([0.0, 0.0, gravity_m_s2])
    norm = float(np.linalg.norm(thrust))
    if norm < 1e-6 * gravity_m_s2:
        raise SimError(
            f"acceleration {a} m/s^2 cancels gravity; a quadrotor has no attitude in free fall: "
            "keep the path's downward acceleration below g"
        )
    z_b = thrust / norm
    x_c = np.array([math.cos(yaw_rad), math.sin(yaw_rad), 0.0])
    y_b = np.cross(z_b, x_c)
    y_norm = float(np.linalg.norm(y_b))
    if y_norm < 1e-9:
        raise SimError(
            f"thrust axis {z_b} is horizontal along the heading; the attitude is undefined: "
            "keep the path's horizontal acceleration below a few g"
        )
    y_b /= y_norm
    x_b = np.cross(y_b, z_b)
    return Rotation.from_matrix(np.column_stack([x_b, y_b, z_b]))


def _position_yaw(path: Any) -> tuple[Callable[[float], tuple[npt.NDArray[np.float64], float]], float | None]:
    """Normalise a pattern-like object or a callable into ``t -> (pos, yaw)`` and its duration."""
    if hasattr(path, "reference") and hasattr(path, "duration_s"):
        duration = float(path.duration_s)

        def from_reference(t_s: float) -> tuple[npt.NDArray[np.float64], float]:
            ref = path.reference(min(max(t_s, 0.0), duration))
            return np.asarray(ref.pos_m, dtype=np.float64), float(ref.yaw_rad)

        return from_reference, duration
    if callable(path):

        def from_callable(t_s: float) -> tuple[npt.NDArray[np.float64], float]:
            pos, yaw = path(t_s)
            return np.asarray(pos, dtype=np.float64).reshape(3), float(yaw)

        return from_callable, None
    raise TypeError(
        f"path must have .reference(t_s) and .duration_s (a trajectory pattern) or be a callable "
        f"t_s -> (pos_m, yaw_rad); got {type(path).__name__}"
    )


def body_poses_along(
    path: Any,
    rate_hz: float,
    *,
    start_s: float = 0.0,
    duration_s: float | None = None,
    stamp0_ns: int = 0,
    tilt: bool = True,
    accel_window_s: float = 0.4,
    gravity_m_s2: float = GRAVITY_M_S2,
) -> list[BodyPose]:
    """Body poses ``(stamp_ns, T_world_body)`` sampled along a path at ``rate_hz``.

    Args:
        path: a pattern (``.reference(t_s)`` with ``pos_m``/``yaw_rad``, and ``.duration_s``;
            duck-typed) or a callable ``t_s -> (pos_m, yaw_rad)``.
        rate_hz: camera frame rate.
        start_s: path time of the first frame.
        duration_s: seconds of path to sample (default: to the pattern's end; required for
            a callable). Frames are at ``start_s + k / rate_hz`` up to ``start_s + duration_s``.
        stamp0_ns: stamp of path time 0; frame stamps are ``stamp0_ns + t * 1e9``.
        tilt: add the roll and pitch a quadrotor needs for the path's acceleration (else
            the body is level, yaw only).
        accel_window_s: acceleration is the second difference of position over this window
            (``h = window / 2``), a triangular average that smooths the steps of a trapezoid
            speed profile as a real attitude loop does.
        gravity_m_s2: gravity for the tilt.

    Returns:
        One pose per frame, stamps strictly increasing.

    Raises:
        SimError: a non-positive rate, no duration for a callable, or an empty window.
    """
    if not rate_hz > 0.0:
        raise SimError(f"rate_hz must be positive, got {rate_hz}; give a frame rate such as 30.0")
    fn, path_duration = _position_yaw(path)
    if duration_s is None:
        if path_duration is None:
            raise SimError(f"the path {path!r} has no .duration_s; give duration_s for a path given as a callable")
        duration_s = path_duration - start_s
    if not duration_s >= 0.0:
        raise SimError(
            f"duration_s must not be negative, got {duration_s} (start_s {start_s}); start earlier in the path",
        )
    n = int(math.floor(duration_s * rate_hz + 1e-9)) + 1
    h = accel_window_s / 2.0
    poses: list[BodyPose] = []
    for k in range(n):
        t = start_s + k / rate_hz
        pos, yaw = fn(t)
        if tilt and h > 0.0:
            p_minus, _ = fn(t - h)
            p_plus, _ = fn(t + h)
            accel = (p_plus - 2.0 * pos + p_minus) / (h * h)
            rot = quadrotor_attitude(accel, yaw, gravity_m_s2)
        else:
            rot = Rotation.from_euler("z", yaw)
        poses.append((stamp0_ns + round(t * 1e9), Transform(rot, pos)))
    return poses


# ----------------------------------------------------------------------------- imaging
@dataclass(frozen=True, slots=True)
class ImagingOptions:
    """Sensor effects on the rendered images (all off by default).

    Attributes:
        noise_std: standard deviation of additive Gaussian intensity noise, grey levels
            (0-255 scale); each image (left, right) gets its own noise.
        depth_noise_m_per_m2: depth noise standard deviation per squared metre of range
            (structured-light and stereo depth: sigma_z = k z^2; a RealSense D435 is about
            0.001-0.002), rounded to millimetres like the driver.
        exposure_s: motion blur: images average ``blur_samples`` renders over an exposure of
            this length centred on the frame stamp (0 = no blur). Depth stays sharp (at the
            stamp), as a depth sensor's shorter exposure gives.
        blur_samples: renders per blurred image (each costs one full render).
        seed: seed of the noise; a frame's noise depends only on (seed, frame index).
    """

    noise_std: float = 0.0
    depth_noise_m_per_m2: float = 0.0
    exposure_s: float = 0.0
    blur_samples: int = 5
    seed: int = 0

    def __post_init__(self) -> None:
        if self.noise_std < 0.0 or self.depth_noise_m_per_m2 < 0.0 or self.exposure_s < 0.0:
            raise SimError(
                f"noise_std ({self.noise_std}), depth_noise_m_per_m2 ({self.depth_noise_m_per_m2}) and "
                f"exposure_s ({self.exposure_s}) must not be negative; give 0 (off) or more"
            )
        if self.blur_samples < 2:
            raise SimError(
                f"blur_samples must be at least 2, got {self.blur_samples}; use 2 or more (or exposure_s = 0)",
            )

    @property
    def blurred(self) -> bool:
        return self.exposure_s > 0.0


# ----------------------------------------------------------------------------- sequence
class SimSequence:
    """A camera sequence rendered on demand along body poses (implements ``Sequence``).

    Args:
        camera: the renderer (scene, pinhole model, stereo baseline, depth range).
        body_poses: ``(stamp_ns, T_world_body)`` per frame, stamps strictly increasing.
        T_body_camera: the camera mount (OpenCV camera into FLU body).
        name: sequence name (tables, file names).
        stereo: render the right image of the stereo pair (a second render per frame).
        color: keep the BGR colour image in frames (``gray`` is always there).
        imaging: noise and blur (off by default).
        cache: keep rendered frames in memory so a second pass does not render again
            (about 0.3 MB per frame at 320x240 without colour).

    Attributes (besides the ``Sequence`` ones): ``camera``, ``T_body_camera``, ``stereo``,
    ``color``, ``imaging``, and ``render_s``: wall seconds spent rendering so far.

    Frames are rendered lazily, one at a time, so memory stays small unless ``cache`` is on.
    Depth is registered to the colour image (same camera), in millimetres
    (``depth_scale_m = 0.001``, 0 = no surface within ``camera.depth_max_m``).

    Raises:
        DatasetError: no poses, or stamps that do not increase.
    """

    kind: str = SIM_KIND
    rectification: StereoRectification | None = None

    def __init__(
        self,
        camera: SimCamera,
        body_poses: SequenceABC[BodyPose],
        T_body_camera: Transform,  # noqa: N803
        *,
        name: str = "sim",
        stereo: bool = True,
        color: bool = True,
        imaging: ImagingOptions | None = None,
        cache: bool = False,
    ) -> None:
        if len(body_poses) == 0:
            raise DatasetError(f"simulated sequence {name!r} has no poses; give at least one (stamp_ns, T_world_body)")
        stamps = np.array([int(s) for s, _ in body_poses], dtype=np.int64)
        if stamps.size > 1 and np.any(np.diff(stamps) <= 0):
            bad = int(np.argmin(np.diff(stamps)))
            raise DatasetError(
                f"simulated sequence {name!r}: stamps must increase, but pose {bad + 1} has "
                f"{stamps[bad + 1]} ns after {stamps[bad]} ns; sort the poses by time"
            )
        self.camera = camera
        self.name = name
        self.path = Path(f"sim:{name}")
        self.T_body_camera = T_body_camera
        self.stereo = stereo
        self.color = color
        self.imaging = imaging or ImagingOptions()
        m = camera.model
        self.intrinsics = CameraIntrinsics(m.fx_px, m.fy_px, m.cx_px, m.cy_px, m.width_px, m.height_px)
        self.depth_intrinsics: CameraIntrinsics | None = self.intrinsics
        self.baseline_m: float | None = float(camera.baseline_m) if stereo else None
        self._stamps = stamps
        self._T_world_body = [T for _, T in body_poses]
        self._T_world_camera = [T @ T_body_camera for T in self._T_world_body]
        self._cache: dict[int, Frame] | None = {} if cache else None
        self._T_left_right = Transform(translation=np.array([camera.baseline_m, 0.0, 0.0]))
        self._slerp: Slerp | None = None
        self.render_s = 0.0
        """Wall seconds spent rendering so far (all frames, all passes)."""

    @staticmethod
    def from_config(
        camera_cfg: Any,
        body_poses: SequenceABC[BodyPose],
        *,
        scene: Scene | None = None,
        **kwargs: Any,
    ) -> SimSequence:
        """Build from a :class:`flightkit.config.CameraConfig` (size, intrinsics, baseline, depth
        range and the mount ``T_body_camera``); ``kwargs`` go to :class:`SimSequence`."""
        camera = SimCamera.from_config(camera_cfg, scene)
        return SimSequence(camera, body_poses, camera_cfg.T_body_camera.to_transform(), **kwargs)

    # -------------------------------------------------------------- Sequence protocol
    def __len__(self) -> int:
        return int(self._stamps.size)

    def __repr__(self) -> str:
        i = self.intrinsics
        return f"SimSequence({self.name!r}, {len(self)} frames, {i.width}x{i.height}, stereo={self.stereo})"

    def stamps_ns(self) -> npt.NDArray[np.int64]:
        return self._stamps.copy()

    def has_groundtruth(self) -> bool:
        return True

    def groundtruth(self) -> Trajectory:
        """The exact camera poses ``T_world_camera`` at the frame stamps (no rendering)."""
        mats = np.stack([T.as_matrix() for T in self._T_world_camera])
        return Trajectory.from_matrices(self._stamps, mats, name=f"{self.name} ground truth")

    def body_groundtruth(self) -> Trajectory:
        """The body poses ``T_world_body`` the sequence was made from."""
        mats = np.stack([T.as_matrix() for T in self._T_world_body])
        return Trajectory.from_matrices(self._stamps, mats, name=f"{self.name} body")

    def T_world_camera(self, index: int) -> Transform:  # noqa: N802
        """Ground-truth camera pose of frame ``index``."""
        return self._T_world_camera[index]

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1) -> Iterator[Frame]:
        """Yield frames ``start:stop:step``, rendering each when it is reached (blocks ~25-50 ms
        per frame at 320x240: one render, plus one for the right image)."""
        for i in range(*slice(start, stop, step).indices(len(self))):
            yield self.frame(i)

    # -------------------------------------------------------------- rendering
    def frame(self, index: int) -> Frame:
        """Render frame ``index`` (or return it from the cache)."""
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"frame {index} out of range for {self.name!r} with {n} frames")
        index %= n
        if self._cache is not None and index in self._cache:
            return self._cache[index]
        t0 = time.perf_counter()
        frame = self._render(index)
        self.render_s += time.perf_counter() - t0
        if self._cache is not None:
            self._cache[index] = frame
        return frame

    def _render(self, index: int) -> Frame:
        opts = self.imaging
        rng = np.random.default_rng([opts.seed, index]) if (opts.noise_std or opts.depth_noise_m_per_m2) else None
        T_wc = self._T_world_camera[index]
        rendered = self.camera.render(T_wc)
        color_rgb = rendered.color_rgb
        if opts.blurred:
            color_rgb = self._blurred_rgb(index, T_wc, color_rgb)
        color_rgb = self._add_noise(color_rgb, rng)
        gray = cast("npt.NDArray[np.uint8]", cv2.cvtColor(color_rgb, cv2.COLOR_RGB2GRAY))
        right: npt.NDArray[np.uint8] | None = None
        if self.stereo:
            right_rgb = self.camera.render(T_wc @ self._T_left_right).color_rgb
            if opts.blurred:
                right_rgb = self._blurred_rgb(index, T_wc, right_rgb, self._T_left_right)
            right = cast("npt.NDArray[np.uint8]", cv2.cvtColor(self._add_noise(right_rgb, rng), cv2.COLOR_RGB2GRAY))
        depth_mm = rendered.depth_mm
        if rng is not None and opts.depth_noise_m_per_m2 > 0.0:
            valid = depth_mm > 0
            z_m = depth_mm[valid].astype(np.float64) * 1e-3
            noisy = z_m + rng.normal(0.0, 1.0, z_m.size) * opts.depth_noise_m_per_m2 * z_m * z_m
            depth_mm = depth_mm.copy()
            depth_mm[valid] = np.clip(np.round(noisy * 1000.0), 1, 65535).astype(np.uint16)
        return Frame(
            index=index,
            stamp_ns=int(self._stamps[index]),
            gray=gray,
            color_bgr=cast("npt.NDArray[np.uint8]", cv2.cvtColor(color_rgb, cv2.COLOR_RGB2BGR)) if self.color else None,
            right_gray=right,
            depth_raw=depth_mm,
            depth_scale_m=0.001,
            T_world_camera=T_wc,
        )

    def _add_noise(self, rgb: npt.NDArray[np.uint8], rng: np.random.Generator | None) -> npt.NDArray[np.uint8]:
        if rng is None or self.imaging.noise_std <= 0.0:
            return rgb
        noisy = rgb.astype(np.float32) + rng.normal(0.0, self.imaging.noise_std, rgb.shape).astype(np.float32)
        return np.clip(np.round(noisy), 0, 255).astype(np.uint8)

    def _camera_pose_at(self, stamp_ns: float) -> Transform:
        """``T_world_camera`` at any time, interpolated between the body poses (linear position,
        slerp attitude; held constant beyond the ends)."""
        t = self._stamps
        if t.size == 1:
            return self._T_world_camera[0]
        if self._slerp is None:
            rots = Rotation.concatenate([T.rotation for T in self._T_world_body])
            self._slerp = Slerp(t.astype(np.float64), rots)
        s = float(np.clip(stamp_ns, t[0], t[-1]))
        pos = np.array([np.interp(s, t, [T.translation[k] for T in self._T_world_body]) for k in range(3)])
        return Transform(self._slerp([s])[0], pos) @ self.T_body_camera

    def _blurred_rgb(
        self,
        index: int,
        T_wc: Transform,  # noqa: N803
        sharp: npt.NDArray[np.uint8],
        T_left_eye: Transform | None = None,  # noqa: N803
    ) -> npt.NDArray[np.uint8]:
        """Average of renders across the exposure centred on the stamp (the centre one is ``sharp``)."""
        k = self.imaging.blur_samples
        offsets = np.linspace(-0.5, 0.5, k) * self.imaging.exposure_s * 1e9
        acc = np.zeros(sharp.shape, np.float32)
        for off in offsets:
            if abs(off) < 1.0:
                acc += sharp
                continue
            T = self._camera_pose_at(float(self._stamps[index]) + off)
            if T_left_eye is not None:
                T = T @ T_left_eye
            acc += self.camera.render(T).color_rgb
        return np.clip(np.round(acc / k), 0, 255).astype(np.uint8)

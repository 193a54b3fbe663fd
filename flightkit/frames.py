"""Rigid transforms, rotations and the frame conventions of flightkit.

Conventions (the full text is ``docs/frames.md``):

* World frame: right-handed, z up, fixed to the lab (ENU-like). Body frame: FLU
  (x forward, y left, z up). Camera frame: OpenCV (x right, y down, z forward).
* ``T_a_b`` maps points expressed in frame ``b`` into frame ``a`` (it is also the pose of
  ``b`` in ``a``), so inner frames cancel: ``T_a_c = T_a_b @ T_b_c``.
* NED (world) and FRD (body) exist only at the MAVLink edge; the conversions live here
  and nowhere else.
* Quaternions always spell out their order: ``quat_wxyz`` or ``quat_xyzw`` (scipy's order).
* A pose on the bus or in a recording names its frame (``frame_id``): ``"world"`` or
  ``"mocap"`` (the mocap system's own frame). :class:`WorldFrames` places every named frame
  in the world, so a reader turns any pose into ``T_world_body`` in one call, and refuses a
  frame it cannot place.

Rotations are scipy's :class:`~scipy.spatial.transform.Rotation`; nothing here hand-rolls
quaternion algebra.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from flightkit.errors import FrameError, TransformError

__all__ = [
    "MOCAP_FRAME_ID",
    "R_ENU_NED",
    "R_FLU_FRD",
    "WORLD_FRAME_ID",
    "Transform",
    "Vec3",
    "Vec3Tuple",
    "WorldFrames",
    "angle_diff_rad",
    "enu_to_ned",
    "flu_to_frd",
    "frd_to_flu",
    "ned_to_enu",
    "quat_wxyz_to_xyzw",
    "quat_xyzw_to_wxyz",
    "rotation_enu_flu_from_ned_frd",
    "rotation_ned_frd_from_enu_flu",
    "unwrap_angles_rad",
    "world_to_body_yaw",
    "wrap_angle_rad",
    "yaw_enu_to_ned",
    "yaw_from_rotation",
    "yaw_ned_to_enu",
]

Vec3 = npt.NDArray[np.float64]
"""A 3-vector as an array, shape (3,)."""

Vec3Tuple = tuple[float, float, float]
"""A 3-vector as a plain tuple (message fields, pattern geometry)."""

WORLD_FRAME_ID = "world"
"""``frame_id`` of poses in the lab's world frame (ENU, z up)."""

MOCAP_FRAME_ID = "mocap"
"""``frame_id`` of poses in the mocap system's own frame (as Vicon/OptiTrack report them)."""

# Frame-change rotations. R_ENU_NED maps NED coordinates into ENU (x_e = y_n, y_e = x_n, z_e = -z_n);
# it is its own inverse. R_FLU_FRD maps FRD body coordinates into FLU (a rotation of pi about x).
R_ENU_NED: Rotation = Rotation.from_matrix([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
R_FLU_FRD: Rotation = Rotation.from_matrix([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])

_SWAP_ENU_NED: npt.NDArray[np.float64] = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_FLIP_FLU_FRD: npt.NDArray[np.float64] = np.array([1.0, -1.0, -1.0])


def _as_vec(values: Sequence[float] | npt.ArrayLike, name: str = "vector") -> npt.NDArray[np.float64]:
    arr = np.asarray(values, dtype=np.float64)
    if arr.shape[-1:] != (3,):
        raise TransformError(
            f"{name} must have a last dimension of 3, got shape {arr.shape}; pass (x, y, z) or an (N, 3) array",
        )
    return arr


def enu_to_ned(v_enu: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Express ENU vectors (shape (..., 3)) in NED: (e, n, u) -> (n, e, -u)."""
    v = _as_vec(v_enu, "v_enu")
    return v @ _SWAP_ENU_NED.T


def ned_to_enu(v_ned: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Express NED vectors (shape (..., 3)) in ENU: (n, e, d) -> (e, n, -d)."""
    v = _as_vec(v_ned, "v_ned")
    return v @ _SWAP_ENU_NED.T


def flu_to_frd(v_flu: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Express FLU body vectors (shape (..., 3)) in FRD: (x, y, z) -> (x, -y, -z)."""
    return _as_vec(v_flu, "v_flu") * _FLIP_FLU_FRD


def frd_to_flu(v_frd: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Express FRD body vectors (shape (..., 3)) in FLU: (x, y, z) -> (x, -y, -z)."""
    return _as_vec(v_frd, "v_frd") * _FLIP_FLU_FRD


def rotation_ned_frd_from_enu_flu(R_enu_flu: Rotation) -> Rotation:
    """Attitude of an FLU body in ENU -> attitude of the same body as FRD in NED."""
    return R_ENU_NED.inv() * R_enu_flu * R_FLU_FRD


def rotation_enu_flu_from_ned_frd(R_ned_frd: Rotation) -> Rotation:
    """Attitude of an FRD body in NED -> attitude of the same body as FLU in ENU."""
    return R_ENU_NED * R_ned_frd * R_FLU_FRD.inv()


def wrap_angle_rad(angle_rad: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def angle_diff_rad(a_rad: float, b_rad: float) -> float:
    """Shortest signed angle from ``b`` to ``a`` (``a - b`` wrapped to [-pi, pi))."""
    return wrap_angle_rad(a_rad - b_rad)


def unwrap_angles_rad(angles_rad: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Remove 2*pi jumps from a sequence of angles so it is continuous."""
    return np.unwrap(np.asarray(angles_rad, dtype=np.float64))


def yaw_enu_to_ned(yaw_enu_rad: float) -> float:
    """Heading in ENU (counter-clockwise from east) -> NED yaw (clockwise from north)."""
    return wrap_angle_rad(math.pi / 2.0 - yaw_enu_rad)


def yaw_ned_to_enu(yaw_ned_rad: float) -> float:
    """NED yaw (clockwise from north) -> heading in ENU (counter-clockwise from east)."""
    return wrap_angle_rad(math.pi / 2.0 - yaw_ned_rad)


def yaw_from_rotation(R_world_body: Rotation) -> float:
    """Heading of the body x axis about the world z axis (ZYX Euler yaw), radians."""
    # The body x axis in the world is the first column of R: from the quaternion directly,
    # because this runs every control cycle and Rotation.apply costs ~0.1 ms per vector.
    qx, qy, qz, qw = (float(v) for v in R_world_body.as_quat())
    x_east = 1.0 - 2.0 * (qy * qy + qz * qz)
    x_north = 2.0 * (qx * qy + qz * qw)
    # For a body pitched exactly +-90 degrees the x axis has no heading; use the ZYX yaw then.
    if math.hypot(x_east, x_north) < 1e-9:
        return float(R_world_body.as_euler("ZYX")[0])
    return math.atan2(x_north, x_east)


def world_to_body_yaw(v_world: npt.ArrayLike, yaw_rad: float) -> npt.NDArray[np.float64]:
    """Rotate a world vector into the yaw-only (level) body frame: R_z(-yaw) @ v.

    This is what "body frame" velocity setpoints use: x along the heading, y to the left,
    z up, independent of roll and pitch.
    """
    v = _as_vec(v_world, "v_world")
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    out = np.empty_like(v)
    out[..., 0] = c * v[..., 0] + s * v[..., 1]
    out[..., 1] = -s * v[..., 0] + c * v[..., 1]
    out[..., 2] = v[..., 2]
    return out


def quat_wxyz_to_xyzw(q_wxyz: Sequence[float] | npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Reorder quaternions (shape (..., 4)) from w,x,y,z to x,y,z,w."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    return np.concatenate([q[..., 1:4], q[..., 0:1]], axis=-1)


def quat_xyzw_to_wxyz(q_xyzw: Sequence[float] | npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Reorder quaternions (shape (..., 4)) from x,y,z,w to w,x,y,z."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    return np.concatenate([q[..., 3:4], q[..., 0:3]], axis=-1)


@dataclass(frozen=True, slots=True, eq=False)
class Transform:
    """A rigid transform ``T_a_b``: ``p_a = T_a_b.apply(p_b)``.

    Name variables after the frames they connect (``T_world_body``). Compose with ``@``:
    ``T_a_c = T_a_b @ T_b_c``.

    Attributes:
        rotation: ``R_a_b``.
        translation: position of b's origin in a, metres, shape (3,).
    """

    rotation: Rotation = field(default_factory=Rotation.identity)
    translation: npt.NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        t = np.array(self.translation, dtype=np.float64).reshape(-1)
        if t.shape != (3,):
            raise TransformError(f"translation must have 3 elements, got shape {t.shape}; pass (x, y, z) in metres")
        if not np.all(np.isfinite(t)):
            raise TransformError(f"translation must be finite, got {t}; check the pose source for NaN or inf")
        object.__setattr__(self, "translation", t)

    @staticmethod
    def identity() -> Transform:
        return Transform()

    @staticmethod
    def from_matrix(T: npt.ArrayLike) -> Transform:
        """From a 4x4 (or 3x4) homogeneous matrix."""
        m = np.asarray(T, dtype=np.float64)
        if m.shape not in ((4, 4), (3, 4)):
            raise TransformError(f"expected a 4x4 or 3x4 homogeneous matrix, got shape {m.shape}; pass [R | t] rows")
        return Transform(Rotation.from_matrix(m[:3, :3]), m[:3, 3].copy())

    @staticmethod
    def from_quat_wxyz(translation: npt.ArrayLike, quat_wxyz: npt.ArrayLike) -> Transform:
        return Transform(Rotation.from_quat(quat_wxyz_to_xyzw(quat_wxyz)), np.asarray(translation, float))

    @staticmethod
    def from_quat_xyzw(translation: npt.ArrayLike, quat_xyzw: npt.ArrayLike) -> Transform:
        return Transform(Rotation.from_quat(np.asarray(quat_xyzw, float)), np.asarray(translation, float))

    @staticmethod
    def from_xyz_yaw(translation: npt.ArrayLike, yaw_rad: float) -> Transform:
        """A transform with rotation about z only (heading ``yaw_rad``)."""
        return Transform(Rotation.from_euler("z", yaw_rad), np.asarray(translation, float))

    @staticmethod
    def from_xyz_euler_deg(translation: npt.ArrayLike, seq: str, angles_deg: Sequence[float]) -> Transform:
        """From a translation and Euler angles in degrees, scipy's ``seq`` convention
        (lower case extrinsic, upper case intrinsic)."""
        return Transform(Rotation.from_euler(seq, angles_deg, degrees=True), np.asarray(translation, float))

    @property
    def quat_wxyz(self) -> npt.NDArray[np.float64]:
        return quat_xyzw_to_wxyz(self.rotation.as_quat())

    @property
    def quat_xyzw(self) -> npt.NDArray[np.float64]:
        return np.asarray(self.rotation.as_quat(), dtype=np.float64)

    @property
    def yaw_rad(self) -> float:
        return yaw_from_rotation(self.rotation)

    @property
    def is_identity(self) -> bool:
        """Exactly the identity: composing with it changes nothing (hot paths skip the composition)."""
        return not self.translation.any() and float(self.rotation.magnitude()) == 0.0

    def as_matrix(self) -> npt.NDArray[np.float64]:
        """The 4x4 homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.rotation.as_matrix()
        m[:3, 3] = self.translation
        return m

    def inverse(self) -> Transform:
        """``T_b_a`` from ``T_a_b``."""
        r_inv = self.rotation.inv()
        return Transform(r_inv, -r_inv.apply(self.translation))

    def apply(self, points_b: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Map points (shape (3,) or (N, 3)) from frame b into frame a."""
        p = _as_vec(points_b, "points")
        return np.asarray(self.rotation.apply(p), dtype=np.float64) + self.translation

    def __matmul__(self, other: Transform) -> Transform:
        if not isinstance(other, Transform):
            return NotImplemented
        return Transform(self.rotation * other.rotation, self.rotation.apply(other.translation) + self.translation)

    def almost_equal(self, other: Transform, tol_m: float = 1e-9, tol_rad: float = 1e-9) -> bool:
        """True when translation and rotation agree within the tolerances."""
        dt = float(np.linalg.norm(self.translation - other.translation))
        dr = float((self.rotation.inv() * other.rotation).magnitude())
        return dt <= tol_m and dr <= tol_rad

    def __repr__(self) -> str:
        t = ", ".join(f"{x:.4f}" for x in self.translation)
        q = ", ".join(f"{x:.4f}" for x in self.quat_wxyz)
        return f"Transform(t=[{t}], q_wxyz=[{q}])"


@dataclass(frozen=True, slots=True)
class WorldFrames:
    """Where each named frame sits in the world: the one place a pose's ``frame_id`` is resolved.

    ``"world"`` is always known (the identity); ``"mocap"`` maps through ``T_world_mocap``;
    ``extra`` names further frames (e.g. an autopilot's local frame, ``T_world_local``).

    Attributes:
        T_world_mocap: the mocap system's frame in the world (from config or a recording).
        extra: frame id -> ``T_world_frame``.
    """

    T_world_mocap: Transform = field(default_factory=Transform.identity)
    extra: tuple[tuple[str, Transform], ...] = ()

    def known(self) -> tuple[str, ...]:
        """Every frame id this table can place."""
        return (WORLD_FRAME_ID, MOCAP_FRAME_ID, *(name for name, _ in self.extra))

    def T_world(self, frame_id: str) -> Transform:  # noqa: N802
        """``T_world_<frame_id>``.

        Raises:
            FrameError: the frame is not one this table knows (the message names it and the known ones).
        """
        if frame_id == WORLD_FRAME_ID:
            return Transform.identity()
        if frame_id == MOCAP_FRAME_ID:
            return self.T_world_mocap
        for name, T in self.extra:
            if name == frame_id:
                return T
        raise FrameError(frame_id, self.known())

    def to_world(self, frame_id: str, T_frame_body: Transform) -> Transform:  # noqa: N803
        """``T_world_body`` of a pose given in ``frame_id``.

        Raises:
            FrameError: unknown frame.
        """
        if frame_id == WORLD_FRAME_ID:
            return T_frame_body
        return self.T_world(frame_id) @ T_frame_body

    def to_mocap(self, T_world_body: Transform) -> Transform:  # noqa: N803
        """``T_mocap_body`` of a world pose (what the mocap system measures)."""
        return self.T_world_mocap.inverse() @ T_world_body

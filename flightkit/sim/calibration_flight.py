"""Ground-truth motions for calibration flights in the simulated lab.

:func:`calibration_motion` follows a path (a lab pattern, or any ``t_s -> (pos_m, yaw_rad)``)
and rocks the body about all three axes with a sum of sines of unrelated periods, as a pilot
(or a hand-held rig) does for a calibration: the rotation rate changes all the time and never
repeats, so the time offset has one answer, and rotations about several axes make the hand-eye
transform observable. ``rock_deg=(0, 0, 0)`` with ``follow_yaw=False`` is a pure translation,
which every calibration must refuse.

The result is a truth function, clock seconds -> ``T_world_body`` (world ENU, body FLU), like
:meth:`flightkit.sim.lab.SimLab.T_world_body`, for :class:`~flightkit.sim.mocap.SimMocapSystem`
and :class:`~flightkit.sim.camera_publisher.SimCameraPublisher`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from flightkit.clock import LockstepClock
from flightkit.datasets.trajectory import Trajectory
from flightkit.frames import Transform
from flightkit.sim.mocap import SimMocapSystem
from flightkit.sim.timing_errors import SimTimingErrors

__all__ = ["CalibrationStreams", "PathFn", "calibration_motion", "path_of", "simulate_streams"]

PathFn = Callable[[float], tuple[npt.NDArray[np.float64], float]]
"""Seconds from the start -> (position in the world, m (3,), heading, rad)."""

# periods (s) of the two sines rocking each axis: unrelated, so the motion never repeats
_PERIODS_S = ((2.3, 3.7), (2.9, 4.3), (3.3, 5.9))


def path_of(path: Any) -> PathFn:
    """A path function from a pattern (``.reference(t_s)`` with ``pos_m`` and ``yaw_rad``) or a callable."""
    if hasattr(path, "reference"):

        def from_reference(t_s: float) -> tuple[npt.NDArray[np.float64], float]:
            ref = path.reference(t_s)
            return np.asarray(ref.pos_m, dtype=np.float64), float(ref.yaw_rad)

        return from_reference
    if callable(path):
        return path  # type: ignore[no-any-return]
    raise TypeError(f"{path!r} is neither a pattern (with .reference) nor a callable")


def calibration_motion(
    path: Any,
    *,
    rock_deg: Sequence[float] = (20.0, 20.0, 25.0),
    follow_yaw: bool = True,
    start_s: float = 0.0,
    phase_seed: int = 0,
) -> Callable[[float], Transform]:
    """A truth function for a calibration flight along ``path``.

    Args:
        path: a pattern or ``t_s -> (pos_m, yaw_rad)`` (see :func:`path_of`).
        rock_deg: peak roll, pitch and yaw swing about the path's attitude, degrees.
        follow_yaw: turn with the path's heading (False: keep heading 0).
        start_s: clock time at which the path starts.
        phase_seed: varies the phases of the rocking (same seed, same motion).

    Returns:
        clock seconds -> ``T_world_body``.
    """
    fn = path_of(path)
    amp = np.radians(np.asarray(rock_deg, dtype=np.float64))
    phases = np.random.default_rng(phase_seed).uniform(0.0, 2.0 * math.pi, (3, 2))

    def truth(t_s: float) -> Transform:
        t = t_s - start_s
        pos, yaw = fn(t)
        angles = [
            amp[k] * 0.5 * sum(math.sin(2.0 * math.pi * t / p + phases[k, j]) for j, p in enumerate(_PERIODS_S[k]))
            for k in range(3)
        ]
        heading = yaw if follow_yaw else 0.0  # about z, before the rocking's own z-y-x turns
        return Transform(Rotation.from_euler("ZYX", [heading + angles[2], angles[1], angles[0]]), pos)

    return truth


@dataclass(frozen=True, slots=True)
class CalibrationStreams:
    """What a calibration flight's recording holds, without rendering or a bus.

    Attributes:
        mocap: the body's poses as the simulated mocap stamps them (world frame; latency injected).
        camera: the camera's poses at the camera's stamps (offset and drift injected), in the
            world frame, as a drift-free VO would give them up to its noise.
        camera_truth_ns: the true capture time of each camera frame (int64 ns).
        start_ns: the true time at which both clocks started.
        errors: the injected timing errors.
        T_body_camera: the true mount.
    """

    mocap: Trajectory
    camera: Trajectory
    camera_truth_ns: npt.NDArray[np.int64]
    start_ns: int
    errors: SimTimingErrors
    T_body_camera: Transform


def simulate_streams(
    truth: Callable[[float], Transform],
    duration_s: float,
    *,
    errors: SimTimingErrors | None = None,
    T_body_camera: Transform | None = None,  # noqa: N803
    mocap_rate_hz: float = 120.0,
    camera_rate_hz: float = 30.0,
    mocap_noise_m: float = 0.0,
    mocap_noise_rad: float = 0.0,
    camera_noise_deg: float = 0.0,
    camera_noise_m: float = 0.0,
    seed: int = 0,
) -> CalibrationStreams:
    """Sample a calibration flight the way the simulated lab records it.

    The mocap poses come from :class:`~flightkit.sim.mocap.SimMocapSystem` (its stamping and its
    latency) on a lock-step clock; the camera stamps from :meth:`SimTimingErrors.camera_stamp_ns`,
    which :class:`~flightkit.sim.camera_publisher.SimCameraPublisher` uses too. Camera noise is
    a random walk per frame (VO's relative-motion error): ``camera_noise_deg`` about each axis and
    ``camera_noise_m`` along each axis.

    Returns immediately (no rendering); a minute of flight takes well under a second.
    """
    err = errors or SimTimingErrors()
    T_bc = T_body_camera or Transform.identity()  # noqa: N806
    clock = LockstepClock()
    start_ns = clock.time_ns()
    system = SimMocapSystem(clock, {"body": truth}, rate_hz=mocap_rate_hz, noise_m=mocap_noise_m,
                            noise_rad=mocap_noise_rad, seed=seed, latency_s=err.mocap_latency_s)
    stamps: list[int] = []
    poses: list[Transform] = []
    n_mocap = int(duration_s * mocap_rate_hz) + 1
    for i in range(n_mocap):
        if i:
            clock.advance(i / mocap_rate_hz - clock.monotonic_s())
        for s in system.sample():
            if s.T_frame_body is not None:
                stamps.append(s.stamp_ns)
                poses.append(s.T_frame_body)
    mocap = Trajectory.from_transforms(np.asarray(stamps, dtype=np.int64), poses, "mocap")
    rng = np.random.default_rng(seed + 1)
    n_cam = int(duration_s * camera_rate_hz) + 1
    true_ns = start_ns + np.round(np.arange(n_cam) / camera_rate_hz * 1e9).astype(np.int64)
    cam_stamps = np.array([err.camera_stamp_ns(int(t), start_ns) for t in true_ns], dtype=np.int64)
    drift_rot = Rotation.identity()
    drift_pos = np.zeros(3)
    cam_poses: list[Transform] = []
    for t in true_ns:
        T_wc = truth((int(t) - start_ns) / 1e9) @ T_bc  # noqa: N806
        if camera_noise_deg > 0:
            drift_rot = Rotation.from_rotvec(rng.normal(0.0, math.radians(camera_noise_deg), 3)) * drift_rot
        if camera_noise_m > 0:
            drift_pos = drift_pos + rng.normal(0.0, camera_noise_m, 3)
        cam_poses.append(Transform(drift_rot * T_wc.rotation, drift_rot.apply(T_wc.translation) + drift_pos))
    camera = Trajectory.from_transforms(cam_stamps, cam_poses, "camera")
    return CalibrationStreams(mocap, camera, true_ns, start_ns, err, T_bc)

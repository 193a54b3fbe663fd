"""Known timing and mounting errors the simulated lab injects, so calibration has exact answers.

* the camera's stamps run ``camera_time_offset_s`` late and its clock ``camera_drift_ppm`` fast:
  a frame captured at true time ``t`` is stamped ``t + offset + drift * 1e-6 * (t - start)``;
* the mocap poses reach the host ``mocap_latency_s`` after they were captured (the pose handed
  out now is the one of ``latency`` ago); they carry their capture time as the header stamp, as
  a system that reports its frame time does, and the bus time (arrival) beside it;
* the camera is really mounted at ``true_T_body_camera`` (default: where the config says).

So a calibration of the recording should find ``offset`` (camera minus mocap stamp, at the
start) and ``drift``: :meth:`SimTimingErrors.expected_offset_s`; the latency shows as the
difference between the mocap poses' bus time and their capture stamps, and as the age of the
pose a runner flies on.

All default to zero (no error); ``[sim]`` in the lab config sets them (``camera_time_offset_ms``,
``camera_drift_ppm``, ``mocap_latency_ms``, ``true_T_body_camera``).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from scipy.spatial.transform import Rotation

from flightkit.errors import ConfigError
from flightkit.frames import Transform

__all__ = ["PoseDelay", "SimTimingErrors"]

_NS = 1_000_000_000


@dataclass(frozen=True, slots=True)
class SimTimingErrors:
    """Timing errors of the simulated camera and mocap (see the module docstring).

    Attributes:
        camera_time_offset_s: how late the camera's stamps are, seconds (0-0.1 in the lab's tests).
        camera_drift_ppm: how fast the camera's clock runs, parts per million.
        mocap_latency_s: capture-to-arrival delay of the mocap poses, seconds.
    """

    camera_time_offset_s: float = 0.0
    camera_drift_ppm: float = 0.0
    mocap_latency_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("camera_time_offset_s", "camera_drift_ppm", "mocap_latency_s"):
            if not math.isfinite(getattr(self, name)):
                raise ConfigError("<sim>", name, "not finite", "give a finite number", getattr(self, name))
        if self.mocap_latency_s < 0:
            raise ConfigError("<sim>", "mocap_latency_s", "negative", "give a latency >= 0", self.mocap_latency_s)

    def camera_stamp_ns(self, true_ns: int, start_ns: int) -> int:
        """The stamp the camera puts on a frame captured at ``true_ns`` (its clock started at ``start_ns``)."""
        err_s = self.camera_time_offset_s + self.camera_drift_ppm * 1e-6 * (true_ns - start_ns) / _NS
        return true_ns + round(err_s * _NS)

    def expected_offset_s(self, at_ns: int, start_ns: int) -> float:
        """Camera stamp minus mocap stamp of one instant at true time ``at_ns``: what a time calibration
        should find there."""
        drift_s = self.camera_drift_ppm * 1e-6 * (at_ns - start_ns) / _NS
        return self.camera_time_offset_s + drift_s

    @property
    def any(self) -> bool:
        return bool(self.camera_time_offset_s or self.camera_drift_ppm or self.mocap_latency_s)


class PoseDelay:
    """A short history of true poses, to hand out the pose of ``delay_s`` ago (slerped between samples).

    Args:
        delay_s: how far back, seconds (0: the pose given is returned as is).
    """

    def __init__(self, delay_s: float) -> None:
        self.delay_s = float(delay_s)
        self._hist: deque[tuple[float, Transform]] = deque()

    def __call__(self, now_s: float, T_world_body: Transform) -> Transform:  # noqa: N803
        """Record the pose at ``now_s`` and return the one of ``now_s - delay_s`` (the oldest known at first)."""
        if self.delay_s <= 0.0:
            return T_world_body
        hist = self._hist
        if hist and now_s <= hist[-1][0]:
            hist.clear()  # time went back: a new run
        hist.append((now_s, T_world_body))
        want = now_s - self.delay_s
        while len(hist) > 2 and hist[1][0] <= want:
            hist.popleft()
        t0, T0 = hist[0]  # noqa: N806
        if want <= t0 or len(hist) == 1:
            return T0
        t1, T1 = hist[1]  # noqa: N806
        u = (want - t0) / (t1 - t0)
        rot = T0.rotation * Rotation.from_rotvec(u * (T0.rotation.inv() * T1.rotation).as_rotvec())
        return Transform(rot, (1.0 - u) * T0.translation + u * T1.translation)

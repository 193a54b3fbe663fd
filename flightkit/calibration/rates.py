"""Angular rates from a sequence of timestamped orientations.

A pose trajectory (mocap body, VO camera) gives orientations ``R_world_x`` at stamps; the body
rate between two consecutive samples is ``log(R_i^-1 R_{i+1}) / dt`` in the frame ``x`` (body
rates, as a gyro measures them), assigned to the midpoint of the interval. It does not depend on
the world frame the orientations are given in, so a VO camera trajectory (arbitrary world) and a
mocap trajectory (lab world) give comparable rates.

Pure numpy/scipy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation, Slerp

from flightkit.errors import CalibrationError
from flightkit.frames import quat_wxyz_to_xyzw

__all__ = [
    "AngularRates",
    "TimedOrientations",
    "angular_rates",
    "interval_rates",
    "rotations_of",
]

_NS = 1e-9


class TimedOrientations(Protocol):
    """Anything with stamps and orientations, e.g. :class:`flightkit.datasets.trajectory.Trajectory`.

    Attributes:
        stamps_ns: int64 (N,), strictly increasing.
        quats_wxyz: float64 (N, 4), orientation ``R_world_x`` of each sample.
    """

    @property
    def stamps_ns(self) -> npt.NDArray[np.int64]: ...

    @property
    def quats_wxyz(self) -> npt.NDArray[np.float64]: ...


@dataclass(frozen=True, slots=True)
class AngularRates:
    """Body rates at stamps.

    Attributes:
        stamps_s: float64 (N,), seconds (same epoch as the input stamps).
        omega_rad_s: float64 (N, 3), body-frame angular rate, rad/s.
    """

    stamps_s: npt.NDArray[np.float64]
    omega_rad_s: npt.NDArray[np.float64]

    @property
    def norm_rad_s(self) -> npt.NDArray[np.float64]:
        """|omega| per sample, rad/s (N,)."""
        return np.asarray(np.linalg.norm(self.omega_rad_s, axis=1), dtype=np.float64)

    def resampled(self, rate_hz: float, start_s: float | None = None, stop_s: float | None = None) -> AngularRates:
        """Linearly interpolated onto a uniform grid of ``rate_hz`` (within the samples' span)."""
        if not rate_hz > 0:
            raise CalibrationError(f"a resampling rate must be > 0 Hz, got {rate_hz!r}; give e.g. 200")
        lo = self.stamps_s[0] if start_s is None else max(start_s, self.stamps_s[0])
        hi = self.stamps_s[-1] if stop_s is None else min(stop_s, self.stamps_s[-1])
        n = int(np.floor((hi - lo) * rate_hz + 1e-9)) + 1
        grid = lo + np.arange(max(n, 0)) / rate_hz
        omega = np.stack([np.interp(grid, self.stamps_s, self.omega_rad_s[:, k]) for k in range(3)], axis=1)
        return AngularRates(grid, omega)


def rotations_of(orientations: TimedOrientations, origin_ns: int = 0) -> tuple[npt.NDArray[np.float64], Rotation]:
    """(stamps in seconds since ``origin_ns``, rotations) of a trajectory, checked.

    Give an ``origin_ns`` near the data (epoch stamps as float seconds keep only ~0.2 us).

    Raises:
        CalibrationError: fewer than 3 samples or stamps that do not increase.
    """
    stamps = np.asarray(orientations.stamps_ns, dtype=np.int64)
    if stamps.shape[0] < 3:
        raise CalibrationError(f"{stamps.shape[0]} orientation samples are too few for a rate; record longer")
    if np.any(np.diff(stamps) <= 0):
        raise CalibrationError("orientation stamps must increase strictly; sort and de-duplicate them first")
    t_s = (stamps - np.int64(origin_ns)).astype(np.float64) * _NS
    return t_s, Rotation.from_quat(quat_wxyz_to_xyzw(np.asarray(orientations.quats_wxyz, dtype=np.float64)))


def angular_rates(
    orientations: TimedOrientations, max_gap_s: float | None = None, origin_ns: int = 0
) -> AngularRates:
    """Body rates between consecutive samples, at the interval midpoints.

    Args:
        orientations: the trajectory (``R_world_x``).
        origin_ns: the epoch of the returned stamps (seconds since ``origin_ns``).
        max_gap_s: intervals longer than this are left out (default: 3x the median interval).

    Raises:
        CalibrationError: too few samples, or stamps that do not increase.
    """
    t_s, rots = rotations_of(orientations, origin_ns)
    dt = np.diff(t_s)
    gap = 3.0 * float(np.median(dt)) if max_gap_s is None else max_gap_s
    rel = rots[:-1].inv() * rots[1:]
    omega = rel.as_rotvec() / dt[:, None]
    keep = dt <= gap
    mid = 0.5 * (t_s[:-1] + t_s[1:])
    return AngularRates(mid[keep], np.asarray(omega[keep], dtype=np.float64))


def interval_rates(
    slerp: Slerp, start_s: npt.NDArray[np.float64], stop_s: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """The mean body rate over each interval [start, stop] of an interpolated orientation track,
    rad/s (N, 3): the rate a sensor sampling at those instants would see. Instants a rounding
    error outside the track are taken at its ends."""
    lo, hi = float(slerp.times[0]), float(slerp.times[-1])
    r0 = slerp(np.clip(start_s, lo, hi))
    r1 = slerp(np.clip(stop_s, lo, hi))
    return np.asarray((r0.inv() * r1).as_rotvec() / (stop_s - start_s)[:, None], dtype=np.float64)

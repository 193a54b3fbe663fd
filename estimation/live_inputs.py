"""The camera side of live visual odometry: colour and depth frames paired by stamp, and the
pinhole intrinsics of a ``camera_info`` message."""

from __future__ import annotations

import collections
from typing import Any

from flightkit.bus.image_msgs import CameraInfo
from flightkit.datasets.base import CameraIntrinsics
from flightkit.errors import EstimationError

__all__ = ["FramePairer", "intrinsics_from_camera_info"]


def intrinsics_from_camera_info(info: CameraInfo) -> CameraIntrinsics:
    """Pinhole intrinsics (and distortion, when any coefficient is non-zero) of a CameraInfo.

    Raises:
        EstimationError: the CameraInfo has no focal length (an uncalibrated camera).
    """
    fx, fy, cx, cy = info.k[0], info.k[4], info.k[2], info.k[5]
    if not (fx > 0 and fy > 0):
        raise EstimationError(
            f"camera_info has no focal length (K = {list(info.k)}); calibrate the camera or fix its driver"
        )
    dist = tuple(float(d) for d in info.d) if any(d != 0.0 for d in info.d) else ()
    return CameraIntrinsics(fx, fy, cx, cy, int(info.width), int(info.height), dist)


class FramePairer:
    """Pairs colour and depth frames by stamp (depth aligned to colour arrives separately).

    Add each frame as it arrives; a pair comes back as soon as its partner is there (stamps
    within ``tolerance_ns``). Frames older than a matched pair can no longer be matched and
    are discarded (counted in :attr:`unmatched`); at most ``keep`` frames of each stream wait.
    Not thread-safe: call it under one lock.
    """

    def __init__(self, tolerance_ns: int = 1_000_000, keep: int = 4) -> None:
        self.tolerance_ns = int(tolerance_ns)
        self.keep = max(1, int(keep))
        self._waiting: dict[str, collections.OrderedDict[int, Any]] = {
            "color": collections.OrderedDict(),
            "depth": collections.OrderedDict(),
        }
        self.unmatched = 0
        self.paired = 0

    def add_color(self, stamp_ns: int, item: Any) -> tuple[int, Any, Any] | None:
        """Add a colour frame; returns ``(stamp_ns, color, depth)`` when it completes a pair."""
        return self._add("color", "depth", stamp_ns, item)

    def add_depth(self, stamp_ns: int, item: Any) -> tuple[int, Any, Any] | None:
        """Add a depth frame; returns ``(stamp_ns, color, depth)`` when it completes a pair."""
        return self._add("depth", "color", stamp_ns, item)

    def _add(self, mine: str, other: str, stamp_ns: int, item: Any) -> tuple[int, Any, Any] | None:
        theirs = self._waiting[other]
        best: int | None = None
        for s in theirs:
            if abs(s - stamp_ns) <= self.tolerance_ns and (
                best is None or abs(s - stamp_ns) < abs(best - stamp_ns)
            ):
                best = s
        if best is None:
            own = self._waiting[mine]
            own[int(stamp_ns)] = item
            while len(own) > self.keep:
                own.popitem(last=False)
                self.unmatched += 1
            return None
        partner = theirs.pop(best)
        # everything older than this pair in either stream can no longer be paired
        for stream in (theirs, self._waiting[mine]):
            for s in [s for s in stream if s < min(best, stamp_ns)]:
                del stream[s]
                self.unmatched += 1
        self.paired += 1
        if mine == "color":
            return int(stamp_ns), item, partner
        return int(best), partner, item

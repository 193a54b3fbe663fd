"""What visual odometry returns: per-frame :class:`FramePose` (with its :class:`Quality` flag)
and the whole run's :class:`VoResult`, which counts the frames it could not estimate."""

from __future__ import annotations

import enum
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from flightkit.errors import EstimationError

if TYPE_CHECKING:
    from flightkit.datasets.trajectory import Trajectory

__all__ = ["MAX_FAILED_FRACTION", "STAGES", "FramePose", "FrameTimer", "Quality", "VoResult", "collect_result"]

F64 = npt.NDArray[np.float64]

STAGES = ("track", "motion", "keyframe", "ba", "total")
"""Per-frame timing stages, milliseconds: front-end tracking (pyramid + LK), motion
estimation (incl. fallback), keyframe creation (detection + 3D), bundle adjustment, total."""


class Quality(enum.IntEnum):
    """How a pose was obtained."""

    INIT = 0  #: the start pose: the first keyframe, or held while an RGB-D method waits for depth
    GOOD = 1  #: estimate with enough inliers
    WEAK = 2  #: estimate accepted, but with few inliers (< 2 x min_inliers)
    PREDICTED = 3  #: not estimated (failed or implausible): the constant-velocity prediction is kept
    FALLBACK = 4  #: tracking failed; ORB matching against the keyframe recovered the pose

    @property
    def estimated(self) -> bool:
        """The pose was measured from the images (GOOD, WEAK or FALLBACK)."""
        return self in (Quality.GOOD, Quality.WEAK, Quality.FALLBACK)


MAX_FAILED_FRACTION = 0.5
"""A run in which the motion of more than this fraction of the frames could not be estimated
is an error (:meth:`VoResult.check`)."""


@dataclass(frozen=True, slots=True, eq=False)
class FramePose:
    """The VO output of one frame.

    Attributes:
        index: frame counter (0-based).
        stamp_ns: frame stamp.
        T_world_camera, T_world_body: (4, 4) poses.
        n_inliers: correspondences supporting the estimate (0 when predicted/initial).
        quality: :class:`Quality`.
        keyframe: this frame became a keyframe.
        stage_ms: per-stage processing (wall) time of this frame (keys from :data:`STAGES`).
        cpu_ms: CPU time of this thread for the frame (differs from the wall time when the
            core is shared).
    """

    index: int
    stamp_ns: int
    T_world_camera: F64
    T_world_body: F64
    n_inliers: int
    quality: Quality
    keyframe: bool
    stage_ms: dict[str, float]
    cpu_ms: float = 0.0


@dataclass(frozen=True, slots=True, eq=False)
class VoResult:
    """All frames of one VO run.

    Attributes:
        method: the method name.
        sequence: the sequence name.
        stamps_ns: (N,) int64.
        T_world_camera, T_world_body: (N, 4, 4).
        n_inliers: (N,) int.
        quality: (N,) int8 values of :class:`Quality`.
        keyframe: (N,) bool.
        stage_ms: stage -> (N,) float64 milliseconds (:data:`STAGES`).
        wall_s: wall time of the run including image loading.
        image_size: (width, height) processed.
        cpu_ms: (N,) per-frame CPU time of the processing thread.
    """

    method: str
    sequence: str
    stamps_ns: npt.NDArray[np.int64]
    T_world_camera: F64
    T_world_body: F64
    n_inliers: npt.NDArray[np.int64]
    quality: npt.NDArray[np.int8]
    keyframe: npt.NDArray[np.bool_]
    stage_ms: dict[str, F64]
    wall_s: float
    image_size: tuple[int, int]
    cpu_ms: F64 = field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @property
    def fps(self) -> float:
        """Frames per second of processing (images already decoded), from the total stage."""
        total = float(np.sum(self.stage_ms["total"]))
        return len(self) / (total * 1e-3) if total > 0 else math.inf

    @property
    def fps_cpu(self) -> float:
        """Frames per CPU second of the processing thread (what one dedicated core would do)."""
        total = float(np.sum(self.cpu_ms))
        return len(self) / (total * 1e-3) if total > 0 else math.inf

    def trajectory(self, frame: str = "camera") -> Trajectory:
        """The poses as a :class:`~flightkit.datasets.trajectory.Trajectory` (``"camera"`` or ``"body"``)."""
        from flightkit.datasets.trajectory import Trajectory

        if frame not in ("camera", "body"):
            raise EstimationError(f"trajectory frame must be 'camera' or 'body', got {frame!r}")
        mats = self.T_world_camera if frame == "camera" else self.T_world_body
        return Trajectory.from_matrices(self.stamps_ns, mats, name=f"{self.method}")

    def write_tum(self, path: str | Path, frame: str = "camera") -> Path:
        """Write the trajectory as a TUM file; returns the path."""
        from flightkit.datasets.trajectory import write_tum

        return write_tum(
            path, self.trajectory(frame), header=f"flightkit vo {self.method} on {self.sequence} ({frame})"
        )

    @property
    def n_failed(self) -> int:
        """Frames after the first whose motion was not estimated: predicted (``Quality.PREDICTED``)
        or held at the start pose (``Quality.INIT`` while waiting for depth)."""
        q = self.quality[1:]
        return int(np.count_nonzero((q == Quality.PREDICTED) | (q == Quality.INIT)))

    @property
    def failed_fraction(self) -> float:
        """:attr:`n_failed` over the frames after the first (0 for a single frame)."""
        return self.n_failed / (len(self) - 1) if len(self) > 1 else 0.0

    def failure_message(self) -> str:
        """One sentence: how many frames were not estimated, and what that means."""
        return (
            f"{self.method} could not estimate the motion of {self.n_failed} of {len(self) - 1} frames of "
            f"{self.sequence} ({100.0 * self.failed_fraction:.0f} %); those poses are the constant-velocity "
            "prediction, not measurements"
        )

    def check(self, max_failed_fraction: float = MAX_FAILED_FRACTION) -> None:
        """Raise when the motion of most of the sequence could not be estimated.

        Raises:
            EstimationError: more than ``max_failed_fraction`` of the frames were not estimated.
        """
        if self.failed_fraction > max_failed_fraction:
            raise EstimationError(
                f"{self.failure_message()}: the method does not suit this sequence or sensor "
                "(docs/estimation.md, 'When VO fails')"
            )

    def summary(self) -> dict[str, float]:
        """Mean per-stage milliseconds and frames/s."""
        out = {f"{k}_ms": float(np.mean(v)) if len(v) else 0.0 for k, v in self.stage_ms.items()}
        out["fps"] = self.fps
        return out


def collect_result(poses: list[FramePose], method: str, name: str, wall_s: float, size: tuple[int, int]) -> VoResult:
    """Stack per-frame poses into a :class:`VoResult`."""
    if not poses:
        raise EstimationError(f"no frames were processed for {name}; check the frame range")
    return VoResult(
        method=method,
        sequence=name,
        stamps_ns=np.array([p.stamp_ns for p in poses], dtype=np.int64),
        T_world_camera=np.stack([p.T_world_camera for p in poses]),
        T_world_body=np.stack([p.T_world_body for p in poses]),
        n_inliers=np.array([p.n_inliers for p in poses], dtype=np.int64),
        quality=np.array([int(p.quality) for p in poses], dtype=np.int8),
        keyframe=np.array([p.keyframe for p in poses], dtype=bool),
        stage_ms={s: np.array([p.stage_ms[s] for p in poses]) for s in STAGES},
        wall_s=wall_s,
        image_size=size,
        cpu_ms=np.array([p.cpu_ms for p in poses]),
    )


class FrameTimer:
    """Per-stage wall milliseconds (:data:`STAGES`) and the thread's CPU time of one frame."""

    __slots__ = ("_cpu0", "_t", "ms")

    def __init__(self) -> None:
        self.ms = dict.fromkeys(STAGES, 0.0)
        self._t = time.perf_counter()
        self._cpu0 = time.thread_time()

    def cpu_ms(self) -> float:
        return (time.thread_time() - self._cpu0) * 1e3

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.ms[stage] += (now - self._t) * 1e3
        self._t = now

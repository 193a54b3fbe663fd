"""A recorded sequence replayed another way: backwards, or every n-th frame.

Both are harder variants of the same real data, for checking that an estimator holds up on
motion it was not tuned on (``bench/vo.py --replay``):

* :func:`reversed_sequence` plays the frames from last to first, with the stamps mirrored so
  they still increase (``t' = t_first + t_last - t``) and the ground truth remapped the same
  way. A car driving forwards becomes one reversing; a camera turning left turns right.
  Played backwards, a rolling shutter would read its rows from the bottom up; with
  ``mirror_rows`` (the default for a rolling-shutter camera) the images are also flipped
  upside down, so the readout runs top to bottom again and the sequence is one a real camera
  could have recorded: that of a mirrored world (``y -> -y`` in every camera and world frame,
  ``T' = S T S`` with ``S = diag(1, -1, 1)``, still a proper rotation).
* :func:`strided_sequence` keeps every ``step``-th frame from ``offset`` on: the same camera at
  a lower frame rate, so each step is ``step`` times larger.
* :func:`exposure_sequence` multiplies each frame's images by a gain (:func:`lognormal_gains`: the
  bench's and the tests' seeded set), as a camera's automatic
  exposure does from frame to frame (the depth images are left as they are).

The result is a :class:`~flightkit.datasets.base.Sequence` like any other: ``run_vo``,
``run_plain`` and the evaluation take it as they take the original.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from flightkit.datasets.base import CameraIntrinsics, Frame, Sequence, StereoRectification
from flightkit.datasets.trajectory import Trajectory
from flightkit.errors import DatasetError
from flightkit.frames import Transform

__all__ = [
    "ReplayedSequence",
    "exposure_sequence",
    "lognormal_gains",
    "mirror_rows_intrinsics",
    "reversed_sequence",
    "strided_sequence",
]

_MIRROR_XYZ = np.array([1.0, -1.0, 1.0])
"""The mirror ``y -> -y`` of a camera or world frame (``S``'s diagonal)."""

_S4 = np.diag([*_MIRROR_XYZ, 1.0])
"""``S`` as a homogeneous transform."""

_QUAT_WXYZ_MIRROR = np.array([1.0, -1.0, 1.0, -1.0])
"""``S R S`` of a rotation with quaternion (w, x, y, z) has the quaternion (w, -x, y, -z)."""


def mirror_rows_intrinsics(k: CameraIntrinsics) -> CameraIntrinsics:
    """The camera of images flipped upside down: the principal point's row mirrored, and the
    first tangential distortion term (``p1``, the one odd in y) negated."""
    dist = list(k.dist)
    if len(dist) >= 3:
        dist[2] = -dist[2]
    return replace(k, cy=k.height - 1 - k.cy, dist=tuple(dist))


class ReplayedSequence:
    """Frames of another sequence in another order (see the module docstring); build it with
    :func:`reversed_sequence` or :func:`strided_sequence`.

    Args:
        source: the sequence replayed.
        indices: the source's frame indices, in replay order (increasing or decreasing).
        mirror_rows: flip every image upside down and mirror the poses with it.
        name: the replay's name (tables and logs).
        gains: one factor per replayed frame for its 8-bit images (None: as recorded).
    """

    def __init__(
        self,
        source: Sequence,
        indices: list[int],
        mirror_rows: bool,
        name: str,
        gains: npt.ArrayLike | None = None,
    ) -> None:
        if len(indices) < 2:
            raise DatasetError(f"a replay of {source.name} needs at least 2 frames, got {len(indices)}")
        self._gains = None if gains is None else np.asarray(gains, dtype=np.float64).reshape(-1)
        if self._gains is not None and (
            len(self._gains) != len(indices) or not np.all(np.isfinite(self._gains) & (self._gains > 0))
        ):
            raise DatasetError(
                f"exposure gains for {source.name}: {len(self._gains)} given for {len(indices)} frames; "
                "give one positive, finite gain per frame"
            )
        self._source = source
        self._indices = list(indices)
        self._mirror = bool(mirror_rows)
        self.name = name
        self.kind: str = source.kind
        self.path: Path = source.path
        self.baseline_m: float | None = source.baseline_m
        self.rectification: StereoRectification | None = source.rectification
        self.intrinsics: CameraIntrinsics = (
            mirror_rows_intrinsics(source.intrinsics) if self._mirror else source.intrinsics
        )
        d = source.depth_intrinsics
        self.depth_intrinsics: CameraIntrinsics | None = (
            mirror_rows_intrinsics(d) if (self._mirror and d is not None) else d
        )
        self.depth_registered = bool(getattr(source, "depth_registered", True))
        src_stamps = source.stamps_ns()
        self._reversed = indices[-1] < indices[0]
        # Reversed: t' = t_first + t_last - t keeps the stamps increasing over the same span.
        self._stamp_sum_ns = int(src_stamps[0]) + int(src_stamps[-1]) if self._reversed else 0
        self._stamps = self._map_stamps(src_stamps[self._indices])

    def _map_stamps(self, stamps_ns: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        s = np.asarray(stamps_ns, dtype=np.int64)
        return (self._stamp_sum_ns - s) if self._reversed else s.copy()

    def _map_pose(self, T: Transform | None) -> Transform | None:  # noqa: N803
        if T is None or not self._mirror:
            return T
        return Transform.from_matrix(_S4 @ T.as_matrix() @ _S4)

    def __len__(self) -> int:
        return len(self._indices)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, frames={len(self)})"

    def stamps_ns(self) -> npt.NDArray[np.int64]:
        return self._stamps.copy()

    def _source_frame(self, index: int) -> Frame:
        frame = getattr(self._source, "frame", None)
        if frame is not None:
            return frame(index)  # type: ignore[no-any-return]
        return next(iter(self._source.frames(index, index + 1)))

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1) -> Iterator[Frame]:
        flip = _flip_rows if self._mirror else _same
        for pos in range(len(self))[start:stop:step]:
            f = self._source_frame(self._indices[pos])
            gain = 1.0 if self._gains is None else float(self._gains[pos])
            yield replace(
                f,
                index=pos,
                stamp_ns=int(self._stamps[pos]),
                gray=_scaled(flip(f.gray), gain),
                color_bgr=_scaled(flip(f.color_bgr), gain),
                right_gray=_scaled(flip(f.right_gray), gain),
                depth_raw=flip(f.depth_raw),
                T_world_camera=self._map_pose(f.T_world_camera),
            )

    def has_groundtruth(self) -> bool:
        return self._source.has_groundtruth()

    def groundtruth(self) -> Trajectory:
        gt = self._source.groundtruth()
        order = slice(None, None, -1) if self._reversed else slice(None)
        positions = gt.positions[order]
        quats = gt.quats_wxyz[order]
        if self._mirror:
            positions = positions * _MIRROR_XYZ
            quats = quats * _QUAT_WXYZ_MIRROR
        return Trajectory(self._map_stamps(gt.stamps_ns)[order], positions, quats, name=gt.name)


def _flip_rows(image: Any) -> Any:
    return None if image is None else np.ascontiguousarray(image[::-1])


def _same(image: Any) -> Any:
    return image


def _scaled(image: Any, gain: float) -> Any:
    """An 8-bit image times ``gain``, rounded and saturated as a sensor's would be."""
    if image is None or gain == 1.0:
        return image
    return np.clip(np.rint(image.astype(np.float32) * gain), 0, 255).astype(np.uint8)


def reversed_sequence(source: Sequence, mirror_rows: bool | None = None) -> ReplayedSequence:
    """``source`` played from its last frame to its first (see the module docstring).

    Args:
        mirror_rows: also flip the images upside down (and mirror the poses), so a rolling
            shutter still reads top to bottom; None: when the camera has one
            (``intrinsics.readout_s > 0``).
    """
    mirror = source.intrinsics.readout_s > 0 if mirror_rows is None else mirror_rows
    name = f"{source.name} reversed" + (", rows mirrored" if mirror else "")
    return ReplayedSequence(source, list(range(len(source) - 1, -1, -1)), mirror, name)


def strided_sequence(source: Sequence, step: int, offset: int = 0) -> ReplayedSequence:
    """Every ``step``-th frame of ``source`` from ``offset`` on (a lower frame rate)."""
    if step < 1 or not 0 <= offset < step:
        raise DatasetError(f"stride {step} from frame {offset}: use a step >= 1 and 0 <= offset < step")
    return ReplayedSequence(
        source, list(range(offset, len(source), step)), False, f"{source.name} every {step} from {offset}"
    )


def exposure_sequence(source: Sequence, gains: npt.ArrayLike) -> ReplayedSequence:
    """``source`` with frame ``i``'s images (gray, colour, right) multiplied by ``gains[i]``, rounded
    and saturated at 255: a camera's exposure changing from frame to frame. Depth is unchanged."""
    g = np.asarray(gains, dtype=np.float64).reshape(-1)
    spread = float(np.std(np.log(g))) if len(g) and np.all(g > 0) else float("nan")
    name = f"{source.name} with exposure changes ({100 * spread:.2g} % rms)"
    return ReplayedSequence(source, list(range(len(source))), False, name, gains=g)


def lognormal_gains(n: int, rms: float = 0.15, seed: int = 0) -> npt.NDArray[np.float64]:
    """``n`` exposure gains whose logarithms are normal with standard deviation ``rms`` (seeded):
    the exposure replay of the bench and the tests (:func:`exposure_sequence`)."""
    return np.exp(np.random.default_rng(seed).normal(0.0, rms, n))

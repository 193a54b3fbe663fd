"""Calibration jobs on a recording: camera-to-mocap time offset and drift, hand-eye ``T_body_camera``.

``flightkit calibrate time|handeye`` call these; so can a notebook::

    res = calibrate_recording("run.mcap", what="time")           # VO on the recording, then the estimate
    res = calibrate_recording("run.mcap", what="handeye", camera_trajectory="vo.txt")
    write_calibration(res, "cal.json")                            # or "run.mcap" (metadata record)

The body's motion is the recording's mocap pose topic (world frame, through
:class:`~flightkit.datasets.mcap_reader.RecordingReader`); the camera's motion is a visual
odometry run over the recording's images (:func:`estimation.pipeline.run_vo`) or a camera
trajectory file (TUM) made earlier. The numerics are in :mod:`flightkit.calibration`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from flightkit.calibration import (
    METADATA_RECORD,
    CalibrationResult,
    estimate_hand_eye,
    estimate_time_offset,
)
from flightkit.config import LabConfig
from flightkit.datasets.mcap_reader import RecordingReader
from flightkit.datasets.trajectory import Trajectory, read_trajectory
from flightkit.errors import CalibrationError, DatasetError
from flightkit.frames import Transform

__all__ = ["CalibrationInputs", "calibrate_recording", "load_inputs", "write_calibration"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class CalibrationInputs:
    """The two motions a calibration compares.

    Attributes:
        body: the mocap body's trajectory (world frame, mocap stamps).
        camera: the camera's trajectory (any fixed frame, camera stamps).
        configured_T_body_camera: the mount the config or the recording says (None when neither).
        source: what they came from (recording, topic, VO method or file).
        vo_s: wall time of the VO run (0 when a trajectory file was given).
    """

    body: Trajectory
    camera: Trajectory
    configured_T_body_camera: Transform | None
    source: dict[str, str]
    vo_s: float = 0.0


def _body_trajectory(reader: RecordingReader, body: str | None, lab_cfg: LabConfig | None) -> tuple[Trajectory, str]:
    topics = reader.mocap_topics()
    if not topics:
        raise DatasetError(f"{reader.path} has no mocap pose topic (<ns>/mocap/<body>/pose); record the mocap too")
    name = body or (lab_cfg.mocap.body if lab_cfg is not None else "") or reader.calibration().mocap_body
    if not name or name not in topics:
        if body:
            raise DatasetError(f"{reader.path} has no mocap body {body!r}; it has {', '.join(sorted(topics))}")
        name = sorted(topics)[0]
    frames = reader.world_frames(lab_cfg.mocap.T_world_mocap.to_transform() if lab_cfg is not None else None)
    return reader.pose_trajectory(topics[name], frames, name=f"mocap {name}"), topics[name]


def load_inputs(
    recording: str | Path,
    *,
    body: str | None = None,
    camera: str | None = None,
    camera_trajectory: str | Path | None = None,
    method: str = "rgbd-pnp",
    size: tuple[int, int] | None = None,
    lab_cfg: LabConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
    board: str | None = None,
) -> CalibrationInputs:
    """The body and camera motions of a recording.

    Args:
        recording: the ``.mcap`` file.
        body: the mocap body (default: the config's, else the recording's, else the first).
        camera: the camera whose images VO runs on (default: the recording's main camera).
        camera_trajectory: a TUM/KITTI file of the camera's poses at its own stamps; skips VO.
        method: the VO method (``rgbd-pnp``, ``stereo``, ...).
        size: process images at (width, height).
        lab_cfg: gives ``T_world_mocap`` and the configured ``T_body_camera`` when given.
        progress: ``progress(done, total)`` per VO frame.
        board: a ChArUco board or AprilTag grid fixed in the room, ``"5x7:0.04:0.03[:DICT]"`` or
            ``"apriltag:6x6:0.05:0.04"`` (:func:`~flightkit.calibration.board.parse_board`): the camera's
            motion is its pose against the board in every image that shows it, instead of VO.

    Raises:
        DatasetError: unreadable recording, no mocap, no camera. EstimationError: VO cannot run.
    """
    reader = RecordingReader(recording)
    traj_body, topic = _body_trajectory(reader, body, lab_cfg)
    configured = (
        lab_cfg.camera.T_body_camera.to_transform() if lab_cfg is not None else reader.calibration().T_body_camera
    )
    source = {"recording": str(recording), "mocap_topic": topic}
    if camera_trajectory is not None:
        cam = read_trajectory(Path(camera_trajectory))
        source["camera_trajectory"] = str(camera_trajectory)
        return CalibrationInputs(traj_body, cam, configured, source)
    from flightkit.datasets import open_sequence

    seq = open_sequence(recording, **({"camera": camera} if camera else {}))
    if board is not None:
        return _board_inputs(seq, board, traj_body, configured, source)
    from estimation.pipeline import run_vo

    t0 = time.perf_counter()
    result = run_vo(seq, method, size=size, progress=progress)
    vo_s = time.perf_counter() - t0
    source.update(camera_motion=f"vo {method}", camera=camera or "main")
    return CalibrationInputs(traj_body, result.trajectory("camera"), configured, source, vo_s)


def _board_inputs(seq: Any, board: str, body: Trajectory, configured: Transform | None,
                  source: dict[str, str]) -> CalibrationInputs:
    from flightkit.calibration.board import BoardDetector, board_camera_poses, parse_board

    k = seq.intrinsics
    spec = parse_board(board)
    detector = BoardDetector(spec, [[k.fx, 0, k.cx], [0, k.fy, k.cy], [0, 0, 1]], list(k.dist) or None)
    t0 = time.perf_counter()
    stamps, poses, errors = board_camera_poses(detector, ((f.stamp_ns, f.gray) for f in seq.frames()))
    if len(stamps) < 10:
        raise CalibrationError(
            f"the board {board} was found in {len(stamps)} of {len(seq)} images; keep it in view, well lit and "
            "sharp, and check its size and dictionary",
            "T_body_camera",
        )
    source.update(camera_motion=f"{spec.kind} board {board}", board_images=str(len(stamps)),
                  board_reprojection_px=f"{float(np.median(errors)):.3f}")
    cam = Trajectory.from_transforms(np.asarray(stamps, dtype=np.int64), poses, "board")
    return CalibrationInputs(body, cam, configured, source, time.perf_counter() - t0)


def calibrate_recording(
    recording: str | Path,
    what: str,
    *,
    inputs: CalibrationInputs | None = None,
    max_offset_s: float = 0.5,
    window_s: float = 10.0,
    **load_options: object,
) -> CalibrationResult:
    """Calibrate ``what`` (``"time"`` or ``"handeye"``) from a recording. Hand-eye estimates the
    time offset first and aligns the camera frames with it, so its result carries both.

    Args:
        recording: the ``.mcap`` file.
        what: ``"time"`` or ``"handeye"``.
        inputs: the motions, when already loaded (else :func:`load_inputs` with ``load_options``).
        max_offset_s: the largest time offset searched.
        window_s: window length for the drift.

    Returns:
        The result. Blocks through the VO run (minutes for a long recording) and the estimates (seconds).

    Raises:
        CalibrationError: too little rotation, or no clear answer (the message says what to fly).
        DatasetError, EstimationError: see :func:`load_inputs`.
    """
    if what not in ("time", "handeye"):
        raise CalibrationError(f"unknown calibration {what!r}; use time or handeye", what)
    data = inputs or load_inputs(recording, **load_options)  # type: ignore[arg-type]
    t0 = time.perf_counter()
    est = estimate_time_offset(data.body, data.camera, max_offset_s=max_offset_s, window_s=window_s)
    res = CalibrationResult(
        time_offset_ms=est.offset_s * 1e3,
        time_offset_uncertainty_ms=est.offset_uncertainty_s * 1e3,
        drift_ppm=est.drift_ppm,
        drift_uncertainty_ppm=est.drift_uncertainty_ppm,
        drift_estimated=est.drift_estimated,
        ref_ns=est.ref_ns,
        correlation=est.correlation,
        configured_T_body_camera=data.configured_T_body_camera,
        source=dict(data.source),
    )
    if what == "handeye":
        he = estimate_hand_eye(data.body, data.camera, camera_to_body_ns=est.camera_to_mocap_ns)
        res = res.merged(
            CalibrationResult(T_body_camera=he.T_body_camera, residual_m=he.residual_m, residual_deg=he.residual_deg,
                              pairs=he.pairs)
        )
    logger.info("calibration of %s took %.2f s (VO %.1f s)", recording, time.perf_counter() - t0, data.vo_s)
    return res


def write_calibration(result: CalibrationResult, target: str | Path, *, recording: str | Path | None = None,
                      force: bool = False) -> Path:
    """Store a result: ``*.json`` as a calibration file; ``*.mcap`` as a copy of ``recording`` with
    the result in its metadata (record :data:`~flightkit.calibration.METADATA_RECORD`; ``target``
    may be ``recording`` itself, replaced atomically). Returns the path written.

    Raises:
        CalibrationError: another suffix, or ``.mcap`` without ``recording``.
        CaptureError: ``target`` exists (other than the recording) without ``force``.
    """
    path = Path(target)
    if path.suffix.lower() == ".json":
        return result.write_json(path)
    if path.suffix.lower() == ".mcap":
        if recording is None:
            raise CalibrationError("storing a calibration into a recording needs the recording to copy", "calibration")
        from flightkit.datasets.mcap_metadata import with_metadata

        return with_metadata(recording, path, METADATA_RECORD, result.to_metadata(), allow_overwrite=force)
    raise CalibrationError(
        f"cannot write a calibration to {path}: give a .json file or a .mcap recording", "calibration"
    )

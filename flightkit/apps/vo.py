"""Visual odometry jobs: run a method over any sequence, evaluate trajectories, write the results.

``flightkit vo run`` and ``flightkit vo eval`` call these; so can a notebook::

    job = run_vo_job("../shared/data/kitti06_stereo", "stereo", evaluate=True)
    print(job.timing.format(), job.report.ape.translation.rmse)
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from estimation.evaluation import EvaluationReport, evaluate
from estimation.evaluation_checks import alignment_warnings, first_pose_rotation_rmse_deg
from estimation.pipeline import VoOptions, VoResult, run_vo
from estimation.timing import TimingTable
from flightkit.apps.sequences import SIM_PREFIX, open_dataset
from flightkit.datasets.base import Sequence
from flightkit.datasets.trajectory import Trajectory, read_trajectory
from flightkit.errors import DatasetError

__all__ = [
    "EvaluationReport",
    "VoJob",
    "alignment_warnings",
    "evaluate_trajectories",
    "first_pose_rotation_rmse_deg",
    "load_trajectory",
    "run_vo_job",
]

logger = logging.getLogger(__name__)


def load_trajectory(source: Path | str, times: Path | None = None, calibration: Path | None = None) -> Trajectory:
    """A trajectory from a TUM/KITTI file, or the ground truth of a dataset folder, a recording
    or a ``sim:PATTERN`` spec (its camera trajectory). ``calibration`` (a ``flightkit calibrate``
    JSON file) replaces a recording's own stored calibration.

    Raises:
        DatasetError: unreadable file or folder, or a calibration for something not a recording.
        EstimationError: a malformed ``sim:`` spec. CalibrationError: an unreadable calibration file.
    """
    path = Path(source)
    if calibration is not None:
        if path.suffix.lower() != ".mcap":
            raise DatasetError(f"--calibration applies to a .mcap recording's ground truth, not {source}; "
                               "export the recording with it, or drop --calibration")
        from flightkit.calibration.result import CalibrationResult
        from flightkit.datasets.recording import open_mcap

        seq: Sequence = open_mcap(path, calibration=CalibrationResult.read_json(calibration))
    elif isinstance(source, str) and source.startswith(SIM_PREFIX):
        seq = open_dataset(source)
    elif path.is_dir() or path.suffix.lower() == ".mcap":
        seq = open_dataset(path)
    else:
        return read_trajectory(path, times_path=times).renamed(path.name)
    return seq.groundtruth().renamed(f"{seq.name} ground truth")


def evaluate_trajectories(
    est: Path | str,
    gt: Path | str,
    *,
    alignment: str = "se3",
    delta: float = 1.0,
    delta_unit: str = "frames",
    max_diff_s: float = 0.01,
    est_times: Path | None = None,
    gt_times: Path | None = None,
    plot_dir: Path | None = None,
    calibration: Path | None = None,
) -> tuple[EvaluationReport, list[Path]]:
    """APE, RPE and the lab errors of ``est`` against ``gt`` (see :func:`load_trajectory` for
    what each may be), with the plots written to ``plot_dir`` when given.

    Raises:
        DatasetError, EstimationError: unreadable input, nothing to associate.
    """
    report = evaluate(
        load_trajectory(est, est_times),
        load_trajectory(gt, gt_times, calibration),
        alignment=alignment,
        delta=delta,
        delta_unit=delta_unit,
        max_diff_s=max_diff_s,
    )
    plots: list[Path] = []
    if plot_dir is not None:
        from estimation.plots import plot_evaluation

        plots = plot_evaluation(report, plot_dir)
    return report, plots


@dataclass(slots=True)
class VoJob:
    """What :func:`run_vo_job` did.

    Attributes:
        result: the VO output, frame by frame.
        estimate_path: the TUM file written (camera poses).
        timing: per-stage processing time.
        elapsed_s: wall time of the whole run, image loading included.
        report: the evaluation against the sequence's ground truth (None when not asked for,
            or when the sequence has none).
        plots: evaluation plots written.
    """

    result: VoResult
    estimate_path: Path
    timing: TimingTable
    elapsed_s: float
    report: EvaluationReport | None = None
    plots: list[Path] = field(default_factory=list)

    @property
    def speed(self) -> dict[str, float]:
        """Frames per second overall (loading included), of the VO alone and per CPU second."""
        n = len(self.result)
        return {
            "frames": float(n),
            "elapsed_s": self.elapsed_s,
            "fps": n / self.elapsed_s if self.elapsed_s > 0 else math.inf,
            "fps_vo": self.result.fps,
            "fps_vo_cpu": self.result.fps_cpu,
        }

    def to_dict(self) -> dict[str, Any]:
        """A JSON-friendly summary (what ``vo run --json`` prints)."""
        out: dict[str, Any] = {
            "estimate": str(self.estimate_path),
            "frames": len(self.result),
            "frames_not_estimated": self.result.n_failed,
            "timing": self.timing.to_dict(),
            "speed": self.speed,
        }
        if self.report is not None:
            out["evaluation"] = self.report.to_dict()
        if self.plots:
            out["plots"] = [str(p) for p in self.plots]
        return out


def run_vo_job(
    dataset: Path | str,
    method: str,
    *,
    out: Path | None = None,
    size: tuple[int, int] | None = None,
    start: int = 0,
    stop: int | None = None,
    init_from_groundtruth: bool = False,
    readout_s: float | None = None,
    vehicle: str | None = None,
    evaluate_result: bool = False,
    alignment: str = "se3",
    plot_dir: Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> VoJob:
    """Run ``method`` over ``dataset`` (folder, recording or ``sim:`` spec), write the camera
    trajectory as TUM to ``out`` (default ``<sequence>_<method>.txt``), and evaluate it
    against the sequence's ground truth when ``evaluate_result`` or ``plot_dir`` asks for it.
    ``readout_s``: the camera's rolling-shutter readout (None: the sequence's); ``vehicle``: whose
    camera, in a fleet's recording. Blocks until
    done; ``progress(done, total)`` is called after every frame.

    Raises:
        DatasetError: unreadable input. EstimationError: the method cannot run on this sequence,
            or could not estimate the motion of most of its frames (nothing is written then).
    """
    seq = open_dataset(dataset, vehicle)
    t_start = time.perf_counter()
    result = run_vo(
        seq,
        method,
        size=size,
        init_from_groundtruth=init_from_groundtruth,
        start=start,
        stop=stop,
        progress=progress,
        T_body_camera=getattr(seq, "T_body_camera", None),
        options=None if readout_s is None else VoOptions(readout_s=readout_s),
    )
    elapsed_s = time.perf_counter() - t_start
    result.check()  # most frames not estimated: an error, not a file of predictions
    path = out or Path(f"{seq.name}_{method}.txt")
    result.write_tum(path)
    job = VoJob(result, path, TimingTable.from_stage_ms(result.stage_ms), elapsed_s)
    if evaluate_result or plot_dir is not None:
        if seq.has_groundtruth():
            job.report = evaluate(result.trajectory("camera"), seq.groundtruth(), alignment=alignment)
            if plot_dir is not None:
                from estimation.plots import plot_evaluation

                job.plots = plot_evaluation(job.report, plot_dir)
        else:
            logger.warning("%s has no ground truth; skipping the evaluation", seq.name)
    return job

"""Trajectory evaluation: ATE/APE, RPE and the lab's per-step relative/absolute errors.

Pure numpy/scipy; results agree with ``evo`` (``evo.core.metrics.APE``/``RPE``,
``evo.core.sync.associate_trajectories``, ``PoseTrajectory3D.align``) to better than 1e-6
on the same inputs (``tests/integration/test_eval_vs_evo.py``).

API::

    from estimation.evaluation import Alignment, ape, rpe, lab_errors, evaluate
    res = ape(est, gt, alignment=Alignment.SE3)          # est, gt: flightkit.datasets.Trajectory
    res.translation.rmse, res.rotation.mean              # ErrorStats: rmse mean median std min max
    r = rpe(est, gt, delta=1.0, delta_unit="frames")     # or delta_unit="m" (path distance, as evo)
    lab = lab_errors(est, gt)                            # relative (per step) and absolute (accumulated)
    report = evaluate(est, gt, alignment=..., delta=..., delta_unit=...)   # all of it; report.to_dict()

Definitions (poses are ``T_world_x`` 4x4; ``Q`` ground truth, ``P`` estimate):

* Association: nearest stamps within ``max_diff_s`` (default 0.01 s), as evo.
* Alignment: Umeyama (1991) least squares on positions, ``gt ~ s R est + t``; ``SE3`` fixes
  ``s = 1``, ``SIM3`` estimates it (monocular), ``NONE`` skips alignment. The estimate is
  transformed: ``P' = [sR | t] P`` (positions scaled, orientations rotated).
* APE (ATE): translation error ``|p'_i - q_i|``; rotation error ``angle(P'_i^-1 Q_i)``.
* RPE: pairs (i, j) ``delta`` frames apart (consecutive, non-overlapping: 0-d, d-2d, ...) or
  ``delta`` metres of path apart (evo's ``filter_pairs_by_path`` on the estimate's path);
  ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)``; translation ``|t(E)|``, rotation ``angle(R(E))``.
* Lab "relative" error per step i >= 1: the estimated step ``P_{i-1}^-1 P_i`` applied to the
  previous ground-truth pose, ``Q_{i-1} P_{i-1}^-1 P_i``, compared with ``Q_i``.
* Lab "absolute" error per frame i: the accumulated estimate started at the first ground
  truth pose, ``Q_0 P_0^-1 P_i``, compared with ``Q_i``.
* Rotation errors are angle magnitudes in radians; translation errors norms in metres.
"""

from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from flightkit.datasets.trajectory import Trajectory, associate_trajectories
from flightkit.errors import DatasetError, EstimationError

__all__ = [
    "APEResult",
    "Alignment",
    "AlignmentResult",
    "DeltaUnit",
    "ErrorStats",
    "EvaluationReport",
    "LabErrors",
    "RPEResult",
    "align",
    "ape",
    "evaluate",
    "lab_errors",
    "rpe",
    "rpe_pairs",
    "umeyama",
]

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]


class Alignment(enum.Enum):
    """How the estimate is aligned to the ground truth before comparing."""

    NONE = "none"
    SE3 = "se3"
    SIM3 = "sim3"

    @staticmethod
    def parse(value: Alignment | str) -> Alignment:
        if isinstance(value, Alignment):
            return value
        try:
            return Alignment(str(value).lower())
        except ValueError as exc:
            raise EstimationError(f"unknown alignment {value!r}; use one of none, se3, sim3") from exc


class DeltaUnit(enum.Enum):
    """Unit of the RPE pair distance."""

    FRAMES = "frames"
    METERS = "m"

    @staticmethod
    def parse(value: DeltaUnit | str) -> DeltaUnit:
        if isinstance(value, DeltaUnit):
            return value
        text = str(value).lower()
        if text in ("m", "meters", "metres"):
            return DeltaUnit.METERS
        if text in ("frames", "f", "frame"):
            return DeltaUnit.FRAMES
        raise EstimationError(f"unknown RPE delta unit {value!r}; use frames or m")


@dataclass(frozen=True, slots=True)
class ErrorStats:
    """Summary of an error series (same definitions as evo; std is the population std)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    count: int

    @staticmethod
    def of(errors: npt.ArrayLike) -> ErrorStats:
        e = np.asarray(errors, dtype=np.float64).reshape(-1)
        if e.size == 0:
            raise EstimationError("cannot summarise an empty error series; are there any pose pairs?")
        return ErrorStats(
            rmse=math.sqrt(float(np.mean(e * e))),
            mean=float(np.mean(e)),
            median=float(np.median(e)),
            std=float(np.std(e)),
            min=float(np.min(e)),
            max=float(np.max(e)),
            count=int(e.size),
        )

    def to_dict(self) -> dict[str, float | int]:
        return {
            "rmse": self.rmse,
            "mean": self.mean,
            "median": self.median,
            "std": self.std,
            "min": self.min,
            "max": self.max,
            "count": self.count,
        }


@dataclass(frozen=True, slots=True, eq=False)
class AlignmentResult:
    """``gt ~ scale * rotation @ est + translation``."""

    method: Alignment
    rotation: FloatArray = field(default_factory=lambda: np.eye(3))
    translation: FloatArray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "method": self.method.value,
            "rotation": self.rotation.tolist(),
            "translation_m": self.translation.tolist(),
            "scale": self.scale,
        }


def umeyama(
    src: npt.ArrayLike, dst: npt.ArrayLike, with_scale: bool = False
) -> tuple[FloatArray, FloatArray, float]:
    """Least-squares ``(R, t, s)`` with ``dst ~ s R src + t`` (Umeyama 1991), points (N, 3).

    The one implementation in flightkit: the trajectory alignment here and the VO's rigid fits
    (:mod:`estimation.rigid`, which re-exports it) use it. R is a proper rotation (det +1),
    s = 1.0 without ``with_scale``.

    Raises:
        EstimationError: fewer than 3 points, mismatched shapes or a degenerate (collinear) point set.
    """
    x = np.asarray(src, dtype=np.float64)
    y = np.asarray(dst, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3:
        raise EstimationError(
            f"umeyama needs two (N, 3) point sets of equal shape with N >= 3, got {x.shape} and {y.shape}; "
            "pass matched points, one row per pair"
        )
    n = x.shape[0]
    if n < 3:
        raise EstimationError(
            f"umeyama needs at least 3 point pairs (N >= 3), got {n}; align on more matched poses or use alignment none"
        )
    mean_x = x.mean(axis=0)
    mean_y = y.mean(axis=0)
    xc = x - mean_x
    yc = y - mean_y
    sigma_x = float(np.sum(xc * xc)) / n
    cov = (yc.T @ xc) / n
    u, d, vt = np.linalg.svd(cov)
    if np.count_nonzero(d > np.finfo(d.dtype).eps) < 2:
        raise EstimationError(
            "the estimated positions are degenerate (all on one point or line), so they cannot be "
            "aligned; use alignment none or a longer trajectory"
        )
    s_mat = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        s_mat[2, 2] = -1.0
    r = u @ s_mat @ vt
    scale = float(np.trace(np.diag(d) @ s_mat) / sigma_x) if with_scale else 1.0
    t = mean_y - scale * (r @ mean_x)
    return r, t, scale


def align(
    est: Trajectory, gt: Trajectory, alignment: Alignment | str = Alignment.SE3, n_poses: int | None = None
) -> tuple[Trajectory, AlignmentResult]:
    """Align an (already associated) estimate to the ground truth; returns the moved estimate.

    Args:
        n_poses: use only the first ``n_poses`` pairs to estimate the alignment (None: all).
    """
    method = Alignment.parse(alignment)
    if method is Alignment.NONE:
        return est, AlignmentResult(method)
    _check_same_length(est, gt)
    k = len(est) if n_poses is None else int(n_poses)
    r, t, s = umeyama(est.positions[:k], gt.positions[:k], with_scale=method is Alignment.SIM3)
    rot = Rotation.from_matrix(r)
    moved_pos = s * (est.positions @ r.T) + t
    moved_rot = rot * est.rotations
    q_xyzw = moved_rot.as_quat()
    moved = Trajectory(est.stamps_ns, moved_pos, np.column_stack([q_xyzw[:, 3], q_xyzw[:, :3]]), est.name)
    return moved, AlignmentResult(method, r, t, s)


def _check_same_length(est: Trajectory, gt: Trajectory) -> None:
    if len(est) != len(gt):
        raise EstimationError(
            f"estimate and ground truth must be associated first: {len(est)} vs {len(gt)} poses"
        )


def _rot_matrices(traj: Trajectory) -> FloatArray:
    return np.asarray(traj.rotations.as_matrix(), dtype=np.float64).reshape(-1, 3, 3)


def _angles(r: FloatArray) -> FloatArray:
    """Rotation angles (rad) of a stack of 3x3 rotation matrices."""
    if r.shape[0] == 0:
        return np.zeros(0)
    return np.asarray(Rotation.from_matrix(r).magnitude(), dtype=np.float64)


def _associate(est: Trajectory, gt: Trajectory, max_diff_s: float | None) -> tuple[Trajectory, Trajectory]:
    if max_diff_s is None:
        _check_same_length(est, gt)
        return est, gt
    try:
        gt_a, est_a = associate_trajectories(gt, est, max_diff_s)
    except DatasetError as exc:
        raise EstimationError(str(exc)) from exc
    return est_a, gt_a


@dataclass(frozen=True, slots=True, eq=False)
class APEResult:
    """Absolute pose error of an associated, aligned estimate.

    Attributes:
        stamps_ns: stamps of the matched estimate poses (N,).
        translation_errors_m, rotation_errors_rad: per pose (N,).
        translation, rotation: their statistics.
        alignment: the alignment applied.
        est_aligned, gt: the compared trajectories (for plots).
    """

    stamps_ns: npt.NDArray[np.int64]
    translation_errors_m: FloatArray
    rotation_errors_rad: FloatArray
    translation: ErrorStats
    rotation: ErrorStats
    alignment: AlignmentResult
    est_aligned: Trajectory
    gt: Trajectory

    @property
    def n_pairs(self) -> int:
        return int(self.stamps_ns.shape[0])


def ape(
    est: Trajectory,
    gt: Trajectory,
    alignment: Alignment | str = Alignment.SE3,
    max_diff_s: float | None = 0.01,
    align_n_poses: int | None = None,
) -> APEResult:
    """Absolute pose error (ATE) after association and alignment.

    Args:
        max_diff_s: association tolerance; None when est and gt are already paired 1:1.

    Raises:
        EstimationError: nothing associates, or the alignment is degenerate.
    """
    est_a, gt_a = _associate(est, gt, max_diff_s)
    moved, result = align(est_a, gt_a, alignment, align_n_poses)
    t_err = np.linalg.norm(moved.positions - gt_a.positions, axis=1)
    r_rel = np.einsum("nji,njk->nik", _rot_matrices(moved), _rot_matrices(gt_a))
    r_err = _angles(r_rel)
    return APEResult(
        stamps_ns=moved.stamps_ns,
        translation_errors_m=t_err,
        rotation_errors_rad=r_err,
        translation=ErrorStats.of(t_err),
        rotation=ErrorStats.of(r_err),
        alignment=result,
        est_aligned=moved,
        gt=gt_a,
    )


def rpe_pairs(
    positions: FloatArray,
    delta: float,
    delta_unit: DeltaUnit | str = DeltaUnit.FRAMES,
    rel_delta_tol: float = 0.1,
    all_pairs: bool = False,
) -> npt.NDArray[np.int64]:
    """Index pairs (M, 2) for RPE, chosen exactly as evo's ``id_pairs_from_delta``.

    Frames: consecutive ``(0, d), (d, 2d), ...`` or with ``all_pairs`` every ``(i, i + d)``.
    Metres: walking the path, a new index whenever the accumulated distance reaches ``delta``;
    with ``all_pairs``, for each i the j whose path distance is closest to ``delta`` within
    ``delta * rel_delta_tol``.
    """
    unit = DeltaUnit.parse(delta_unit)
    n = positions.shape[0]
    if delta <= 0:
        raise EstimationError(f"RPE delta must be positive, got {delta}")
    if unit is DeltaUnit.FRAMES:
        if float(delta) != int(delta):
            raise EstimationError(f"RPE delta in frames must be an integer, got {delta}")
        d = int(delta)
        if all_pairs:
            first = np.arange(max(n - d, 0))
            pairs = np.column_stack([first, first + d])
        else:
            every = np.arange(0, n, d)
            pairs = np.column_stack([every[:-1], every[1:]])
    else:
        steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
        if all_pairs:
            dist = np.concatenate([[0.0], np.cumsum(steps)])
            out = []
            tol = delta * rel_delta_tol
            for i in range(n - 1):
                from_here = dist[i + 1 :] - dist[i]
                j = int(np.argmin(np.abs(from_here - delta)))
                if abs(from_here[j] - delta) <= tol:
                    out.append((i, j + i + 1))
            pairs = np.array(out, dtype=np.int64).reshape(-1, 2)
        else:
            ids = [0]
            path = 0.0
            for i, step in enumerate(steps, start=1):
                path += float(step)
                if path >= delta:
                    ids.append(i)
                    path = 0.0
            pairs = np.column_stack([ids[:-1], ids[1:]]) if len(ids) > 1 else np.zeros((0, 2))
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if pairs.shape[0] == 0:
        raise EstimationError(
            f"RPE delta {delta} {unit.value} gives no pose pairs on {n} poses; use a smaller delta"
        )
    return pairs


@dataclass(frozen=True, slots=True, eq=False)
class RPEResult:
    """Relative pose error over index pairs.

    Attributes:
        pairs: (M, 2) indices into the associated trajectories.
        stamps_ns: stamp of the second pose of each pair (M,).
        translation_errors_m, rotation_errors_rad: per pair (M,).
    """

    pairs: npt.NDArray[np.int64]
    stamps_ns: npt.NDArray[np.int64]
    translation_errors_m: FloatArray
    rotation_errors_rad: FloatArray
    translation: ErrorStats
    rotation: ErrorStats
    delta: float
    delta_unit: DeltaUnit
    alignment: AlignmentResult

    @property
    def n_pairs(self) -> int:
        return int(self.pairs.shape[0])


def _relative_errors(
    q: FloatArray, p: FloatArray, pairs: npt.NDArray[np.int64]
) -> tuple[FloatArray, FloatArray]:
    """Translation and rotation parts of ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` for (M, 2) pairs."""
    i, j = pairs[:, 0], pairs[:, 1]
    q_rel = _inv_se3(q[i]) @ q[j]
    p_rel = _inv_se3(p[i]) @ p[j]
    e = _inv_se3(q_rel) @ p_rel
    return np.linalg.norm(e[:, :3, 3], axis=1), _angles(e[:, :3, :3])


def _inv_se3(m: FloatArray) -> FloatArray:
    out = np.zeros_like(m)
    rt = np.transpose(m[:, :3, :3], (0, 2, 1))
    out[:, :3, :3] = rt
    out[:, :3, 3] = -np.einsum("nij,nj->ni", rt, m[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def _se3_stack(traj: Trajectory) -> FloatArray:
    return traj.as_matrices()


def rpe(
    est: Trajectory,
    gt: Trajectory,
    delta: float = 1.0,
    delta_unit: DeltaUnit | str = DeltaUnit.FRAMES,
    alignment: Alignment | str = Alignment.NONE,
    max_diff_s: float | None = 0.01,
    rel_delta_tol: float = 0.1,
    all_pairs: bool = False,
    pairs_from_reference: bool = False,
) -> RPEResult:
    """Relative pose error (drift per ``delta`` frames or metres), as ``evo_rpe``.

    Alignment changes only the result of a Sim(3) (scale) alignment; SE(3) leaves RPE as is.
    Metre pairs follow the estimate's path unless ``pairs_from_reference`` (evo's default).
    """
    unit = DeltaUnit.parse(delta_unit)
    est_a, gt_a = _associate(est, gt, max_diff_s)
    moved, result = align(est_a, gt_a, alignment)
    source = gt_a if pairs_from_reference else moved
    pairs = rpe_pairs(source.positions, delta, unit, rel_delta_tol, all_pairs)
    t_err, r_err = _relative_errors(_se3_stack(gt_a), _se3_stack(moved), pairs)
    return RPEResult(
        pairs=pairs,
        stamps_ns=moved.stamps_ns[pairs[:, 1]],
        translation_errors_m=t_err,
        rotation_errors_rad=r_err,
        translation=ErrorStats.of(t_err),
        rotation=ErrorStats.of(r_err),
        delta=float(delta),
        delta_unit=unit,
        alignment=result,
    )


@dataclass(frozen=True, slots=True, eq=False)
class LabErrors:
    """The lab's per-step measures (see the module docstring).

    Attributes:
        stamps_ns: stamps of the matched poses (N,).
        relative_translation_m, relative_rotation_rad: per step (N - 1,), step i -> i+1.
        absolute_translation_m, absolute_rotation_rad: per pose (N,), accumulated from pose 0.
    """

    stamps_ns: npt.NDArray[np.int64]
    relative_translation_m: FloatArray
    relative_rotation_rad: FloatArray
    absolute_translation_m: FloatArray
    absolute_rotation_rad: FloatArray

    @property
    def relative_translation(self) -> ErrorStats:
        return ErrorStats.of(self.relative_translation_m)

    @property
    def relative_rotation(self) -> ErrorStats:
        return ErrorStats.of(self.relative_rotation_rad)

    @property
    def absolute_translation(self) -> ErrorStats:
        return ErrorStats.of(self.absolute_translation_m)

    @property
    def absolute_rotation(self) -> ErrorStats:
        return ErrorStats.of(self.absolute_rotation_rad)

    def to_dict(self) -> dict[str, dict[str, float]]:
        """Mean and standard deviation of the four series (the lab's table)."""
        out = {}
        for name in (
            "relative_translation",
            "relative_rotation",
            "absolute_translation",
            "absolute_rotation",
        ):
            s: ErrorStats = getattr(self, name)
            out[name] = {"mean": s.mean, "std": s.std}
        return out


def lab_errors(est: Trajectory, gt: Trajectory, max_diff_s: float | None = 0.01) -> LabErrors:
    """The lab's relative (per step) and absolute (accumulated) errors.

    Raises:
        EstimationError: fewer than 2 matched poses.
    """
    est_a, gt_a = _associate(est, gt, max_diff_s)
    if len(est_a) < 2:
        raise EstimationError(f"the lab errors need at least 2 matched poses, got {len(est_a)}")
    p = _se3_stack(est_a)
    q = _se3_stack(gt_a)
    steps = _inv_se3(p[:-1]) @ p[1:]  # P_{i-1}^-1 P_i
    predicted = q[:-1] @ steps  # Q_{i-1} P_{i-1}^-1 P_i
    rel_t = np.linalg.norm(predicted[:, :3, 3] - q[1:, :3, 3], axis=1)
    rel_r = _angles(np.einsum("nji,njk->nik", predicted[:, :3, :3], q[1:, :3, :3]))
    accumulated = (q[0] @ _inv_se3(p[:1])[0]) @ p  # Q_0 P_0^-1 P_i
    abs_t = np.linalg.norm(accumulated[:, :3, 3] - q[:, :3, 3], axis=1)
    abs_r = _angles(np.einsum("nji,njk->nik", accumulated[:, :3, :3], q[:, :3, :3]))
    return LabErrors(est_a.stamps_ns, rel_t, rel_r, abs_t, abs_r)


@dataclass(frozen=True, slots=True, eq=False)
class EvaluationReport:
    """Everything ``flightkit vo eval`` prints: APE, RPE and the lab errors."""

    ape: APEResult
    rpe: RPEResult
    lab: LabErrors
    est_name: str
    gt_name: str
    n_est: int
    n_gt: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "estimate": self.est_name,
            "groundtruth": self.gt_name,
            "poses": {"estimate": self.n_est, "groundtruth": self.n_gt, "matched": self.ape.n_pairs},
            "alignment": self.ape.alignment.to_dict(),
            "ape": {
                "translation_m": self.ape.translation.to_dict(),
                "rotation_rad": self.ape.rotation.to_dict(),
            },
            "rpe": {
                "delta": self.rpe.delta,
                "delta_unit": self.rpe.delta_unit.value,
                "pairs": self.rpe.n_pairs,
                "translation_m": self.rpe.translation.to_dict(),
                "rotation_rad": self.rpe.rotation.to_dict(),
            },
            "lab": self.lab.to_dict(),
        }


def evaluate(
    est: Trajectory,
    gt: Trajectory,
    alignment: Alignment | str = Alignment.SE3,
    delta: float = 1.0,
    delta_unit: DeltaUnit | str = DeltaUnit.FRAMES,
    max_diff_s: float = 0.01,
) -> EvaluationReport:
    """APE with ``alignment``, RPE (with the same alignment's scale) and the lab errors.

    The lab errors use the estimate as given (scaled by the Sim(3) scale when ``SIM3``), as
    they start from the ground truth and need no rigid alignment.
    """
    method = Alignment.parse(alignment)
    a = ape(est, gt, method, max_diff_s)
    r = rpe(est, gt, delta, delta_unit, method, max_diff_s)
    lab_est = est
    if method is Alignment.SIM3:
        s = a.alignment.scale
        lab_est = Trajectory(est.stamps_ns, est.positions * s, est.quats_wxyz, est.name)
    lab = lab_errors(lab_est, gt, max_diff_s)
    return EvaluationReport(a, r, lab, est.name, gt.name, len(est), len(gt))

"""PNG plots of an evaluation: trajectories (top x-y and side x-z views) and errors against time.

API::

    paths = plot_evaluation(report, out_dir)        # EvaluationReport -> list of written PNGs
    plot_trajectories(est, gt, path, title=...)     # two panels: x-y and x-z, metres
    plot_errors(report, path)                       # APE / RPE / lab errors against time

matplotlib runs on its non-interactive Agg canvas (no display needed, no global backend
switch); figures are closed after saving.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from estimation.evaluation import EvaluationReport
from flightkit.datasets.trajectory import Trajectory
from flightkit.errors import EstimationError

__all__ = ["plot_errors", "plot_evaluation", "plot_trajectories"]

logger = logging.getLogger(__name__)


def _figure(width_in: float, height_in: float):  # type: ignore[no-untyped-def]
    # A Figure with an Agg canvas, without pyplot (no global state, no GUI backend).
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: Path) -> Path:  # type: ignore[no-untyped-def]
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fig.savefig(path, format="png")
    except OSError as exc:
        raise EstimationError(f"cannot write plot {path}: {exc.strerror}; check the plot directory") from exc
    logger.info("wrote %s", path)
    return path


def plot_trajectories(est: Trajectory, gt: Trajectory, path: str | Path, title: str = "") -> Path:
    """Top (x-y) and side (x-z) views of the estimate against the ground truth, equal axes."""
    fig = _figure(11.0, 5.0)
    axes = fig.subplots(1, 2)
    for ax, (i, j, label) in zip(axes, ((0, 1, "top view (x-y)"), (0, 2, "side view (x-z)")), strict=True):
        ax.plot(
            gt.positions[:, i], gt.positions[:, j], "-", color="0.3", lw=1.5, label=gt.name or "ground truth"
        )
        ax.plot(
            est.positions[:, i],
            est.positions[:, j],
            "-",
            color="tab:blue",
            lw=1.0,
            label=est.name or "estimate",
        )
        if len(gt):
            ax.plot(gt.positions[0, i], gt.positions[0, j], "o", color="0.3", ms=5)
        if len(est):
            ax.plot(est.positions[0, i], est.positions[0, j], "o", color="tab:blue", ms=4)
        ax.set_xlabel("x (m)")
        ax.set_ylabel(f"{'xyz'[j]} (m)")
        ax.set_title(label)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, Path(path))


def plot_errors(report: EvaluationReport, path: str | Path) -> Path:
    """APE, RPE and the lab's relative/absolute errors against time (translation and rotation)."""
    fig = _figure(11.0, 8.0)
    axes = fig.subplots(3, 2, sharex=True)
    t0 = int(report.ape.stamps_ns[0]) if report.ape.n_pairs else 0

    def t_s(stamps: np.ndarray) -> np.ndarray:
        return (stamps.astype(np.int64) - t0) * 1e-9

    lab = report.lab
    rows = [
        (
            f"APE ({report.ape.alignment.method.value})",
            t_s(report.ape.stamps_ns),
            report.ape.translation_errors_m,
            report.ape.rotation_errors_rad,
        ),
        (
            f"RPE (delta {report.rpe.delta:g} {report.rpe.delta_unit.value})",
            t_s(report.rpe.stamps_ns),
            report.rpe.translation_errors_m,
            report.rpe.rotation_errors_rad,
        ),
    ]
    for r, (name, t, trans, rot) in enumerate(rows):
        axes[r, 0].plot(t, trans, lw=1.0, color="tab:blue")
        axes[r, 0].axhline(float(np.sqrt(np.mean(trans**2))), color="tab:red", lw=0.8, ls="--", label="rmse")
        axes[r, 0].set_ylabel(f"{name}\ntranslation (m)")
        axes[r, 1].plot(t, np.degrees(rot), lw=1.0, color="tab:green")
        axes[r, 1].set_ylabel("rotation (deg)")
        axes[r, 0].legend(loc="upper left", fontsize=8)
    t_lab = t_s(lab.stamps_ns)
    axes[2, 0].plot(t_lab[1:], lab.relative_translation_m, lw=1.0, label="relative (per step)")
    axes[2, 0].plot(t_lab, lab.absolute_translation_m, lw=1.0, label="absolute (accumulated)")
    axes[2, 0].set_ylabel("lab errors\ntranslation (m)")
    axes[2, 0].legend(loc="upper left", fontsize=8)
    axes[2, 1].plot(t_lab[1:], np.degrees(lab.relative_rotation_rad), lw=1.0, label="relative")
    axes[2, 1].plot(t_lab, np.degrees(lab.absolute_rotation_rad), lw=1.0, label="absolute")
    axes[2, 1].set_ylabel("rotation (deg)")
    axes[2, 1].legend(loc="upper left", fontsize=8)
    for ax in axes.flat:
        ax.grid(True, alpha=0.3)
    axes[2, 0].set_xlabel("time (s)")
    axes[2, 1].set_xlabel("time (s)")
    fig.suptitle(f"{report.est_name} vs {report.gt_name}")
    return _save(fig, Path(path))


def plot_evaluation(report: EvaluationReport, out_dir: str | Path, prefix: str = "") -> list[Path]:
    """Write ``<prefix>trajectory.png`` (aligned estimate vs ground truth) and ``<prefix>errors.png``."""
    out = Path(out_dir)
    title = f"{report.est_name} vs {report.gt_name} ({report.ape.alignment.method.value} aligned)"
    return [
        plot_trajectories(report.ape.est_aligned, report.ape.gt, out / f"{prefix}trajectory.png", title),
        plot_errors(report, out / f"{prefix}errors.png"),
    ]

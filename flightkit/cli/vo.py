"""``flightkit vo``: run visual odometry on a dataset, and evaluate trajectories against ground truth.

::

    flightkit vo eval EST GT [--align se3|sim3|none] [--delta N --delta-unit frames|m]
                             [--max-diff S] [--plot-dir DIR] [--json]
    flightkit vo run DATASET --method stereo [--out est.txt] [--eval] [--plot-dir DIR]
    flightkit vo run sim:circle --method rgbd-pnp --eval      # synthetic sequence, exact ground truth

``EST`` and ``GT`` are TUM (8 values per line) or KITTI (12 values per line) files; ``GT`` may
also be a dataset folder or recording with ground truth (its camera trajectory is used).
KITTI files carry no stamps: give ``--est-times``/``--gt-times`` (KITTI ``times.txt``) or
both are paired line by line.

``DATASET`` (and ``GT``) may also be a synthetic sequence: ``sim:circle``, ``sim:rectangle`` or
``sim:lawnmower`` -- the simulated camera (``flightkit.sim.sequence``) flown along the lab's
pattern with its exact ground truth -- with options as a query:
``sim:circle?rate_hz=30&size=640x480&duration_s=20&start_s=0&seed=1&noise=2&blur_s=0.01``.
See :func:`flightkit.apps.sequences.synthetic_sequence`.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from flightkit.apps.vo import EvaluationReport

__all__ = ["print_report", "register", "run_eval", "run_vo_command"]

logger = logging.getLogger(__name__)


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "vo",
        help="visual odometry: run it on a dataset, evaluate trajectories",
        description="Visual odometry on recorded sequences and its evaluation against ground truth.",
    )
    sub = parser.add_subparsers(dest="vo_command", metavar="VO_COMMAND")
    parser.set_defaults(func=lambda args: _usage(parser))

    ev = sub.add_parser(
        "eval",
        help="ATE/RPE and lab errors of an estimate against ground truth",
        description="Associate, align and compare an estimated trajectory with ground truth (evo-compatible).",
    )
    ev.add_argument("est", type=Path, help="estimated trajectory (TUM or KITTI file)")
    ev.add_argument("gt", help="ground truth (TUM/KITTI file, a dataset folder/recording, or sim:PATTERN)")
    ev.add_argument("--align", choices=("se3", "sim3", "none"), default="se3", help="alignment (default se3)")
    ev.add_argument("--delta", type=float, default=1.0, help="RPE pair distance (default 1)")
    ev.add_argument("--delta-unit", choices=("frames", "m"), default="frames", help="RPE delta unit")
    ev.add_argument("--max-diff", type=float, default=0.01, help="association tolerance, s (default 0.01)")
    ev.add_argument("--est-times", type=Path, help="times.txt for a KITTI estimate file")
    ev.add_argument("--gt-times", type=Path, help="times.txt for a KITTI ground-truth file")
    ev.add_argument("--plot-dir", type=Path, help="write trajectory.png and errors.png here")
    ev.add_argument("--calibration", type=Path, metavar="FILE.json",
                    help="a recording ground truth: apply this flightkit calibrate result instead of its own")
    ev.add_argument("--json", action="store_true", help="print the results as JSON instead of a table")
    ev.set_defaults(func=run_eval)

    rn = sub.add_parser(
        "run",
        help="run visual odometry on a dataset folder or recording",
        description="Run a VO method over a sequence, write its trajectory, optionally evaluate it.",
    )
    rn.add_argument(
        "dataset",
        help="dataset folder (EuRoC, KITTI, TUM, 7-Scenes), .mcap recording, video with a calibration file, "
        "or sim:circle|rectangle|lawnmower",
    )
    rn.add_argument("--method", default="stereo", help="rgbd-pnp, rgbd-essential, rgbd-kabsch, stereo, flow")
    rn.add_argument("-o", "--out", type=Path, help="write the estimate here (TUM); default <dataset name>_<method>.txt")
    rn.add_argument("--size", help="process at WIDTHxHEIGHT (e.g. 640x480)")
    rn.add_argument("--start", type=int, default=0, help="first frame")
    rn.add_argument("--stop", type=int, help="stop before this frame")
    rn.add_argument("--init-from-gt", action="store_true", help="start at the first ground-truth pose")
    rn.add_argument(
        "--readout-ms",
        type=_readout_ms,
        help="the camera's rolling-shutter readout, first row to last, ms (default: the dataset's, 20 for the "
        "TUM and 7-Scenes Kinects, 0 for a global shutter)",
    )
    rn.add_argument(
        "--vehicle", help="in a fleet's .mcap recording: the vehicle (bus namespace) whose camera to run on"
    )
    rn.add_argument("--eval", action="store_true", help="evaluate against the sequence's ground truth")
    rn.add_argument("--align", choices=("se3", "sim3", "none"), default="se3", help="alignment for --eval")
    rn.add_argument("--plot-dir", type=Path, help="write evaluation plots here (implies --eval)")
    rn.add_argument("--json", action="store_true", help="print results as JSON")
    rn.set_defaults(func=run_vo_command)


def _readout_ms(text: str) -> float:
    """``--readout-ms``: a readout time in ms, 0 or more."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"{text!r} is not a readout in ms (0 for a global shutter, or more)")
    return value


def _usage(parser: argparse.ArgumentParser) -> int:
    parser.print_help(sys.stderr)
    return 2


# ------------------------------------------------------------------------------- vo eval
def run_eval(args: argparse.Namespace) -> int:
    """``flightkit vo eval``: returns the exit code."""
    from flightkit.apps.vo import evaluate_trajectories

    report, plots = evaluate_trajectories(
        args.est,
        args.gt,
        alignment=args.align,
        delta=args.delta,
        delta_unit=args.delta_unit,
        max_diff_s=args.max_diff,
        est_times=args.est_times,
        gt_times=args.gt_times,
        plot_dir=args.plot_dir,
        calibration=args.calibration,
    )
    if args.json:
        from flightkit.apps.vo import alignment_warnings, first_pose_rotation_rmse_deg

        out = report.to_dict()
        out["plots"] = [str(p) for p in plots]
        out["rotation_first_pose_aligned_rmse_deg"] = first_pose_rotation_rmse_deg(report)
        out["warnings"] = alignment_warnings(report)
        print(json.dumps(out, indent=2))
    else:
        print_report(report, plots)
    return 0


def print_report(report: EvaluationReport, plots: list[Path]) -> None:
    """Print an evaluation as a table (rich), then the plot paths."""
    from rich.console import Console
    from rich.table import Table

    console = Console()
    console = Console(width=max(console.width, 110))
    d = report.to_dict()
    poses = d["poses"]
    al = report.ape.alignment
    console.print(
        f"[bold]{report.est_name}[/] vs [bold]{report.gt_name}[/]: {poses['matched']} matched poses "
        f"(estimate {poses['estimate']}, ground truth {poses['groundtruth']}), "
        f"alignment {al.method.value}" + (f", scale {al.scale:.4f}" if al.method.value == "sim3" else "")
    )
    table = Table(show_header=True, header_style="bold")
    table.add_column("metric", no_wrap=True)
    table.add_column("part", no_wrap=True)
    for col in ("rmse", "mean", "median", "std", "min", "max", "n"):
        table.add_column(col, justify="right")

    def row(name: str, unit: str, stats: Any, scale: float = 1.0) -> None:
        table.add_row(
            name,
            unit,
            *(f"{getattr(stats, k) * scale:.5f}" for k in ("rmse", "mean", "median", "std", "min", "max")),
            str(stats.count),
        )

    deg = 180.0 / math.pi
    row("APE", "trans m", report.ape.translation)
    row("", "rot deg", report.ape.rotation, deg)
    row(f"RPE {report.rpe.delta:g} {report.rpe.delta_unit.value}", "trans m", report.rpe.translation)
    row("", "rot deg", report.rpe.rotation, deg)
    lab = report.lab
    row("lab relative", "trans m", lab.relative_translation)
    row("", "rot deg", lab.relative_rotation, deg)
    row("lab absolute", "trans m", lab.absolute_translation)
    row("", "rot deg", lab.absolute_rotation, deg)
    console.print(table)
    from flightkit.apps.vo import alignment_warnings, first_pose_rotation_rmse_deg

    console.print(f"rotation error with the first pose aligned: {first_pose_rotation_rmse_deg(report):.3f} deg RMSE")
    for w in alignment_warnings(report):
        print(f"warning: {w}", file=sys.stderr)
    for p in plots:
        console.print(f"plot: {p}")


# ------------------------------------------------------------------------------- vo run
def run_vo_command(args: argparse.Namespace) -> int:
    """``flightkit vo run``: returns the exit code."""
    from rich.progress import Progress

    from flightkit.apps.sequences import parse_size
    from flightkit.apps.vo import run_vo_job

    with Progress(transient=True) as progress:
        task = progress.add_task(f"{args.method} on {args.dataset}", total=None)

        def on_progress(done: int, total: int) -> None:
            progress.update(task, completed=done, total=total)

        job = run_vo_job(
            args.dataset,
            args.method,
            out=args.out,
            size=parse_size(args.size) if args.size else None,
            start=args.start,
            stop=args.stop,
            init_from_groundtruth=args.init_from_gt,
            readout_s=None if args.readout_ms is None else args.readout_ms * 1e-3,
            vehicle=args.vehicle,
            evaluate_result=args.eval,
            alignment=args.align,
            plot_dir=args.plot_dir,
            progress=on_progress,
        )
    if args.json:
        print(json.dumps(job.to_dict(), indent=2))
        return 0
    print(f"wrote {job.estimate_path} ({len(job.result)} poses)")
    print(job.timing.format())
    if job.report is not None:
        print_report(job.report, job.plots)
    print(_speed_line(job.speed))
    return 0


def _speed_line(speed: dict[str, float]) -> str:
    """The final line of ``vo run``: frames/s overall (with loading/rendering) and of VO alone."""
    return (
        f"{int(speed['frames'])} frames in {speed['elapsed_s']:.2f} s: {speed['fps']:.1f} frames/s "
        f"including loading; VO alone {speed['fps_vo']:.1f} frames/s ({speed['fps_vo_cpu']:.1f} per CPU second)"
    )

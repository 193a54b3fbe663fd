"""``flightkit vo``: run visual odometry on a dataset, and evaluate trajectories against ground truth.

::

    flightkit vo eval EST GT [--align se3|sim3|none] [--delta N --delta-unit frames|m]
                             [--max-diff S] [--plot-dir DIR] [--json]
    flightkit vo run DATASET --method stereo [--out est.txt] [--eval] [--plot-dir DIR]

``EST`` and ``GT`` are TUM (8 values per line) or KITTI (12 values per line) files; ``GT`` may
also be a dataset folder or recording with ground truth (its camera trajectory is used).
KITTI files carry no stamps: give ``--est-times``/``--gt-times`` (KITTI ``times.txt``) or
both are paired line by line.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from flightkit.errors import EstimationError

if TYPE_CHECKING:
    from estimation.evaluation import EvaluationReport
    from flightkit.datasets.trajectory import Trajectory

__all__ = ["register", "run_eval", "run_vo_command"]

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
    ev.add_argument("gt", type=Path, help="ground truth (TUM/KITTI file, or a dataset folder/recording)")
    ev.add_argument("--align", choices=("se3", "sim3", "none"), default="se3", help="alignment (default se3)")
    ev.add_argument("--delta", type=float, default=1.0, help="RPE pair distance (default 1)")
    ev.add_argument("--delta-unit", choices=("frames", "m"), default="frames", help="RPE delta unit")
    ev.add_argument("--max-diff", type=float, default=0.01, help="association tolerance, s (default 0.01)")
    ev.add_argument("--est-times", type=Path, help="times.txt for a KITTI estimate file")
    ev.add_argument("--gt-times", type=Path, help="times.txt for a KITTI ground-truth file")
    ev.add_argument("--plot-dir", type=Path, help="write trajectory.png and errors.png here")
    ev.add_argument("--json", action="store_true", help="print the results as JSON instead of a table")
    ev.set_defaults(func=run_eval)

    # ---------------------------------------------------------------------------------------
    # `vo run` -- owned by the VO pipeline (estimation/pipeline.py). The arguments below map
    # onto estimation.pipeline.run_vo(sequence, method, *, size, init_from_groundtruth, start,
    # stop, progress); extend them here when run_vo grows options.
    # ---------------------------------------------------------------------------------------
    rn = sub.add_parser(
        "run",
        help="run visual odometry on a dataset folder or recording",
        description="Run a VO method over a sequence, write its trajectory, optionally evaluate it.",
    )
    rn.add_argument(
        "dataset", type=Path, help="dataset folder (EuRoC, KITTI, TUM, 7-Scenes) or .mcap recording"
    )
    rn.add_argument("--method", default="stereo", help="rgbd-pnp, rgbd-essential, rgbd-kabsch, stereo, flow")
    rn.add_argument(
        "--out", type=Path, help="write the estimate here (TUM); default <dataset name>_<method>.txt"
    )
    rn.add_argument("--size", help="process at WIDTHxHEIGHT (e.g. 640x480)")
    rn.add_argument("--start", type=int, default=0, help="first frame")
    rn.add_argument("--stop", type=int, help="stop before this frame")
    rn.add_argument("--init-from-gt", action="store_true", help="start at the first ground-truth pose")
    rn.add_argument("--eval", action="store_true", help="evaluate against the sequence's ground truth")
    rn.add_argument("--align", choices=("se3", "sim3", "none"), default="se3", help="alignment for --eval")
    rn.add_argument("--plot-dir", type=Path, help="write evaluation plots here (implies --eval)")
    rn.add_argument("--json", action="store_true", help="print results as JSON")
    rn.set_defaults(func=run_vo_command)


def _usage(parser: argparse.ArgumentParser) -> int:
    parser.print_help(sys.stderr)
    return 2


# ------------------------------------------------------------------------------- vo eval
def _load_trajectory(path: Path, times: Path | None, role: str) -> Trajectory:
    from flightkit.datasets.registry import open_sequence
    from flightkit.datasets.trajectory import read_trajectory

    if path.is_dir() or path.suffix.lower() == ".mcap":
        seq = open_sequence(path)
        return seq.groundtruth().renamed(f"{seq.name} ground truth")
    traj = read_trajectory(path, times_path=times)
    return traj.renamed(path.name)


def run_eval(args: argparse.Namespace) -> int:
    """``flightkit vo eval``: returns the exit code."""
    from estimation.evaluation import evaluate

    est = _load_trajectory(args.est, args.est_times, "estimate")
    gt = _load_trajectory(args.gt, args.gt_times, "ground truth")
    report = evaluate(
        est, gt, alignment=args.align, delta=args.delta, delta_unit=args.delta_unit, max_diff_s=args.max_diff
    )
    plots = []
    if args.plot_dir:
        from estimation.plots import plot_evaluation

        plots = plot_evaluation(report, args.plot_dir)
    if args.json:
        out = report.to_dict()
        out["plots"] = [str(p) for p in plots]
        print(json.dumps(out, indent=2))
    else:
        _print_report(report, plots)
    return 0


def _print_report(report: EvaluationReport, plots: list[Path]) -> None:
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

    import math

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
    for p in plots:
        console.print(f"plot: {p}")


# ------------------------------------------------------------------------------- vo run
def _parse_size(text: str | None) -> tuple[int, int] | None:
    if not text:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise EstimationError(f"--size {text!r} is not WIDTHxHEIGHT; write e.g. 640x480") from exc
    return w, h


def run_vo_command(args: argparse.Namespace) -> int:
    """``flightkit vo run``: calls ``estimation.pipeline.run_vo`` (the VO engineer's pipeline)."""
    try:
        from estimation import pipeline
    except ImportError as exc:
        raise EstimationError(f"the VO pipeline (estimation.pipeline) is not available: {exc}") from exc
    if not hasattr(pipeline, "run_vo"):
        raise EstimationError(
            "estimation.pipeline has no run_vo(); the VO pipeline is not installed in this build"
        )
    from rich.progress import Progress

    from flightkit.datasets.registry import open_sequence

    seq = open_sequence(args.dataset)
    with Progress(transient=True) as progress:
        task = progress.add_task(f"{args.method} on {seq.name}", total=len(seq))

        def on_progress(done: int, total: int) -> None:
            progress.update(task, completed=done, total=total)

        result = pipeline.run_vo(
            seq,
            args.method,
            size=_parse_size(args.size),
            init_from_groundtruth=args.init_from_gt,
            start=args.start,
            stop=args.stop,
            progress=on_progress,
        )
    out = args.out or Path(f"{seq.name}_{args.method}.txt")
    result.write_tum(out)
    from estimation.timing import TimingTable

    timing = TimingTable.from_stage_ms(result.stage_ms)
    summary: dict[str, Any] = {"estimate": str(out), "frames": len(result), "timing": timing.to_dict()}
    report = None
    if (args.eval or args.plot_dir) and seq.has_groundtruth():
        from estimation.evaluation import evaluate

        report = evaluate(result.trajectory("camera"), seq.groundtruth(), alignment=args.align)
        summary["evaluation"] = report.to_dict()
        if args.plot_dir:
            from estimation.plots import plot_evaluation

            summary["plots"] = [str(p) for p in plot_evaluation(report, args.plot_dir)]
    elif args.eval:
        logger.warning("%s has no ground truth; skipping the evaluation", seq.name)
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"wrote {out} ({len(result)} poses)")
    print(timing.format())
    if report is not None:
        _print_report(report, [Path(p) for p in summary.get("plots", [])])
    return 0

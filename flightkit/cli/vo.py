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
See :func:`synthetic_sequence`.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from flightkit.errors import EstimationError

if TYPE_CHECKING:
    from estimation.evaluation import EvaluationReport
    from flightkit.datasets.trajectory import Trajectory

__all__ = [
    "SYNTHETIC_PATTERNS",
    "lab_pattern",
    "open_dataset",
    "parse_sim_spec",
    "register",
    "run_eval",
    "run_vo_command",
    "synthetic_sequence",
]

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
    rn.add_argument("--eval", action="store_true", help="evaluate against the sequence's ground truth")
    rn.add_argument("--align", choices=("se3", "sim3", "none"), default="se3", help="alignment for --eval")
    rn.add_argument("--plot-dir", type=Path, help="write evaluation plots here (implies --eval)")
    rn.add_argument("--json", action="store_true", help="print results as JSON")
    rn.set_defaults(func=run_vo_command)


# ------------------------------------------------------------------ synthetic sequences
SIM_PREFIX = "sim:"


@dataclass(frozen=True, slots=True)
class SyntheticWindow:
    """The part of a lab pattern a synthetic sequence covers by default.

    Attributes:
        start_s: pattern time of the first frame.
        duration_s: seconds of motion rendered.
        what: what happens in the window (for tables and docs).
    """

    start_s: float
    duration_s: float
    what: str


SYNTHETIC_PATTERNS: dict[str, SyntheticWindow] = {
    "circle": SyntheticWindow(0.0, 12.0, "start of a lap of the 1 m circle at 1.5 m, 40 s/lap, looking inward"),
    "rectangle": SyntheticWindow(14.0, 14.0, "end of the first 2 m side, the 90 deg corner turn, start of the next"),
    "lawnmower": SyntheticWindow(15.0, 14.0, "end of the first 2 m lane, turn, 0.5 m shift to the next lane"),
}
"""The three lab patterns (as in ``examples/*.toml``), each with a short window of motion that
contains what makes it hard for VO: the speed-up from rest, and the turns in place."""


def lab_pattern(name: str) -> Any:
    """The lab's pattern ``name`` (one lap, as flown by ``examples/<name>.toml``): a 1 m circle at
    1.5 m, 40 s per lap, looking inward; a 2 m x 1 m rectangle at 0.1 m/s looking inward with
    5 s turns; a lawnmower over 2 m x 1 m with 0.5 m lanes at 0.1 m/s facing the travel.

    Raises:
        EstimationError: unknown name.
    """
    from trajectories.patterns import Circle, Lawnmower, Rectangle, rectangle_corners

    if name == "circle":
        return Circle(centre_m=(0.0, 0.0), radius_m=1.0, height_m=1.5, period_s=40.0)
    if name == "rectangle":
        return Rectangle(rectangle_corners((0.0, 0.0), (2.0, 1.0)), 1.5, speed_m_s=0.1, accel_m_s2=0.2, turn_s=5.0)
    if name == "lawnmower":
        return Lawnmower((-1.0, -0.5), (2.0, 1.0), 0.5, 1.5, speed_m_s=0.1, accel_m_s2=0.2, turn_s=5.0)
    raise EstimationError(
        f"unknown synthetic pattern {name!r}; use one of {', '.join(SIM_PREFIX + n for n in SYNTHETIC_PATTERNS)}"
    )


def synthetic_sequence(
    pattern: str,
    *,
    size: tuple[int, int] = (320, 240),
    rate_hz: float = 15.0,
    start_s: float | None = None,
    duration_s: float | None = None,
    seed: int = 0,
    noise_std: float = 0.0,
    blur_s: float = 0.0,
    stereo: bool = True,
    color: bool = True,
    cache: bool = False,
) -> Any:
    """A :class:`flightkit.sim.sequence.SimSequence` of the simulated lab camera (the default
    mount, 90 degrees HFOV, 5 cm stereo baseline) flown along the lab pattern ``pattern``.

    Args:
        pattern: ``circle``, ``rectangle`` or ``lawnmower``.
        size: rendered image size (width, height).
        rate_hz: frame rate.
        start_s, duration_s: the pattern-time window (default: :data:`SYNTHETIC_PATTERNS`).
        seed: scene layout (box placement and textures) and noise seed.
        noise_std: image noise, grey levels (0 = none).
        blur_s: motion-blur exposure, seconds (0 = none).
        stereo, color, cache: see :class:`~flightkit.sim.sequence.SimSequence`.

    Returns immediately; frames render when iterated (~25 ms per view at 320x240).

    Raises:
        EstimationError: unknown pattern.
    """
    from flightkit.config import CameraConfig
    from flightkit.sim.camera import Scene
    from flightkit.sim.sequence import ImagingOptions, SimSequence, body_poses_along

    path = lab_pattern(pattern)
    window = SYNTHETIC_PATTERNS[pattern]
    start = window.start_s if start_s is None else start_s
    duration = window.duration_s if duration_s is None else duration_s
    duration = min(duration, float(path.duration_s) - start)
    poses = body_poses_along(path, rate_hz, start_s=start, duration_s=duration)
    camera_cfg = CameraConfig(width_px=size[0], height_px=size[1], rate_hz=rate_hz)
    imaging = ImagingOptions(noise_std=noise_std, exposure_s=blur_s, seed=seed)
    return SimSequence.from_config(
        camera_cfg,
        poses,
        scene=Scene.default_lab(seed),
        name=f"sim_{pattern}",
        stereo=stereo,
        color=color,
        imaging=imaging,
        cache=cache,
    )


def parse_sim_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """``"sim:circle?rate_hz=30&size=640x480"`` -> ``("circle", {"rate_hz": 30.0, "size": (640, 480)})``.

    Raises:
        EstimationError: not a ``sim:`` spec, or an unknown or malformed option.
    """
    from urllib.parse import parse_qsl

    if not spec.startswith(SIM_PREFIX):
        raise EstimationError(f"{spec!r} is not a synthetic sequence; write e.g. sim:circle")
    name, _, query = spec[len(SIM_PREFIX) :].partition("?")
    floats = {"rate_hz": "rate_hz", "start_s": "start_s", "duration_s": "duration_s", "noise": "noise_std"}
    floats["blur_s"] = "blur_s"
    kwargs: dict[str, Any] = {}
    for key, value in parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query)):
        try:
            if key in floats:
                kwargs[floats[key]] = float(value)
            elif key == "seed":
                kwargs["seed"] = int(value)
            elif key == "size":
                size = _parse_size(value)
                assert size is not None
                kwargs["size"] = size
            elif key == "stereo":
                kwargs["stereo"] = value.lower() not in ("0", "false", "no")
            else:
                raise EstimationError(
                    f"unknown option {key!r} in {spec!r}; use rate_hz, size, start_s, duration_s, seed, noise, "
                    "blur_s or stereo"
                )
        except ValueError as exc:
            raise EstimationError(f"option {key}={value!r} in {spec!r} is not a number") from exc
    return name, kwargs


def open_dataset(source: str | Path) -> Any:
    """Open a dataset folder, recording or ``sim:PATTERN[?options]`` as a ``Sequence``.

    Raises:
        DatasetError: the path is missing or not recognised.
        EstimationError: a malformed ``sim:`` spec.
    """
    from flightkit.datasets.registry import open_sequence

    if isinstance(source, str) and source.startswith(SIM_PREFIX):
        name, kwargs = parse_sim_spec(source)
        return synthetic_sequence(name, **kwargs)
    return open_sequence(Path(source))


def _usage(parser: argparse.ArgumentParser) -> int:
    parser.print_help(sys.stderr)
    return 2


# ------------------------------------------------------------------------------- vo eval
def _load_trajectory(path: Path | str, times: Path | None, role: str) -> Trajectory:
    from flightkit.datasets.trajectory import read_trajectory

    if isinstance(path, str) and path.startswith(SIM_PREFIX):
        seq = open_dataset(path)
        return seq.groundtruth().renamed(f"{seq.name} ground truth")
    path = Path(path)
    if path.is_dir() or path.suffix.lower() == ".mcap":
        seq = open_dataset(path)
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
        raise EstimationError("estimation.pipeline has no run_vo(); the VO pipeline is not installed in this build")
    from rich.progress import Progress

    seq = open_dataset(args.dataset)
    t_start = time.perf_counter()
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
            **({"T_body_camera": seq.T_body_camera} if hasattr(seq, "T_body_camera") else {}),
        )
    elapsed_s = time.perf_counter() - t_start
    out = args.out or Path(f"{seq.name}_{args.method}.txt")
    result.write_tum(out)
    from estimation.timing import TimingTable

    timing = TimingTable.from_stage_ms(result.stage_ms)
    summary: dict[str, Any] = {"estimate": str(out), "frames": len(result), "timing": timing.to_dict()}
    summary["speed"] = _speed(len(result), elapsed_s, result.fps, result.fps_cpu)
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
    print(_speed_line(summary["speed"]))
    return 0


def _speed(frames: int, elapsed_s: float, fps_vo: float, fps_cpu: float) -> dict[str, float]:
    return {
        "frames": float(frames),
        "elapsed_s": elapsed_s,
        "fps": frames / elapsed_s if elapsed_s > 0 else math.inf,
        "fps_vo": fps_vo,
        "fps_vo_cpu": fps_cpu,
    }


def _speed_line(speed: dict[str, float]) -> str:
    """The final line of ``vo run``: frames/s overall (with loading/rendering) and of VO alone."""
    return (
        f"{int(speed['frames'])} frames in {speed['elapsed_s']:.2f} s: {speed['fps']:.1f} frames/s "
        f"including loading; VO alone {speed['fps_vo']:.1f} frames/s ({speed['fps_vo_cpu']:.1f} per CPU second)"
    )

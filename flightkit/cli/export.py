"""``flightkit export RUN.mcap --format tum|euroc -o DIR``: a recording as a dataset folder."""

from __future__ import annotations

import argparse
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser(
        "export",
        help="export a recording to a TUM RGB-D or EuRoC folder",
        description="Write images, depth, associations, ground truth (mocap body through the extrinsics to the "
        "camera, in the world frame by default) and calibration files. The folder opens with "
        "flightkit.datasets.open_sequence.",
    )
    p.add_argument("recording", help="an .mcap recording")
    p.add_argument("--format", required=True, choices=("tum", "euroc"), help="folder layout")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--camera", help="main camera name (default: color for TUM, left for EuRoC)")
    p.add_argument("--body", help="mocap rigid body for ground truth (default: the first one)")
    p.add_argument("--max-diff", type=float, default=0.02, metavar="S", help="association limit (TUM: 0.02 s)")
    p.add_argument(
        "--config", metavar="LAB.toml",
        help="take T_body_camera and T_world_mocap from this config instead of the recording",
    )
    p.add_argument(
        "--frame", choices=("world", "mocap"), default="world",
        help="frame of the ground truth: world (the recording's T_world_mocap applied; default) or mocap "
        "(the mocap system's own frame, as TUM and EuRoC publish)",
    )
    p.add_argument(
        "--vehicle", help="export this vehicle (bus namespace) only; default: every vehicle with a camera, "
        "one folder each (OUTPUT/<vehicle>) when the recording holds several",
    )
    p.add_argument(
        "--calibration", metavar="FILE.json",
        help="a flightkit calibrate result to apply (time offset, T_body_camera) instead of the recording's own",
    )
    p.add_argument("--force", action="store_true", help="replace a non-empty output folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from flightkit.apps.capture import export_recording, export_vehicles
    from flightkit.calibration.result import CalibrationResult
    from flightkit.config import load_config

    T_body_camera = T_world_mocap = None  # noqa: N806
    if args.config:
        lab = load_config(args.config)
        T_body_camera = lab.camera.T_body_camera.to_transform()  # noqa: N806
        T_world_mocap = lab.mocap.T_world_mocap.to_transform()  # noqa: N806
    console = Console(stderr=True)
    with Progress(
        TextColumn("exporting"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(), console=console,
        transient=True,
    ) as bar:
        task = bar.add_task("export", total=None)

        def progress(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total or None)

        options: dict[str, Any] = {
            "camera": args.camera, "mocap_body": args.body, "max_diff_s": args.max_diff,
            "T_body_camera": T_body_camera, "T_world_mocap": T_world_mocap, "frame": args.frame,
            "allow_overwrite": args.force, "progress": progress,
            "calibration": CalibrationResult.read_json(args.calibration) if args.calibration else None,
        }
        if args.vehicle:
            reports = {args.vehicle: export_recording(args.recording, args.output, args.format, vehicle=args.vehicle,
                                                      **options)}
        else:
            force = options.pop("allow_overwrite")
            reports = export_vehicles(args.recording, args.output, args.format, allow_overwrite=force, **options)
    for vehicle, report in reports.items():
        print((f"{vehicle}: " if len(reports) > 1 else "") + report.summary())
        for note in report.notes:
            print(f"note: {note}")
    return 0

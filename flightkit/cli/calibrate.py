"""``flightkit calibrate``: camera-to-mocap time offset and hand-eye extrinsics from a recording.

::

    flightkit calibrate time REC.mcap [--method rgbd-pnp | --camera-trajectory VO.txt] [--json] [--write OUT]
    flightkit calibrate handeye REC.mcap [...same options...]
    flightkit capture calibrate time|handeye REC.mcap [...same options...]   (the same command)

``--write`` takes a ``.json`` file (a calibration file) or a ``.mcap`` path (a copy of the
recording with the result in its metadata; the recording's own path rewrites it in place).
Exit codes: 0 ok, 1 the data cannot support the estimate (e.g. too little rotation), 2 usage.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from flightkit.calibration import CalibrationResult

__all__ = ["add_options", "format_result", "register", "run"]


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "calibrate",
        help="camera-to-mocap time offset and hand-eye T_body_camera from a recording",
        description="Estimate the camera's time offset and drift against the mocap, or its mount on the body, "
        "from a recording of a calibration flight (docs/calibration.md).",
    )
    sub = parser.add_subparsers(dest="calibrate_command", metavar="WHAT")
    parser.set_defaults(func=lambda args: _usage(parser))
    for what, help_ in (
        ("time", "camera-to-mocap time offset (ms, with its uncertainty) and drift (ppm)"),
        ("handeye", "T_body_camera from the body's and the camera's motion, with residuals"),
    ):
        p = sub.add_parser(what, help=help_, description=help_)
        add_options(p)
        p.set_defaults(func=run, what=what)


def add_options(p: argparse.ArgumentParser) -> None:
    """The recording and options of one calibration (``calibrate time|handeye`` and ``capture calibrate``)."""
    p.add_argument("recording", type=Path, help="the .mcap recording of a calibration flight")
    p.add_argument("--camera-trajectory", type=Path, metavar="FILE",
                   help="the camera's poses (TUM) at its own stamps, instead of running VO")
    p.add_argument("--board", metavar="SPEC",
                   help="a board fixed in the room, [charuco|apriltag:]NXxNY:SQUARE_M:MARKER_M[:DICT] "
                   "(e.g. 5x7:0.04:0.03, apriltag:6x6:0.05:0.04): the camera's motion comes from it instead of VO")
    p.add_argument("--method", default="rgbd-pnp", help="VO method for the camera's motion (default rgbd-pnp)")
    p.add_argument("--camera", help="camera name in the recording (default: its main camera)")
    p.add_argument("--body", help="mocap body (default: the config's or the recording's)")
    p.add_argument("--size", help="run VO at WIDTHxHEIGHT")
    p.add_argument("--config", metavar="LAB.toml", help="T_world_mocap and the configured T_body_camera")
    p.add_argument("--max-offset", type=float, default=0.5, metavar="S", help="largest offset searched (0.5 s)")
    p.add_argument("--window", type=float, default=10.0, metavar="S", help="window for the drift fit (10 s)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--write", type=Path, action="append", default=[], metavar="OUT",
                   help="store the result: OUT.json, or OUT.mcap (a copy of the recording with it in the metadata; "
                   "the recording's own path rewrites it); may be repeated")
    p.add_argument("--force", action="store_true", help="overwrite an existing OUT")


def _usage(parser: argparse.ArgumentParser) -> int:
    parser.print_help(sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    """``flightkit calibrate time|handeye``: returns the exit code."""
    from flightkit.apps.calibrate import calibrate_recording, write_calibration
    from flightkit.apps.sequences import parse_size
    from flightkit.config import load_config

    lab = load_config(args.config) if args.config else None
    result = calibrate_recording(
        args.recording,
        args.what,
        max_offset_s=args.max_offset,
        window_s=args.window,
        body=args.body,
        camera=args.camera,
        camera_trajectory=args.camera_trajectory,
        method=args.method,
        size=parse_size(args.size) if args.size else None,
        lab_cfg=lab,
        board=args.board,
    )
    written = [write_calibration(result, out, recording=args.recording, force=args.force) for out in args.write]
    if args.json:
        doc = result.to_dict()
        doc["written"] = [str(p) for p in written]
        print(json.dumps(doc, indent=2))
    else:
        print(format_result(result))
        for p in written:
            print(f"wrote {p}")
    return 0


def format_result(res: CalibrationResult) -> str:
    """The result as a two-column table."""
    rows: list[tuple[str, str]] = []
    if res.time_offset_ms is not None:
        sigma = res.time_offset_uncertainty_ms or 0.0
        rows.append(("time offset (camera - mocap)", f"{res.time_offset_ms:+.2f} +- {sigma:.2f} ms"))
        drift = f"{res.drift_ppm or 0:+.1f} +- {res.drift_uncertainty_ppm or 0:.1f} ppm" if res.drift_estimated else (
            "not estimated (record at least 30 s)")
        rows.append(("camera clock drift", drift))
        rows.append(("rate correlation", f"{res.correlation or 0:.4f}"))
    if res.T_body_camera is not None:
        T = res.T_body_camera  # noqa: N806
        rows.append(("T_body_camera translation", "[" + ", ".join(f"{v:+.4f}" for v in T.translation) + "] m"))
        rows.append(("T_body_camera quat_wxyz", "[" + ", ".join(f"{v:+.5f}" for v in T.quat_wxyz) + "]"))
        rows.append(("hand-eye residual", f"{(res.residual_m or 0) * 1e3:.2f} mm, {res.residual_deg or 0:.3f} deg "
                                          f"({res.pairs} pairs)"))
        diff = res.difference_to_configured
        rows.append(("vs configured T_body_camera",
                     f"{diff[0] * 1e3:.1f} mm, {diff[1]:.2f} deg" if diff is not None else "no configured mount"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)

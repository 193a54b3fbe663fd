"""Capture jobs: record the bus, inspect, recover and export recordings, publish a source or a mocap system.

``flightkit record``, ``flightkit capture info|recover|publish`` and ``flightkit export`` call these.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import zenoh

from capture.bus_recorder import BusRecorder, start_recording
from capture.config import CaptureConfig
from capture.export import ExportReport, export_recording, export_vehicles
from capture.info import RecordingInfo, StreamStats, recording_info
from capture.sources._runner import SourceThread
from flightkit.bus.keys import Keys
from flightkit.clock import Clock, SimClock, WallClock
from flightkit.config import BusConfig, LabConfig
from flightkit.datasets.mcap_recovery import RecoveryReport, recover
from flightkit.errors import CaptureError, ConfigError

__all__ = [
    "BusRecorder",
    "ExportReport",
    "PublishOptions",
    "RecordingInfo",
    "RecoveryReport",
    "StreamStats",
    "bridge_mocap",
    "export_recording",
    "export_vehicles",
    "open_publisher",
    "parse_source",
    "recording_info",
    "recover",
    "start_recording",
]

logger = logging.getLogger(__name__)

SOURCE_KINDS = "camera:0, camera:/dev/video2, video:FILE, realsense, replay:RUN.mcap, replay:DIR or mocap"


def parse_source(text: str) -> tuple[str, str]:
    """``"camera:0"`` -> ``("camera", "0")``; ``realsense`` and ``mocap`` take no argument.

    Raises:
        ConfigError: not a source flightkit can publish.
    """
    kind, _, arg = text.partition(":")
    if kind in ("realsense", "mocap") and not arg:
        return kind, ""
    if kind in ("camera", "video", "replay") and arg:
        return kind, arg
    raise ConfigError("<command line>", "SOURCE", f"{text!r} is not a source", f"use {SOURCE_KINDS}", text)


@dataclass(frozen=True, slots=True)
class PublishOptions:
    """How a camera, video or replay source publishes (the ``capture publish`` options).

    Attributes:
        speed: replay and video files: times the recorded rate (``inf``: as fast as the bus takes it).
        calibration: camera calibration file (JSON/YAML), None for the config's ``[camera]``.
        color_format: ``bgr8``, ``rgb8`` or ``jpeg`` (CompressedImage only).
        jpeg_quality: JPEG quality (None: ``[capture] jpeg_quality``, or 90 with ``jpeg``).
        rate_hz: camera: frame rate to ask for; video: playback rate.
        loop: video files: start again at the end.
        name: camera name in the keys (``<ns>/camera/<name>/image``).
        key_prefix: replay of a recording: publish under ``<prefix>/<topic>``.
        gt_body: replay of a dataset folder: ground truth on ``<ns>/mocap/<gt_body>/pose``.
    """

    speed: float = 1.0
    calibration: str | None = None
    color_format: str = "bgr8"
    jpeg_quality: int | None = None
    rate_hz: float | None = None
    loop: bool = False
    name: str = "color"
    key_prefix: str = ""
    gt_body: str = "groundtruth"


def open_publisher(kind: str, arg: str, lab: LabConfig, session: zenoh.Session, opts: PublishOptions) -> SourceThread:
    """The publisher of a camera, video, RealSense or replay source (not started; ``start()`` it).

    Raises:
        CaptureError: a bad speed, a missing file, a device that cannot be opened.
    """
    keys = Keys(lab.vehicle.namespace)
    cap_cfg = lab.section("capture", CaptureConfig)
    if not opts.speed > 0:
        raise CaptureError(f"speed {opts.speed} must be positive (1 = as recorded)")
    if kind in ("camera", "video"):
        from capture.sources.opencv import OpenCVCameraPublisher
        from flightkit.bus.streams import CameraModel

        quality = opts.jpeg_quality if opts.jpeg_quality is not None else (
            cap_cfg.jpeg_quality or (90 if opts.color_format == "jpeg" else 0))
        model = None
        if opts.calibration is None and kind == "camera":
            cam = lab.camera  # no calibration file: the [camera] section of the config
            fx, fy, cx, cy = cam.intrinsics()
            model = CameraModel(cam.width_px, cam.height_px, fx, fy, cx, cy)
            logger.warning("camera %s: no calibration given; publishing the [camera] intrinsics of the config", arg)
        if kind == "video" and not Path(arg).is_file():
            raise CaptureError(f"video {arg} does not exist; check the path")
        speed = opts.speed if math.isfinite(opts.speed) else 1000.0
        clock: Clock = SimClock(speed=speed) if kind == "video" and speed != 1.0 else WallClock()
        return OpenCVCameraPublisher(
            session, keys, arg, clock, model=model, calibration=opts.calibration, name=opts.name,
            color_format=opts.color_format, jpeg_quality=quality, rate_hz=opts.rate_hz, loop=opts.loop,
        )
    if kind == "realsense":
        from capture.sources.realsense import RealSensePublisher

        cam = lab.camera
        return RealSensePublisher(
            session, keys, WallClock(), width_px=cam.width_px, height_px=cam.height_px,
            rate_hz=int(opts.rate_hz or cam.rate_hz), depth=cap_cfg.depth, jpeg_quality=cap_cfg.jpeg_quality,
        )
    if kind == "replay":
        from capture.sources.replay import open_replay

        if not Path(arg).exists():
            raise CaptureError(f"{arg} does not exist; give an .mcap recording or a dataset folder")
        return open_replay(
            session, keys, arg, WallClock(), speed=opts.speed, key_prefix=opts.key_prefix, gt_body=opts.gt_body
        )
    raise CaptureError(f"source kind {kind!r} is not a camera, video, realsense or replay source")


async def bridge_mocap(
    lab: LabConfig, bus_cfg: BusConfig, duration_s: float | None = None, on_start: Callable[[str], None] | None = None
) -> int:
    """Publish the lab's mocap system (``[mocap]``, via motioncapture) on the bus until ``duration_s``
    passes or the task is cancelled; returns the number of poses published.

    Raises:
        CaptureError: the config names the bus as the mocap source. MocapError: the system failed.
    """
    from capture.sources.mocap import MocapBridge, open_bridge_source
    from flightkit.bus.session import open_session

    clock = WallClock()
    with open_session(bus_cfg) as session:
        async with open_bridge_source(lab, clock) as source:
            bridge = MocapBridge(session, Keys(lab.vehicle.namespace), source)
            if on_start is not None:
                on_start(f"bridging mocap {lab.mocap.system_type} to {lab.vehicle.namespace}/mocap/*/pose")
            try:
                await bridge.run(duration_s, clock)
            except asyncio.CancelledError:
                pass
            finally:
                bridge.close()
            return bridge.published

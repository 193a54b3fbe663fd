"""Motion capture: timestamped rigid-body poses, placed in the world frame once, at the edge.

Sources (all :class:`MocapSource`, all built on :class:`WorldFrameSource`):
:class:`~flightkit.mocap.bus_source.BusMocapSource` (poses on the Zenoh bus, e.g. from the
simulator or a mocap bridge), :class:`~flightkit.mocap.motioncapture_source.MotionCaptureSource`
(Vicon, OptiTrack, Qualisys, VRPN, ... through libmotioncapture) and
:class:`~flightkit.mocap.telemetry_source.TelemetryPoseSource` (the autopilot's own estimate).
:func:`open_mocap` picks one from config; :func:`forward_to_vehicle` feeds one body to the
autopilot as external pose. The simulated system is :mod:`flightkit.sim.mocap`.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from flightkit.mocap.base import MocapPose, MocapSample, MocapSource
from flightkit.mocap.factory import open_mocap
from flightkit.mocap.forward import ForwardStats, forward_to_vehicle
from flightkit.mocap.motioncapture_source import MotionCaptureSource, mock_rigid_bodies
from flightkit.mocap.source import WorldFrameSource
from flightkit.mocap.store import PoseStore

if TYPE_CHECKING:
    from flightkit.mocap.bus_source import BusMocapSource

__all__ = [
    "BusMocapSource",
    "ForwardStats",
    "MocapPose",
    "MocapSample",
    "MocapSource",
    "MotionCaptureSource",
    "PoseStore",
    "WorldFrameSource",
    "forward_to_vehicle",
    "mock_rigid_bodies",
    "open_mocap",
]


def __getattr__(name: str) -> Any:
    if name == "BusMocapSource":  # imports zenoh
        return importlib.import_module("flightkit.mocap.bus_source").BusMocapSource
    raise AttributeError(f"module 'flightkit.mocap' has no attribute {name!r}")

"""Motion capture: timestamped rigid-body poses in the world frame.

Sources (all :class:`MocapSource`): :class:`~flightkit.mocap.bus_source.BusMocapSource`
(poses on the Zenoh bus, e.g. from the simulator or a mocap bridge) and
:class:`~flightkit.mocap.motioncapture_source.MotionCaptureSource` (Vicon, OptiTrack,
Qualisys, VRPN, ... through libmotioncapture). :func:`open_mocap` picks one from config;
:func:`forward_to_vehicle` feeds one body to the autopilot as external pose.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from flightkit.mocap.base import MocapPose, MocapSource
from flightkit.mocap.factory import open_mocap
from flightkit.mocap.forward import ForwardStats, forward_to_vehicle
from flightkit.mocap.motioncapture_source import MotionCaptureSource, mock_rigid_bodies
from flightkit.mocap.store import PoseStore

if TYPE_CHECKING:
    from flightkit.mocap.bus_source import BusMocapSource

__all__ = [
    "BusMocapSource",
    "ForwardStats",
    "MocapPose",
    "MocapSource",
    "MotionCaptureSource",
    "PoseStore",
    "forward_to_vehicle",
    "mock_rigid_bodies",
    "open_mocap",
]


def __getattr__(name: str) -> Any:
    if name == "BusMocapSource":  # imports zenoh
        return importlib.import_module("flightkit.mocap.bus_source").BusMocapSource
    raise AttributeError(f"module 'flightkit.mocap' has no attribute {name!r}")

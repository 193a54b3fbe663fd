"""The message bus: Zenoh sessions, key naming, ROS 2 CDR messages, typed pub/sub.

See ``docs/bus.md``. ``flightkit.bus.keys``, ``flightkit.bus.cdr`` and the messages
(``msg_base``, ``pose_msgs``, ``image_msgs``, ``msgs``) are pure (no Zenoh); the names re-exported
here from ``session`` and ``pubsub`` import :mod:`zenoh` lazily, on first use.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from flightkit.bus.keys import Keys, check_name

if TYPE_CHECKING:
    from flightkit.bus.pubsub import BusPublisher, BusSample, BusSubscriber, StreamStats
    from flightkit.bus.session import build_zenoh_config, bus_session, open_session

__all__ = [
    "BusPublisher",
    "BusSample",
    "BusSubscriber",
    "Keys",
    "StreamStats",
    "build_zenoh_config",
    "check_name",
    "open_session",
    "bus_session",
]

_LAZY = {
    "BusPublisher": "pubsub",
    "BusSample": "pubsub",
    "BusSubscriber": "pubsub",
    "StreamStats": "pubsub",
    "build_zenoh_config": "session",
    "open_session": "session",
    "bus_session": "session",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'flightkit.bus' has no attribute {name!r}")
    return getattr(importlib.import_module(f"flightkit.bus.{module}"), name)

"""Every ROS 2 message type flightkit puts on the bus, by name, and decoding by type name.

Types: ``geometry_msgs/PoseStamped``, ``geometry_msgs/TransformStamped``,
``tf2_msgs/TFMessage``, ``nav_msgs/Odometry`` (:mod:`flightkit.bus.pose_msgs`),
``sensor_msgs/Image``, ``sensor_msgs/CompressedImage``, ``sensor_msgs/CameraInfo``
(:mod:`flightkit.bus.image_msgs`); ``std_msgs/Header``, the :class:`Message` protocol and the
schema texts: :mod:`flightkit.bus.msg_base`.
"""

from __future__ import annotations

from flightkit.bus.image_msgs import CameraInfo, CompressedImage, Image
from flightkit.bus.msg_base import Message
from flightkit.bus.pose_msgs import Odometry, PoseStamped, TFMessage, TransformStamped
from flightkit.errors import BusError

__all__ = [
    "MESSAGE_TYPES",
    "decode_message",
]

MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (PoseStamped, TransformStamped, TFMessage, Odometry, Image, CompressedImage, CameraInfo)
}
"""Full ROS 2 type name -> message class."""


def decode_message(msgtype: str, payload: bytes | bytearray | memoryview) -> Message:
    """Decode a payload of the named type (full ROS 2 name).

    Raises:
        BusError: for an unknown type or a malformed payload.
    """
    cls = MESSAGE_TYPES.get(msgtype)
    if cls is None:
        known = ", ".join(sorted(MESSAGE_TYPES))
        raise BusError(f"cannot decode message type {msgtype!r}; known types: {known}")
    return cls.decode(payload)

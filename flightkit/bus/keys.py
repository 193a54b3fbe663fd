"""Key-expression naming on the bus: one namespace per vehicle.

``<ns>/mocap/<body>/pose``                   geometry_msgs/PoseStamped, mocap system frame
``<ns>/camera/<name>/image``                 sensor_msgs/Image (name: color, depth, left, right)
``<ns>/camera/<name>/image/compressed``      sensor_msgs/CompressedImage
``<ns>/camera/<name>/camera_info``           sensor_msgs/CameraInfo
``<ns>/camera/<name>/calibration``           queryable: the camera's calibration as JSON (readout_s, ...)
``<ns>/tf``                                  tf2_msgs/TFMessage (extrinsics, ground truth)
``<ns>/odometry/<estimator>``                VO output (PoseStamped)
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from flightkit.errors import BusError

__all__ = ["Keys", "check_name"]

_NAME = re.compile(r"^[A-Za-z0-9_\-]+$")


def check_name(name: str, what: str) -> str:
    """Validate one key-expression chunk (no '/', '*', '$', '?', '#', spaces)."""
    if not _NAME.match(name):
        raise BusError(
            f"{what} {name!r} is not a valid bus name; use letters, digits, '_' and '-' only"
        )
    return name


@dataclass(frozen=True, slots=True)
class Keys:
    """Key expressions of one vehicle namespace."""

    namespace: str = "uav1"

    def __post_init__(self) -> None:
        for part in self.namespace.split("/"):
            check_name(part, "namespace")

    def mocap_pose(self, body: str) -> str:
        return f"{self.namespace}/mocap/{check_name(body, 'mocap body')}/pose"

    def mocap_all(self) -> str:
        return f"{self.namespace}/mocap/*/pose"

    def camera_image(self, camera: str) -> str:
        return f"{self.namespace}/camera/{check_name(camera, 'camera')}/image"

    def camera_compressed(self, camera: str) -> str:
        return f"{self.namespace}/camera/{check_name(camera, 'camera')}/image/compressed"

    def camera_info(self, camera: str) -> str:
        return f"{self.namespace}/camera/{check_name(camera, 'camera')}/camera_info"

    def camera_calibration(self, camera: str) -> str:
        return f"{self.namespace}/camera/{check_name(camera, 'camera')}/calibration"

    def tf(self) -> str:
        return f"{self.namespace}/tf"

    def odometry(self, estimator: str) -> str:
        return f"{self.namespace}/odometry/{check_name(estimator, 'estimator')}"

    def everything(self) -> str:
        return f"{self.namespace}/**"

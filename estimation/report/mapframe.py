"""The mapping server's 2D map frame and the conversion from the world frame.

The server draws in its own frame: an origin, a rotation and a unit. Configure it with
the world position of the map origin, the angle of the map x axis measured
counter-clockwise from the world x axis (east), and the number of map units per metre::

    [report.map]
    origin_world_m = [1.5, -2.0]   # world (x, y) of the map origin
    rotation_deg = 90.0            # map x axis points along world +y
    units_per_m = 100.0            # the server works in centimetres
    flip_y = false                 # true for image-like maps whose y axis points the other way

Heights are scaled by ``units_per_m`` too (z stays "up"); headings are measured from the
map x axis, counter-clockwise (clockwise when ``flip_y``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from flightkit.frames import Transform, wrap_angle_rad
from flightkit.settings import setting

from .messages import PoseUpdate

__all__ = ["MapFrame", "MapFrameConfig"]


@dataclass(frozen=True, slots=True)
class MapFrameConfig:
    origin_world_m: tuple[float, ...] = setting(
        (0.0, 0.0), length=2, help="world (x, y) of the map origin, m"
    )
    rotation_deg: float = setting(0.0, min=-360.0, max=360.0, help="map x axis, ccw from world x, degrees")
    units_per_m: float = setting(1.0, min=1e-6, max=1e6, help="map units per metre (100 for cm)")
    flip_y: bool = setting(False, help="mirror the map y axis (image-like maps)")


class MapFrame:
    """World (ENU, metres) <-> map (2D + height, map units) conversions."""

    def __init__(self, config: MapFrameConfig | None = None) -> None:
        self.config = config or MapFrameConfig()
        c = self.config
        self._theta = math.radians(c.rotation_deg)
        self._cos, self._sin = math.cos(self._theta), math.sin(self._theta)
        self._ox, self._oy = float(c.origin_world_m[0]), float(c.origin_world_m[1])
        self._s = float(c.units_per_m)
        self._fy = -1.0 if c.flip_y else 1.0

    def point_to_map(
        self, x_world_m: float, y_world_m: float, z_world_m: float = 0.0
    ) -> tuple[float, float, float]:
        dx, dy = x_world_m - self._ox, y_world_m - self._oy
        xm = (self._cos * dx + self._sin * dy) * self._s
        ym = (-self._sin * dx + self._cos * dy) * self._s * self._fy
        return xm, ym, z_world_m * self._s

    def point_to_world(
        self, x_map: float, y_map: float, z_map: float = math.nan
    ) -> tuple[float, float, float]:
        xr, yr = x_map / self._s, y_map * self._fy / self._s
        x = self._cos * xr - self._sin * yr + self._ox
        y = self._sin * xr + self._cos * yr + self._oy
        return x, y, z_map / self._s

    def heading_to_map(self, yaw_world_rad: float) -> float:
        return wrap_angle_rad(self._fy * (yaw_world_rad - self._theta))

    def heading_to_world(self, heading_map_rad: float) -> float:
        return wrap_angle_rad(self._fy * heading_map_rad + self._theta)

    def points_to_map(self, xy_world_m: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Shape (N, 2) world points -> (N, 2) map points."""
        p = np.asarray(xy_world_m, dtype=np.float64).reshape(-1, 2) - (self._ox, self._oy)
        x = (self._cos * p[:, 0] + self._sin * p[:, 1]) * self._s
        y = (-self._sin * p[:, 0] + self._cos * p[:, 1]) * self._s * self._fy
        return np.stack([x, y], axis=1)

    def pose_update(self, stamp_ns: int, T_world_body: Transform, quality: int = 255) -> PoseUpdate:
        """The wire pose of a body pose (position and heading in the map frame)."""
        x, y, z = (float(v) for v in T_world_body.translation)
        xm, ym, zm = self.point_to_map(x, y, z)
        return PoseUpdate(stamp_ns // 1000, xm, ym, zm, self.heading_to_map(T_world_body.yaw_rad), quality)

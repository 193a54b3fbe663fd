"""Compatibility path of the MAVSDK backend; the code lives in :mod:`flightkit.link.mavsdk`.

``from flightkit.link.mavsdk_link import MavsdkLink`` (and the conversions ``mavsdk_url``,
``setpoint_to_mavsdk``, ``external_pose_to_ned``, ``pose_covariance_upper``, ``NedPose``)
keeps working; new code imports from :mod:`flightkit.link.mavsdk`.
"""

from __future__ import annotations

from flightkit.link.mavsdk import *  # noqa: F403  (re-export exactly the package's public names)
from flightkit.link.mavsdk import __all__ as __all__

"""All patterns in one place: ``from trajectories.patterns import Circle, Rectangle, ...``."""

from trajectories.base import Pattern, Reference, YawMode
from trajectories.circle import Circle
from trajectories.hold import Hold
from trajectories.lawnmower import Lawnmower
from trajectories.rectangle import Rectangle, rectangle_corners
from trajectories.takeoff import Land, Takeoff
from trajectories.waypoints import Line, Waypoints

__all__ = [
    "Circle",
    "Hold",
    "Land",
    "Lawnmower",
    "Line",
    "Pattern",
    "Rectangle",
    "Reference",
    "Takeoff",
    "Waypoints",
    "YawMode",
    "rectangle_corners",
]

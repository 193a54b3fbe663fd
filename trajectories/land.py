"""Land reference (defined with take-off in :mod:`trajectories.takeoff`)."""

from trajectories.takeoff import Land

__all__ = ["Land"]

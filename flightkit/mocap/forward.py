"""Forward mocap poses to the autopilot's estimator as external pose (one call).

PX4's EKF2 fuses VISION_POSITION_ESTIMATE or ODOMETRY at 30-50 Hz; ArduPilot wants at
least 4 Hz. :func:`forward_to_vehicle` samples the newest pose of one body at ``rate_hz``
on the clock and sends it through :meth:`VehicleLink.send_vision_pose`, skipping poses that
are invalid (occluded), stale (older than ``stale_after_s`` by ``received_s``) or already
sent -- an estimator is better off with no update than with a repeated or stale one.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

from flightkit.clock import Clock, WallClock
from flightkit.errors import MocapError
from flightkit.mocap.base import MocapSource

if TYPE_CHECKING:
    from flightkit.link.base import ExternalPoseKind, VehicleLink

__all__ = ["ForwardStats", "forward_to_vehicle"]

logger = logging.getLogger(__name__)


@dataclass(slots=True)
class ForwardStats:
    """What :func:`forward_to_vehicle` did so far (updated live)."""

    sent: int = 0
    invalid: int = 0
    stale: int = 0
    repeated: int = 0
    missing: int = 0


async def forward_to_vehicle(
    source: MocapSource,
    link: VehicleLink,
    body: str,
    rate_hz: float = 30.0,
    *,
    clock: Clock | None = None,
    stale_after_s: float = 0.2,
    pos_std_m: float = 0.005,
    rot_std_rad: float = 0.01,
    kind: ExternalPoseKind | None = None,
    stats: ForwardStats | None = None,
) -> None:
    """Send ``body``'s mocap pose to ``link`` as external pose at ``rate_hz`` until cancelled.

    Run it as a task next to the flight: ``tg.create_task(forward_to_vehicle(src, link, "uav1"))``.
    Never returns on its own; errors from the link propagate.

    Args:
        source: an entered mocap source.
        link: a connected vehicle link.
        body: the rigid body of the vehicle.
        rate_hz: sending rate (clock time).
        clock: defaults to the source's clock, else wall time.
        stale_after_s: poses received longer ago than this are not sent.
        pos_std_m, rot_std_rad: the uncertainty sent with each pose.
        kind: VISION_POSITION_ESTIMATE (default) or ODOMETRY.
        stats: counters to update (pass your own to watch them).
    """
    from flightkit.link.base import ExternalPose, ExternalPoseKind

    if rate_hz <= 0:
        raise MocapError(f"forwarding rate_hz must be positive, got {rate_hz}; send poses at e.g. 30.0 Hz")
    clk: Clock = clock or getattr(source, "clock", None) or WallClock()
    kind = kind or ExternalPoseKind.VISION_POSITION_ESTIMATE
    st = stats if stats is not None else ForwardStats()
    period_s = 1.0 / rate_hz
    last_sent: tuple[int, int] | None = None
    next_s = clk.monotonic_s()
    logger.info("forwarding mocap body %r to the vehicle at %g Hz", body, rate_hz)
    while True:
        pose = source.latest(body)
        now_s = clk.monotonic_s()
        if pose is None:
            st.missing += 1
        elif not pose.valid:
            st.invalid += 1
        elif now_s - pose.received_s > stale_after_s:
            st.stale += 1
        elif (pose.stamp_ns, pose.seq) == last_sent:
            st.repeated += 1
        else:
            await link.send_vision_pose(
                ExternalPose(pose.stamp_ns, pose.T_world_body, pos_std_m=pos_std_m, rot_std_rad=rot_std_rad), kind
            )
            last_sent = (pose.stamp_ns, pose.seq)
            st.sent += 1
        next_s += period_s
        delay_s = next_s - clk.monotonic_s()
        if delay_s < -period_s:  # fell behind (suspended?): do not burst to catch up
            next_s = clk.monotonic_s()
            delay_s = 0.0
        await clk.sleep(max(0.0, delay_s))

"""Vehicle state of the MAVSDK backend: the telemetry subscriptions, and waiting on the state.

:class:`VehicleState` runs one asyncio task per MAVSDK subscription (the raw HEARTBEAT
through ``mavlink_direct``, for ``base_mode``/``custom_mode``; position and velocity;
attitude; landed state; battery; STATUSTEXT), each folding what arrives into the state on
the event loop. :meth:`VehicleState.telemetry` takes a snapshot, :meth:`VehicleState.wait_for`
polls a predicate with a clock timeout, and :meth:`VehicleState.reasons_since` collects the
STATUSTEXT lines that explain a refusal.

Frames: MAVSDK reports NED/FRD; the state is stored in ENU/FLU (through :mod:`flightkit.frames`).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import logging
import math
from collections.abc import Awaitable, Callable
from typing import Any

from flightkit.clock import Clock
from flightkit.config import Autopilot
from flightkit.errors import LinkTimeout
from flightkit.frames import (
    ned_to_enu,
    quat_wxyz_to_xyzw,
    quat_xyzw_to_wxyz,
    rotation_enu_flu_from_ned_frd,
    yaw_from_rotation,
)
from flightkit.link.base import BatteryState, FlightMode, LandedState, Telemetry
from flightkit.link.modes import MAV_MODE_FLAG_SAFETY_ARMED, decode_mode

__all__ = ["VehicleState"]

logger = logging.getLogger(__name__)

# Seconds (wall) to wait after a refusal for the STATUSTEXT that explains it.
_REASON_GRACE_S = 0.3
# Clock seconds before a refusal whose STATUSTEXT still counts as its reason.
_REASON_WINDOW_S = 1.0
# Clock seconds between checks of a wait_for predicate.
_POLL_S = 0.02


class VehicleState:
    """The latest vehicle state, written by subscription tasks on the event loop.

    Args:
        autopilot: the firmware, to decode the HEARTBEAT's custom mode.
        clock: time source of the stamps, of :meth:`telemetry` and of :meth:`wait_for`.
    """

    def __init__(self, autopilot: Autopilot, clock: Clock) -> None:
        self._autopilot = autopilot
        self._clock = clock
        self._tasks: list[asyncio.Task[None]] = []
        self.armed = False
        self.mode = FlightMode.UNKNOWN
        self.custom_mode = 0
        self.landed = LandedState.UNDEFINED
        self.pos_enu: tuple[float, float, float] = (math.nan, math.nan, math.nan)
        self.vel_enu: tuple[float, float, float] = (math.nan, math.nan, math.nan)
        self.quat_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
        self.yaw = math.nan
        self.battery = BatteryState()
        self.stamp_s = 0.0
        self.last_heartbeat_s = -math.inf
        self.texts: collections.deque[tuple[float, str]] = collections.deque(maxlen=64)
        self.text_seq = 0
        self._text_arrived = asyncio.Event()

    def telemetry(self) -> Telemetry:
        """A snapshot of the latest state; returns immediately."""
        now = self._clock.monotonic_s()
        return Telemetry(
            stamp_s=self.stamp_s,
            armed=self.armed,
            mode=self.mode,
            custom_mode=self.custom_mode,
            landed_state=self.landed,
            pos_local_enu_m=self.pos_enu,
            vel_local_enu_m_s=self.vel_enu,
            R_local_body_quat_wxyz=self.quat_wxyz,
            yaw_local_rad=self.yaw,
            battery=self.battery,
            heartbeat_age_s=max(0.0, now - self.last_heartbeat_s),
        )

    # ------------------------------------------------------------------ subscriptions

    def start(
        self, direct: Any, telemetry: Any, sysid: int, first_hb: asyncio.Future[dict[str, Any]]
    ) -> None:
        """Start the subscription tasks on the running loop.

        Args:
            direct: MAVSDK's ``mavlink_direct`` plugin (for the raw HEARTBEAT).
            telemetry: MAVSDK's telemetry plugin.
            sysid: the autopilot's system id; heartbeats of other systems are ignored.
            first_hb: resolved with the first autopilot HEARTBEAT's fields (plus ``_component_id``).
        """
        tel = telemetry

        async def heartbeats() -> None:
            async for msg in direct.subscribe_message("HEARTBEAT"):
                if msg.system_id != sysid or msg.component_id != 1:
                    continue  # another component of the vehicle (camera, gimbal, companion)
                try:
                    fields = json.loads(msg.fields_json)
                except ValueError:
                    logger.debug("unparsable HEARTBEAT fields %r", msg.fields_json)
                    continue
                self._on_heartbeat(fields)
                if not first_hb.done():
                    fields["_component_id"] = msg.component_id
                    first_hb.set_result(fields)

        async def position_velocity() -> None:
            async for pv in tel.subscribe_position_velocity_ned():
                p, v = pv.position, pv.velocity
                pe = ned_to_enu([p.north_m, p.east_m, p.down_m])
                ve = ned_to_enu([v.north_m_s, v.east_m_s, v.down_m_s])
                self.pos_enu = (float(pe[0]), float(pe[1]), float(pe[2]))
                self.vel_enu = (float(ve[0]), float(ve[1]), float(ve[2]))
                self.stamp_s = self._clock.monotonic_s()

        async def attitude() -> None:
            from scipy.spatial.transform import Rotation

            async for q in tel.subscribe_attitude_quaternion():
                wxyz = (q.w, q.x, q.y, q.z)
                if not all(math.isfinite(x) for x in wxyz) or sum(x * x for x in wxyz) < 0.5:
                    continue
                R_enu_flu = rotation_enu_flu_from_ned_frd(Rotation.from_quat(quat_wxyz_to_xyzw(wxyz)))
                qq = quat_xyzw_to_wxyz(R_enu_flu.as_quat())
                self.quat_wxyz = (float(qq[0]), float(qq[1]), float(qq[2]), float(qq[3]))
                self.yaw = yaw_from_rotation(R_enu_flu)
                self.stamp_s = self._clock.monotonic_s()

        async def landed() -> None:
            async for s in tel.subscribe_landed_state():
                try:
                    new = LandedState(int(s))
                except ValueError:
                    new = LandedState.UNDEFINED
                if new is not self.landed:
                    logger.info("landed state: %s", new.name)
                self.landed = new

        async def battery() -> None:
            async for b in tel.subscribe_battery():
                self.battery = BatteryState(voltage_v=float(b.voltage_v), remaining_pct=float(b.remaining_percent))

        async def status_text() -> None:
            async for st in tel.subscribe_status_text():
                text = st.text.strip()
                self.texts.append((self._clock.monotonic_s(), text))
                self.text_seq += 1
                self._text_arrived.set()
                logger.info("autopilot says: %s", text)

        for name, fn in (
            ("heartbeat", heartbeats),
            ("position_velocity_ned", position_velocity),
            ("attitude_quaternion", attitude),
            ("landed_state", landed),
            ("battery", battery),
            ("status_text", status_text),
        ):
            self._tasks.append(asyncio.create_task(_guard(name, fn), name=f"mavsdk-{name}"))

    def take_tasks(self) -> list[asyncio.Task[None]]:
        """Hand over the subscription tasks (to cancel them); the state keeps none."""
        tasks, self._tasks = self._tasks, []
        return tasks

    def _on_heartbeat(self, fields: dict[str, Any]) -> None:
        base = int(fields.get("base_mode", 0))
        custom = int(fields.get("custom_mode", 0))
        armed = bool(base & MAV_MODE_FLAG_SAFETY_ARMED)
        mode = decode_mode(self._autopilot, base, custom)
        if armed != self.armed:
            logger.info("%s", "armed" if armed else "disarmed")
        if mode is not self.mode:
            logger.info("mode: %s", mode.value)
        self.armed, self.mode, self.custom_mode = armed, mode, custom
        self.last_heartbeat_s = self._clock.monotonic_s()

    # ------------------------------------------------------------------ reasons and waiting

    async def reasons_since(self, seq0: int) -> tuple[str, ...]:
        """STATUSTEXT lines that explain a refusal: those since text number ``seq0`` (waiting
        briefly for a late one) plus any from the second before the command."""
        if self.text_seq == seq0:
            self._text_arrived.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._text_arrived.wait(), timeout=_REASON_GRACE_S)
        texts = list(self.texts)
        n_new = min(self.text_seq - seq0, len(texts))
        cut = len(texts) - n_new
        newest_old = texts[cut - 1][0] if cut > 0 else -math.inf
        window_start = (texts[cut][0] if n_new else self._clock.monotonic_s()) - _REASON_WINDOW_S
        before = [t for stamp, t in texts[:cut] if stamp >= window_start and stamp <= newest_old]
        return tuple(before + [t for _, t in texts[cut:]])

    async def wait_for(self, predicate: Callable[[Telemetry], bool], timeout_s: float, what: str) -> Telemetry:
        """Wait until ``predicate(telemetry)`` is true (checked every 20 ms of clock time).

        Raises:
            LinkTimeout: not true after ``timeout_s`` clock seconds; the message names ``what``
                and the last state.
        """
        deadline = self._clock.monotonic_s() + timeout_s
        while True:
            t = self.telemetry()
            if predicate(t):
                return t
            if self._clock.monotonic_s() >= deadline:
                raise LinkTimeout(
                    f"timed out after {timeout_s:.1f} s waiting for {what} "
                    f"(mode {t.mode.value}, armed {t.armed}, landed {t.landed_state.name}, "
                    f"heartbeat age {t.heartbeat_age_s:.1f} s)",
                    what=what,
                    timeout_s=timeout_s,
                )
            await self._clock.sleep(_POLL_S)


async def _guard(name: str, fn: Callable[[], Awaitable[None]]) -> None:
    """Run a subscription; log (not raise) if it fails, so one bad stream can't kill the link."""
    try:
        await fn()
    except asyncio.CancelledError:
        raise
    except Exception:
        logger.exception("MAVSDK %s subscription failed; that part of the telemetry stops updating", name)

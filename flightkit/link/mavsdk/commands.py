"""Commands of the MAVSDK backend: plugin calls with deadlines, refusals with their reasons.

:class:`CommandChannel` awaits MAVSDK calls under an overall wall deadline (on top of MAVSDK's
own retries), turns the plugins' errors into :class:`~flightkit.errors.CommandRejected` (with
the STATUSTEXT lines the autopilot sent around the refusal, from the
:class:`~flightkit.link.mavsdk.telemetry.VehicleState`) or
:class:`~flightkit.errors.LinkTimeout`, starts offboard, and sends MAV_CMD_DO_SET_MODE as a raw
COMMAND_LONG through ``mavlink_direct`` for the modes MAVSDK has no call for (ArduPilot BRAKE,
PX4 POSCTL, ...).
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Awaitable, Callable, Sequence
from typing import Any, TypeVar

from flightkit.config import Autopilot, LinkConfig
from flightkit.errors import CommandRejected, LinkTimeout
from flightkit.link.base import FlightMode, VehicleInfo
from flightkit.link.mavlink.encoding import result_name
from flightkit.link.mavsdk.connection import MavsdkConnection
from flightkit.link.mavsdk.telemetry import VehicleState
from flightkit.link.modes import set_mode_params

__all__ = ["MAV_CMD_DO_SET_MODE", "CommandChannel"]

logger = logging.getLogger(__name__)

T = TypeVar("T")

MAV_CMD_DO_SET_MODE = 176

# Extra wall seconds on top of MAVSDK's own command retries before we give up on a call.
_CALL_MARGIN_S = 2.0


class CommandChannel:
    """MAVSDK calls on one connection, with deadlines and refusal reasons.

    Args:
        cfg: link settings (``command_timeout_s``, our system/component ids).
        conn: the open MAVSDK connection (its plugins are looked up at each call).
        state: the vehicle state, for the STATUSTEXT lines that explain a refusal.
    """

    def __init__(self, cfg: LinkConfig, conn: MavsdkConnection, state: VehicleState) -> None:
        self._cfg = cfg
        self._conn = conn
        self._state = state

    async def call(self, what: str, coro: Awaitable[T]) -> T:
        """Await a MAVSDK call with an overall (wall) deadline on top of MAVSDK's own retries."""
        limit = self._cfg.command_timeout_s + _CALL_MARGIN_S
        try:
            return await asyncio.wait_for(coro, timeout=limit)
        except TimeoutError:
            raise LinkTimeout(
                f"MAVSDK {what} did not return within {limit:.1f} s; is the link still up?",
                what=what,
                timeout_s=limit,
            ) from None

    async def action(self, command: str, fn: Callable[[], Awaitable[Any]], hint: str = "") -> None:
        """Run an action-plugin call; ActionError -> CommandRejected with the autopilot's words."""
        from mavsdk.asyncio.plugins.action import ActionError, ActionResult

        seq0 = self._state.text_seq
        try:
            await self.call(command, fn())
        except ActionError as exc:
            result = exc.result
            reasons = await self._state.reasons_since(seq0)
            if result in (ActionResult.TIMEOUT, ActionResult.NO_SYSTEM, ActionResult.CONNECTION_ERROR):
                raise LinkTimeout(
                    f"no answer to {command} ({result.name}) from the autopilot on {self._conn.url}; "
                    "is the link up?",
                    what=command,
                    timeout_s=self._cfg.command_timeout_s,
                ) from exc
            raise CommandRejected(command, result.name, reasons, hint) from exc

    async def read_params(self, names: Sequence[str]) -> dict[str, float]:
        """Read parameters through the param plugin, one by one (float first, then int on
        WRONG_TYPE); returns those that could be read, integers as whole floats."""
        from mavsdk.asyncio.plugins.param import ParamError, ParamResult

        param = self._conn.param
        out: dict[str, float] = {}
        for name in dict.fromkeys(names):
            try:
                try:
                    out[name] = float(await self.call(f"param {name}", param.get_param_float(name)))
                except ParamError as exc:
                    if exc.result not in (ParamResult.WRONG_TYPE, ParamResult.TYPE_MISMATCH):
                        raise
                    out[name] = float(await self.call(f"param {name}", param.get_param_int(name)))
            except (ParamError, LinkTimeout) as exc:
                logger.info("parameter %s not read: %s", name, exc)
        return out

    async def start_offboard(self) -> None:
        """``offboard.start()``; OffboardError -> CommandRejected or LinkTimeout.

        The caller makes sure a setpoint has been sent (MAVSDK refuses otherwise).
        """
        from mavsdk.asyncio.plugins.offboard import OffboardError, OffboardResult

        seq0 = self._state.text_seq
        try:
            await self.call("offboard.start", self._conn.offboard.start())
        except OffboardError as exc:
            reasons = await self._state.reasons_since(seq0)
            if exc.result in (
                OffboardResult.TIMEOUT,
                OffboardResult.NO_SYSTEM,
                OffboardResult.CONNECTION_ERROR,
            ):
                raise LinkTimeout(
                    f"no answer to offboard.start ({exc.result.name}) from the autopilot on {self._conn.url}",
                    what="offboard.start",
                    timeout_s=self._cfg.command_timeout_s,
                ) from exc
            raise CommandRejected(
                "offboard.start",
                exc.result.name,
                reasons,
                "PX4 wants setpoints for about a second before OFFBOARD; keep the stream running and retry",
            ) from exc

    async def do_set_mode(self, autopilot: Autopilot, info: VehicleInfo, target: FlightMode) -> None:
        """MAV_CMD_DO_SET_MODE through mavlink_direct, for modes MAVSDK has no call for."""
        from mavsdk.plugins.mavlink_direct import MavlinkDirectError, MavlinkMessage

        cmd = set_mode_params(autopilot, target)
        fields = {
            "target_system": info.system_id,
            "target_component": info.component_id,
            "command": MAV_CMD_DO_SET_MODE,
            "confirmation": 0,
            "param1": cmd.params[0],
            "param2": cmd.params[1],
            "param3": cmd.params[2],
            "param4": 0.0,
            "param5": 0.0,
            "param6": 0.0,
            "param7": 0.0,
        }
        msg = MavlinkMessage(
            message_name="COMMAND_LONG",
            system_id=self._cfg.source_system,
            component_id=self._cfg.source_component,
            target_system_id=info.system_id,
            target_component_id=info.component_id,
            fields_json=json.dumps(fields),
        )
        seq0 = self._state.text_seq
        what = f"MAV_CMD_DO_SET_MODE {target.value}"
        try:
            ack = await self.call(what, self._conn.direct.send_command(msg))
        except MavlinkDirectError as exc:
            raise LinkTimeout(
                f"no COMMAND_ACK for {what} from the autopilot on {self._conn.url} ({exc.result.name})",
                what=what,
                timeout_s=self._cfg.command_timeout_s,
            ) from exc
        try:
            result = int(json.loads(ack.fields_json).get("result", 0))
        except (ValueError, AttributeError):
            result = 0
        if result != 0:
            reasons = await self._state.reasons_since(seq0)
            raise CommandRejected("MAV_CMD_DO_SET_MODE", result_name(result), reasons)

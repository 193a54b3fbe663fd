"""COMMAND_LONG with COMMAND_ACK handling for the pymavlink backend.

:class:`CommandChannel` sends a command, re-sends it (``confirmation`` counting up) when no
ACK arrives, follows IN_PROGRESS ACKs to the final result, and turns a refusal into a
:class:`~flightkit.errors.CommandRejected` that carries the STATUSTEXT lines the autopilot
sent around it (its reasons). ACKs and texts come from the link's
:class:`~flightkit.link.mavlink.telemetry.VehicleState`, filled by the reader thread.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from flightkit.clock import Clock
from flightkit.errors import CommandRejected, LinkError, LinkTimeout
from flightkit.link.mavlink.encoding import (
    MAV_RESULT_ACCEPTED,
    MAV_RESULT_IN_PROGRESS,
    cmd_name,
    decode_param_value,
    result_name,
)
from flightkit.link.mavlink.telemetry import VehicleState

__all__ = ["CommandChannel"]

logger = logging.getLogger(__name__)

_REJECT_TEXT_WINDOW_S = 1.0  # STATUSTEXT this long before a command belongs to its refusal
_REJECT_TEXT_GRACE_S = 0.2  # and texts arriving this long after the refusal

# Telemetry we ask for (SET_MESSAGE_INTERVAL), as (message id, rate Hz).
_STREAMS: tuple[tuple[int, float], ...] = (
    (mavlink2.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 50.0),
    (mavlink2.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, 50.0),
    (mavlink2.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 5.0),
    (mavlink2.MAVLINK_MSG_ID_SYS_STATUS, 2.0),
    (mavlink2.MAVLINK_MSG_ID_BATTERY_STATUS, 1.0),
    (mavlink2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 5.0),
    (mavlink2.MAVLINK_MSG_ID_HOME_POSITION, 0.5),
)


class CommandChannel:
    """Commands and their acknowledgements over one link.

    Args:
        state: the link's vehicle state (ACKs, STATUSTEXT, heartbeat age).
        clock: time source of timeouts.
        send: puts one message on the wire (any thread).
        require_target: returns the (system, component) to address, or raises LinkError
            when not connected.
        timeout_s: default total time for one command (``link.command_timeout_s``).
    """

    def __init__(
        self,
        state: VehicleState,
        clock: Clock,
        send: Callable[[Any], None],
        require_target: Callable[[], tuple[int, int]],
        timeout_s: float,
    ) -> None:
        self._state = state
        self._clock = clock
        self._send = send
        self._require_target = require_target
        self._timeout_s = timeout_s

    async def command_long(
        self,
        command: int,
        params: tuple[float, ...] = (),
        *,
        attempts: int = 3,
        timeout_s: float | None = None,
    ) -> int:
        """Send COMMAND_LONG and return the final MAV_RESULT of its COMMAND_ACK.

        The command is re-sent (``confirmation`` counting up) when no ACK arrives within
        ``timeout_s / attempts``; IN_PROGRESS ACKs stop the retries and extend the wait
        by ``timeout_s`` for the final answer.

        Raises:
            LinkError: not connected.
            LinkTimeout: no ACK after all attempts.
        """
        target = self._require_target()
        total_s = self._timeout_s if timeout_s is None else timeout_s
        per_attempt_s = total_s / max(1, attempts)
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        name = cmd_name(command)
        for confirmation in range(attempts):
            with self._state.lock:
                seen = self._state.acks.get(command, (0, 0, 0.0))[0]
            self._send(
                mavlink2.MAVLink_command_long_message(target[0], target[1], command, confirmation & 0xFF, *p)
            )
            logger.debug("sent %s (attempt %d) params %s", name, confirmation + 1, p)
            try:
                seq, result = await self._wait_ack(command, seen, per_attempt_s)
            except LinkTimeout:
                continue
            while result == MAV_RESULT_IN_PROGRESS:
                seq, result = await self._wait_ack(command, seq, total_s)
            return result
        raise LinkTimeout(
            f"no COMMAND_ACK for {name} after {attempts} attempts in {total_s:.1f} s "
            f"(heartbeat age {self._state.telemetry().heartbeat_age_s:.1f} s); check the link and raise "
            "link.command_timeout_s if it is slow",
            what=f"COMMAND_ACK {name}",
            timeout_s=total_s,
        )

    async def _wait_ack(self, command: int, after_seq: int, timeout_s: float) -> tuple[int, int]:
        def probe() -> tuple[int, int] | None:
            with self._state.lock:
                entry = self._state.acks.get(command)
            if entry is None or entry[0] <= after_seq:
                return None
            return entry[0], entry[1]

        return await self._state.wait_until(
            probe,
            timeout_s,
            lambda: LinkTimeout(f"no COMMAND_ACK for {cmd_name(command)}", "COMMAND_ACK", timeout_s),
        )

    async def read_params(self, names: Sequence[str], bytewise: bool, attempts: int = 2) -> dict[str, float]:
        """Read parameters with PARAM_REQUEST_READ (by name), re-asking for the missing ones
        ``attempts`` times within the command timeout; returns the values that arrived
        (:func:`~flightkit.link.mavlink.encoding.decode_param_value`, ``bytewise`` for PX4)."""
        target = self._require_target()
        wanted = list(dict.fromkeys(names))
        with self._state.lock:
            for name in wanted:
                self._state.params.pop(name, None)

        def arrived() -> dict[str, tuple[float, int]]:
            with self._state.lock:
                return {n: self._state.params[n] for n in wanted if n in self._state.params}

        def probe() -> dict[str, tuple[float, int]] | None:
            got = arrived()
            return got if len(got) == len(wanted) else None

        per_attempt_s = self._timeout_s / max(1, attempts)
        for _ in range(attempts):
            got = arrived()
            for name in wanted:
                if name not in got:
                    self._send(
                        mavlink2.MAVLink_param_request_read_message(target[0], target[1], name.encode(), -1)
                    )
            try:
                await self._state.wait_until(
                    probe, per_attempt_s, lambda: LinkTimeout("PARAM_VALUE", "PARAM_VALUE", per_attempt_s)
                )
                break
            except LinkTimeout:
                continue
        got = arrived()
        missing = [n for n in wanted if n not in got]
        if missing:
            logger.info("no PARAM_VALUE for %s after %.1f s", ", ".join(missing), self._timeout_s)
        return {n: decode_param_value(wire, ptype, bytewise) for n, (wire, ptype) in got.items()}

    async def checked(self, command: int, params: tuple[float, ...], hint: str = "", **kw: Any) -> None:
        """:meth:`command_long`, raising CommandRejected (with nearby STATUSTEXT) unless ACCEPTED."""
        sent_at = self._clock.monotonic_s()
        result = await self.command_long(command, params, **kw)
        if result != MAV_RESULT_ACCEPTED:
            raise await self.rejection(command, result, sent_at, hint)

    async def rejection(self, command: int, result: int, sent_at: float, hint: str) -> CommandRejected:
        """The CommandRejected for ``result``, with the STATUSTEXT sent around ``sent_at``
        (waits briefly: texts often trail the ACK by a few ms)."""
        await self._clock.sleep(_REJECT_TEXT_GRACE_S)
        with self._state.lock:
            texts = tuple(
                t for when, _, t in self._state.statustext if when >= sent_at - _REJECT_TEXT_WINDOW_S
            )
        logger.info("%s refused: %s %s", cmd_name(command), result_name(result), "; ".join(texts))
        return CommandRejected(cmd_name(command), result_name(result), texts, hint)

    async def request_telemetry(self) -> None:
        """Ask for the telemetry the link decodes and for AUTOPILOT_VERSION; failures are logged only."""

        async def one(command: int, params: tuple[float, ...]) -> None:
            try:
                result = await self.command_long(command, params, attempts=2)
            except LinkError as exc:
                logger.debug("%s %s: %s", cmd_name(command), params, exc)
                return
            if result != MAV_RESULT_ACCEPTED:
                logger.debug("%s %s refused: %s", cmd_name(command), params, result_name(result))

        await one(mavlink2.MAV_CMD_REQUEST_MESSAGE, (float(mavlink2.MAVLINK_MSG_ID_AUTOPILOT_VERSION),))
        for msg_id, rate in _STREAMS:
            await one(mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, (float(msg_id), 1e6 / rate))

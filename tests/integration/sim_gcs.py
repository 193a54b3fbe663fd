"""A raw pymavlink GCS for the simulated autopilot's wire tests and their shared constants
(tests/integration/test_sim_autopilot*.py; the lab and client fixtures are in conftest.py).

Time runs on ``SimClock(speed=...)``; every wait is on a received message or a state, with a
timeout; timing figures are measured in simulated time (``lab.clock.monotonic_s()``).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import Any

from pymavlink import mavutil

from flightkit.sim.lab import SimLab

mav = mavutil.mavlink
SPEED = 10.0

PX4_POSCTL = 196608
PX4_OFFBOARD = 393216
PX4_HOLD = 50593792
PX4_LAND = 100925440
PX4_TAKEOFF = 33816576
HOME_AMSL_M = 488.0

QUIET_STREAMS = {
    mav.MAVLINK_MSG_ID_ATTITUDE: 0.0,
    mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 0.0,
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 0.0,
    mav.MAVLINK_MSG_ID_VFR_HUD: 0.0,
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 10.0,
}

VEL_YAW = 2503  # velocity + yaw
VEL_YAWRATE = 1479  # velocity + yaw rate
VEL_ONLY = 3527


class Client:
    """A raw pymavlink GCS: heartbeats, commands, setpoint streaming."""

    def __init__(self, lab: SimLab, key: bytes | None = None, sign: bool = True, gcs: bool = True) -> None:
        self.lab = lab
        self.conn: Any = mavutil.mavlink_connection(
            lab.client_url, source_system=255, source_component=190, dialect="ardupilotmega"
        )
        if key is not None:
            self.conn.setup_signing(key, sign_outgoing=sign)
        self.texts: list[str] = []
        self._stream: threading.Thread | None = None
        self._stop = threading.Event()
        self.setpoint: tuple[int, int, tuple[float, ...]] | None = None
        self.last_sent_s = -math.inf
        self.gcs = gcs
        self.last_heartbeat_s = -math.inf
        self._closed = threading.Event()
        self._send_lock = threading.Lock()  # the heartbeat and stream threads share the encoder
        self.heartbeat()
        # a GCS sends its heartbeat at 1 Hz (ArduCopter's GCS failsafe watches it)
        self._beat = threading.Thread(target=self._beat_1hz, daemon=True)
        self._beat.start()

    def _beat_1hz(self) -> None:
        while not self._closed.is_set():
            self.lab.clock.sleep_blocking(1.0)
            if not self._closed.is_set():
                self.heartbeat()

    def close(self) -> None:
        """The companion dies: setpoints and heartbeats stop."""
        self._closed.set()
        self.stop_stream()
        self._beat.join(timeout=2.0)
        self.conn.close()

    def heartbeat(self) -> None:
        kind = mav.MAV_TYPE_GCS if self.gcs else mav.MAV_TYPE_ONBOARD_CONTROLLER
        with self._send_lock:
            self.last_heartbeat_s = self.lab.clock.monotonic_s()
            self.conn.mav.heartbeat_send(kind, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def recv(self, types: str | list[str], cond: Callable[[Any], bool] = lambda m: True, timeout_s: float = 5.0) -> Any:
        """Next message of ``types`` satisfying ``cond`` within ``timeout_s`` wall seconds."""
        deadline = wall_s() + timeout_s
        want = [types] if isinstance(types, str) else types
        while wall_s() < deadline:
            msg = self.conn.recv_match(blocking=True, timeout=0.2)
            if msg is None:
                continue
            if msg.get_type() == "STATUSTEXT":
                self.texts.append(msg.text)
            if msg.get_type() in want and msg.get_srcSystem() == 1 and cond(msg):
                return msg
        raise AssertionError(f"no {want} matching within {timeout_s} s")

    def command(self, command: int, *params: float, timeout_s: float = 3.0) -> int:
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(1, 1, command, 0, *p)
        return int(self.recv("COMMAND_ACK", lambda m: m.command == command, timeout_s).result)

    def set_mode(self, custom_mode: int) -> int:
        if self.lab.personality.autopilot.value == "px4":
            main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
            return self.command(mav.MAV_CMD_DO_SET_MODE, 1, main, sub)
        return self.command(mav.MAV_CMD_DO_SET_MODE, 1, custom_mode)

    def wait_heartbeat(self, cond: Callable[[Any], bool], timeout_s: float = 5.0) -> Any:
        return self.recv("HEARTBEAT", cond, timeout_s)

    def send_setpoint(self, frame: int, mask: int, values: tuple[float, ...]) -> None:
        x, y, z, vx, vy, vz, yaw, yaw_rate = values
        with self._send_lock:
            self.last_sent_s = self.lab.clock.monotonic_s()
            self.conn.mav.set_position_target_local_ned_send(
                0, 1, 1, frame, mask, x, y, z, vx, vy, vz, 0, 0, 0, yaw, yaw_rate
            )

    def stream(self, frame: int, mask: int, values: tuple[float, ...], rate_hz: float = 10.0) -> None:
        """Send a setpoint at ``rate_hz`` of sim time in the background (replace with the same call)."""
        self.setpoint = (frame, mask, values)
        if self._stream is not None:
            return
        self._stop.clear()

        def run() -> None:
            while not self._stop.is_set():
                if self.setpoint is not None:
                    self.send_setpoint(*self.setpoint)
                    self.heartbeat()
                self.lab.clock.sleep_blocking(1.0 / rate_hz)

        self._stream = threading.Thread(target=run, daemon=True)
        self._stream.start()

    def stop_stream(self) -> None:
        self._stop.set()
        if self._stream is not None:
            self._stream.join(timeout=2.0)
        self._stream = None


def wall_s() -> float:
    return time.monotonic()


def vel(vn: float, ve: float, vd: float, yaw: float = 0.0, yaw_rate: float = 0.0) -> tuple[float, ...]:
    return (0.0, 0.0, 0.0, vn, ve, vd, yaw, yaw_rate)


def local(client: Client) -> Any:
    return client.recv("LOCAL_POSITION_NED")


def wait_local(client: Client, cond: Callable[[Any], bool], timeout_s: float = 10.0) -> Any:
    return client.recv("LOCAL_POSITION_NED", cond, timeout_s)


def event_s(
    lab: SimLab, kind: str, detail: str = "", after_s: float = -math.inf, timeout_s: float = 5.0
) -> float:
    """When the lab logged the first ``kind`` event containing ``detail`` after ``after_s`` (clock time).

    Timing checks use these stamps, taken by the simulator as it acts, rather than the time the
    test's client happened to receive the consequence (at 10x, 40 ms of wall time between the
    datagram and this thread's next turn are 0.4 s). Waits for the event: the simulator may send
    its consequence (a STATUSTEXT, say) a moment before it logs the event.
    """

    def found() -> list[float]:
        return [e.stamp_s for e in lab.event_log if e.kind == kind and detail in e.detail and e.stamp_s > after_s]

    lab.wait_until(lambda: bool(found()), timeout_s=timeout_s, what=f"a {kind!r} event containing {detail!r}")
    return found()[0]


def new_client(clients: list[Client], lab: SimLab, **kw: Any) -> Client:
    c = Client(lab, **kw)
    clients.append(c)
    return c

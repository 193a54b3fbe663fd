"""MavsdkLink over real UDP against the simulated autopilot (and against nothing at all).

MAVSDK keeps wall time inside (command retries, its 3 s connection timeout, the 20 Hz
offboard re-send), so the simulator and the link share a ``SimClock`` at speed 3 (stall-limited;
MAVSDK keeps up at 3x, as in tests/integration/test_fly_patterns.py): a flight of ~16 simulated
seconds takes ~5.5 s of wall time. Ports are chosen by the OS.
"""

from __future__ import annotations

import asyncio
import functools
import math
import socket
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from dataclasses import replace

import numpy as np
import pytest

from flightkit.clock import ONE_PROCESS_WALL_STEP_S, SimClock
from flightkit.config import Autopilot, ConfigError, LinkBackend, LinkConfig
from flightkit.errors import CommandRejected, EndpointError, LinkTimeout
from flightkit.frames import Transform
from flightkit.link import open_link
from flightkit.link.base import (
    ExternalPose,
    ExternalPoseKind,
    FlightMode,
    LandedState,
    SetpointFrame,
    Telemetry,
    VehicleLink,
    VelocitySetpoint,
)
from flightkit.link.mavsdk import MavsdkLink
from flightkit.sim.lab import SimEvent, SimLab

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(90)]

SPEED = 3.0


def asynctest(fn: Callable[..., Awaitable[None]]) -> Callable[..., None]:
    """Run an async test on a fresh event loop (no plugin needed)."""

    @functools.wraps(fn)
    def wrapper(*args: object, **kwargs: object) -> None:
        asyncio.run(fn(*args, **kwargs))  # type: ignore[arg-type]

    return wrapper


def link_config(url: str, **kw: object) -> LinkConfig:
    base = LinkConfig(url=url, backend=LinkBackend.MAVSDK, heartbeat_timeout_s=5.0, command_timeout_s=3.0)
    return replace(base, **kw)  # type: ignore[arg-type]


@asynccontextmanager
async def flight(
    autopilot: Autopilot, link_kw: dict[str, object] | None = None, **lab_kw: object
) -> AsyncIterator[tuple[SimLab, MavsdkLink]]:
    """A simulated lab on a free port and a connected MAVSDK link to it."""
    # Stall-limited like every one-process lab (docs/sim.md "Time"): a host stall slows simulated
    # time down instead of letting it jump past the offboard-loss failsafe while MAVSDK's
    # threads wait for the CPU.
    clock = SimClock(SPEED, max_wall_step_s=ONE_PROCESS_WALL_STEP_S)
    kw: dict[str, object] = {"ready_after_s": 0.0, **lab_kw}
    lab = SimLab(autopilot=autopilot, url="udpin:127.0.0.1:0", clock=clock, **kw)  # type: ignore[arg-type]
    with lab:
        link = open_link(link_config(lab.client_url, **(link_kw or {})), autopilot, clock)
        assert isinstance(link, MavsdkLink)
        async with link:
            yield lab, link


def above(alt_m: float) -> Callable[[Telemetry], bool]:
    return lambda t: t.pos_local_enu_m[2] >= alt_m


async def feed(link: MavsdkLink, seconds: float, sp: VelocitySetpoint) -> None:
    """Feed a setpoint every 50 ms of clock time, as a controller would."""
    end = link.clock.monotonic_s() + seconds
    while link.clock.monotonic_s() < end:
        link.set_velocity(sp)
        await link.clock.sleep(0.05)


# --------------------------------------------------------------------------- without a simulator


@asynctest
async def test_no_autopilot_gives_link_timeout_with_a_helpful_sentence() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as quiet:
        quiet.bind(("127.0.0.1", 0))  # a port where nobody answers
        port = quiet.getsockname()[1]
        link = MavsdkLink(
            link_config(f"udpout:127.0.0.1:{port}", heartbeat_timeout_s=0.5), Autopilot.PX4, SimClock(1)
        )
        t0 = time.monotonic()
        with pytest.raises(LinkTimeout, match="no autopilot HEARTBEAT .* after 0.5 s") as info:
            await link.connect()
        assert info.value.what == "HEARTBEAT"
        assert time.monotonic() - t0 < 3.0
        await link.close()


@asynctest
async def test_port_in_use_gives_endpoint_error() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        link = MavsdkLink(link_config(f"udpin:127.0.0.1:{port}"), Autopilot.PX4, SimClock(1))
        with pytest.raises(EndpointError, match="cannot open"):
            await link.connect()


def test_bad_url_and_signing_are_refused_at_construction() -> None:
    with pytest.raises(EndpointError):
        open_link(link_config("carrier-pigeon:1:2"), Autopilot.PX4, SimClock(1))
    with pytest.raises(ConfigError, match="signing"):
        MavsdkLink(
            link_config("udpout:127.0.0.1:14540", signing_key_hex="ab" * 32), Autopilot.PX4, SimClock(1)
        )


# --------------------------------------------------------------------------- external pose at the wire


class _PosePeer:
    """A bare MAVLink peer on real UDP: heartbeats as PX4 and records what arrives (pymavlink codec)."""

    def __init__(self) -> None:
        from pymavlink import mavutil

        self.conn = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=1, source_component=1)
        self.port = self.conn.port.getsockname()[1]
        self.received: dict[str, list[object]] = {}
        self._stop = threading.Event()
        self.both_poses = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        last = 0.0
        while not self._stop.is_set():
            if (
                time.monotonic() - last > 0.1 and self.conn.address is not None
            ):  # heartbeat once a client spoke
                last = time.monotonic()
                self.conn.mav.heartbeat_send(2, 12, 1, 3 << 16, 3)
            msg = self.conn.recv_match(blocking=True, timeout=0.02)
            if msg is not None:
                self.received.setdefault(msg.get_type(), []).append(msg)
                if "ODOMETRY" in self.received and "VISION_POSITION_ESTIMATE" in self.received:
                    self.both_poses.set()

    def __enter__(self) -> _PosePeer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.conn.close()


@asynctest
async def test_external_pose_reaches_the_wire_in_ned_frd() -> None:
    with _PosePeer() as peer:
        link = MavsdkLink(link_config(f"udpout:127.0.0.1:{peer.port}"), Autopilot.PX4, SimClock(1))
        async with link:
            # Body at ENU (1, 2, 0.5), facing north (ENU yaw 90 deg), moving east at 0.3 m/s.
            T = Transform.from_xyz_yaw([1.0, 2.0, 0.5], math.pi / 2)
            stamp_ns = 1_700_000_000_123_456_000
            pose = ExternalPose(
                stamp_ns, T, pos_std_m=0.1, rot_std_rad=0.2, vel_world_m_s=(0.3, 0.0, 0.0), quality_pct=80
            )
            for _ in range(5):
                await link.send_vision_pose(pose)
                await link.send_vision_pose(pose, ExternalPoseKind.ODOMETRY)
                await asyncio.sleep(0.02)
            assert await asyncio.to_thread(peer.both_poses.wait, 3.0), peer.received.keys()
    vpe = peer.received["VISION_POSITION_ESTIMATE"][-1]
    assert (vpe.x, vpe.y, vpe.z) == pytest.approx((2.0, 1.0, -0.5), abs=1e-6)  # north, east, down
    assert vpe.yaw == pytest.approx(0.0, abs=1e-6)  # facing north
    assert vpe.roll == pytest.approx(0.0, abs=1e-6) and vpe.pitch == pytest.approx(0.0, abs=1e-6)
    assert vpe.usec == stamp_ns // 1000
    assert vpe.covariance[0] == pytest.approx(0.01) and vpe.covariance[15] == pytest.approx(0.04)
    odo = peer.received["ODOMETRY"][-1]
    assert (odo.x, odo.y, odo.z) == pytest.approx((2.0, 1.0, -0.5), abs=1e-6)
    assert list(odo.q) == pytest.approx([1.0, 0.0, 0.0, 0.0], abs=1e-6)  # FRD aligned with NED
    # East is to the right of a north-facing body: FRD velocity (0, 0.3, 0).
    assert (odo.vx, odo.vy, odo.vz) == pytest.approx((0.0, 0.3, 0.0), abs=1e-6)
    assert odo.frame_id == 14 and odo.child_frame_id == 12  # MAV_FRAME_MOCAP_NED, MAV_FRAME_BODY_FRD
    assert odo.quality == 80


# --------------------------------------------------------------------------- PX4 personality


@asynctest
async def test_px4_refused_arming_raises_command_rejected_with_the_reason() -> None:
    # PX4 sends STATUSTEXT only to a link where it heard a GCS: announce ourselves as one (190).
    async with flight(Autopilot.PX4, {"source_component": 190}, ready_after_s=60.0) as (lab, link):
        assert isinstance(link, VehicleLink)
        assert link.info.autopilot is Autopilot.PX4 and link.info.vehicle_type == 2  # MAV_TYPE_QUADROTOR
        # Not ready: no position estimate yet, but heartbeat and landed state flow.
        t = await link.wait_for(lambda t: t.landed_state is LandedState.ON_GROUND, 5.0, "landed state")
        assert t.mode is FlightMode.POSCTL and not t.armed and t.heartbeat_age_s < 2.0
        with pytest.raises(CommandRejected) as info:
            await link.arm()
        assert info.value.command == "arm"
        assert info.value.result == "COMMAND_DENIED"
        assert any("Arming denied" in text for text in info.value.statustext), info.value.statustext
        assert not lab.autopilot.armed and not link.telemetry.armed


@asynctest
async def test_px4_takeoff_hold_offboard_world_and_body_then_land() -> None:
    # The vehicle faces north in the lab, so body "forward" is world +y.
    async with flight(Autopilot.PX4, start_yaw_rad=math.pi / 2) as (lab, link):
        await link.arm()
        await link.takeoff(1.5)
        assert lab.autopilot.param("MIS_TAKEOFF_ALT") == pytest.approx(1.5)
        await link.wait_for(above(1.4), 15.0, "1.4 m after take-off")
        await link.wait_for(lambda t: t.mode is FlightMode.HOLD, 10.0, "Hold after take-off")
        z_hold = [float(lab.T_world_body().translation[2])]
        end = link.clock.monotonic_s() + 2.0
        while link.clock.monotonic_s() < end:  # hold: altitude stays near 1.5 m
            await link.clock.sleep(0.25)
            z_hold.append(float(lab.T_world_body().translation[2]))
        assert min(z_hold) > 1.3 and max(z_hold) < 1.7, z_hold

        await link.start_setpoint_stream()
        await link.set_mode(FlightMode.OFFBOARD)
        assert lab.autopilot.mode is FlightMode.OFFBOARD

        # World frame, east at 1 m/s with a yaw rate of 0: MAVSDK gets it as a body-frame command.
        p0 = lab.T_world_body().translation.copy()
        await feed(link, 2.5, VelocitySetpoint((1.0, 0.0, 0.0), SetpointFrame.WORLD, yaw_rate_rad_s=0.0))
        d = lab.T_world_body().translation - p0
        assert d[0] > 1.5 and abs(d[1]) < 0.2 and abs(d[2]) < 0.2, d

        # Body frame, forward 1 m/s: the vehicle faces north, so it moves north.
        p0 = lab.T_world_body().translation.copy()
        await feed(link, 2.5, VelocitySetpoint((1.0, 0.0, 0.0), SetpointFrame.BODY, yaw_rate_rad_s=0.0))
        d = lab.T_world_body().translation - p0
        assert d[1] > 1.5 and abs(d[0]) < 0.3, d

        # World frame with an absolute yaw: turn to face east (VelocityNedYaw).
        await feed(link, 3.0, VelocitySetpoint((0.0, 0.0, 0.0), SetpointFrame.WORLD, yaw_rad=0.0))
        assert abs(lab.truth().yaw_rad) < 0.15, lab.truth().yaw_rad

        # The caller goes quiet: the stream sends an explicit stop; the vehicle brakes in OFFBOARD.
        link.set_velocity(VelocitySetpoint((1.0, 0.0, 0.0), SetpointFrame.WORLD, yaw_rate_rad_s=0.0))
        await link.clock.sleep(2.0)
        assert np.linalg.norm(lab.truth().vel_enu_m_s) < 0.15
        assert link.telemetry.mode is FlightMode.OFFBOARD

        await link.stop_setpoint_stream()  # MAVSDK leaves offboard: PX4 Hold
        await link.wait_for(lambda t: t.mode is FlightMode.HOLD, 5.0, "Hold after the stream stopped")
        await link.land()
        await link.wait_for(lambda t: t.landed_state is LandedState.ON_GROUND, 20.0, "touch-down")
        await link.disarm()  # PX4 may have auto-disarmed already; either way it ends disarmed
        await link.wait_for(lambda t: not t.armed, 10.0, "disarmed")
        assert lab.T_world_body().translation[2] < 0.05


# --------------------------------------------------------------------------- ArduPilot personality


@asynctest
async def test_ardupilot_guided_takeoff_velocity_and_land() -> None:
    events: list[SimEvent] = []
    async with flight(Autopilot.ARDUPILOT) as (lab, link):
        lab.events.append(events.append)
        assert link.info.autopilot is Autopilot.ARDUPILOT
        await link.set_mode(FlightMode.GUIDED)
        await link.arm()
        await link.takeoff(1.5)  # MAVSDK puts the altitude in NAV_TAKEOFF for ArduPilot
        await link.wait_for(above(1.4), 15.0, "1.4 m after take-off")
        await link.start_setpoint_stream()
        await link.set_mode(FlightMode.OFFBOARD)  # means GUIDED on ArduPilot
        assert link.telemetry.mode is FlightMode.GUIDED
        p0 = lab.T_world_body().translation.copy()
        await feed(link, 2.5, VelocitySetpoint((0.0, -1.0, 0.0), SetpointFrame.WORLD, yaw_rate_rad_s=0.0))
        d = lab.T_world_body().translation - p0
        assert d[1] < -1.5 and abs(d[0]) < 0.2, d
        await link.stop_setpoint_stream()  # MAVSDK offboard.stop(): BRAKE on ArduPilot
        await link.wait_for(lambda t: t.mode is FlightMode.BRAKE, 5.0, "BRAKE after the stream stopped")
        await link.land()
        await link.wait_for(lambda t: not t.armed, 30.0, "ArduPilot to land and disarm by itself")
    assert any(e.kind == "landed" for e in events)

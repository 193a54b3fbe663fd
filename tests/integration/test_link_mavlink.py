"""MavlinkLink over real sockets (and a real pty) against the simulated autopilot.

Every test shares one ``SimClock(speed=10)`` between the simulator and the link, so a
flight of ~30 simulated seconds takes ~3 s; stall-limited, as both run in this process
(docs/sim.md "Time"). Ports are chosen by the OS (port 0).
"""

from __future__ import annotations

import asyncio
import functools
import json
import math
import os
import socket
import threading
import tty
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from contextlib import asynccontextmanager, contextmanager
from dataclasses import replace

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from flightkit.clock import ONE_PROCESS_WALL_STEP_S, SimClock
from flightkit.config import Autopilot, LinkConfig
from flightkit.errors import CommandRejected, EndpointError, LinkError, LinkTimeout
from flightkit.link import open_link
from flightkit.link.base import FlightMode, LandedState, SetpointFrame, VehicleLink, VelocitySetpoint
from flightkit.link.mavlink import MavlinkLink
from flightkit.sim.autopilot import AutopilotOptions, SimAutopilot
from flightkit.sim.personality import personality_for

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(120)]

SPEED = 10.0
KEY = bytes(range(32))


def lab_clock() -> SimClock:
    """The clock a simulator and a link in this process share (stall-limited: docs/sim.md "Time")."""
    return SimClock(SPEED, max_wall_step_s=ONE_PROCESS_WALL_STEP_S)


def asynctest(fn: Callable[..., Awaitable[None]]) -> Callable[..., None]:
    """Run an async test on a fresh event loop (the link's loop; no plugin needed)."""

    @functools.wraps(fn)
    def wrapper(*args: object, **kwargs: object) -> None:
        asyncio.run(fn(*args, **kwargs))  # type: ignore[arg-type]

    return wrapper


@contextmanager
def sim_autopilot(autopilot: Autopilot, clock: SimClock, **options: object) -> Iterator[SimAutopilot]:
    opts = AutopilotOptions(url="udpin:127.0.0.1:0", **options)  # type: ignore[arg-type]
    sim = SimAutopilot(personality_for(autopilot), clock=clock, options=opts)
    sim.start()
    try:
        yield sim
    finally:
        sim.stop()


def link_config(url: str, **kw: object) -> LinkConfig:
    return replace(LinkConfig(url=url, heartbeat_timeout_s=5.0, command_timeout_s=3.0), **kw)  # type: ignore[arg-type]


@asynccontextmanager
async def connected(
    sim: SimAutopilot, autopilot: Autopilot, clock: SimClock, **kw: object
) -> AsyncIterator[MavlinkLink]:
    link = MavlinkLink(link_config(sim.client_url, **kw), autopilot, clock)
    async with link:
        yield link


def above(alt_m: float):  # type: ignore[no-untyped-def]
    return lambda t: t.pos_local_enu_m[2] >= alt_m


async def hold(link: MavlinkLink, seconds: float, vel: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
    """Feed a setpoint every 50 ms of clock time, as a controller would."""
    end = link.clock.monotonic_s() + seconds
    while link.clock.monotonic_s() < end:
        link.set_velocity(VelocitySetpoint(vel, SetpointFrame.WORLD, yaw_rate_rad_s=0.0))
        await link.clock.sleep(0.05)


# --------------------------------------------------------------------------- whole flights


@asynctest
async def test_px4_flight_arm_refused_then_takeoff_hold_land() -> None:
    clock = lab_clock()
    with sim_autopilot(Autopilot.PX4, clock, ready_after_s=3.0, params={"MIS_TAKEOFF_ALT": 1.5}) as sim:
        async with connected(sim, Autopilot.PX4, clock, source_component=190) as link:
            assert isinstance(link, VehicleLink)
            info = link.info
            assert info.autopilot is Autopilot.PX4 and info.system_id == 1 and info.component_id == 1
            await link.wait_for(lambda t: t.mode is FlightMode.POSCTL, 3.0, "POSCTL at boot")

            with pytest.raises(CommandRejected) as refused:  # estimator not converged yet
                await link.arm()
            assert refused.value.result == "TEMPORARILY_REJECTED"
            assert any("Arming denied" in line for line in refused.value.statustext)
            assert not any(line.endswith("\t") for line in link.statustext)  # PX4's tab stripped

            await clock.sleep(3.0)
            await link.arm()
            assert link.telemetry.armed and sim.armed
            await link.takeoff(1.5)
            tel = await link.wait_for(above(1.4), 20.0, "take-off to 1.5 m")
            assert tel.mode is FlightMode.TAKEOFF or tel.mode is FlightMode.HOLD
            await link.wait_for(lambda t: t.landed_state is LandedState.IN_AIR, 5.0, "in air")

            await link.start_setpoint_stream()
            hold_task = asyncio.ensure_future(hold(link, 4.0))
            await link.set_mode(FlightMode.OFFBOARD)
            await hold_task
            tel = link.telemetry
            assert tel.mode is FlightMode.OFFBOARD
            assert 1.2 < tel.pos_local_enu_m[2] < 1.8
            assert math.hypot(*tel.vel_local_enu_m_s[:2]) < 0.3

            await link.land()
            await link.wait_for(lambda t: not t.armed, 30.0, "landed and auto-disarmed")
            assert link.telemetry.pos_local_enu_m[2] < 0.2
            assert link.info.firmware_version.startswith("1.14")
        assert not link.streaming


@asynctest
async def test_ardupilot_flight_guided_refused_then_takeoff_hold_land() -> None:
    clock = lab_clock()
    with sim_autopilot(Autopilot.ARDUPILOT, clock, ready_after_s=3.0) as sim:
        async with connected(sim, Autopilot.ARDUPILOT, clock) as link:
            assert link.info.autopilot is Autopilot.ARDUPILOT
            with pytest.raises(CommandRejected) as refused:  # GUIDED needs a position estimate
                await link.set_mode(FlightMode.GUIDED)
            assert refused.value.statustext, "ArduPilot says why"
            await clock.sleep(3.0)
            await link.set_mode(FlightMode.GUIDED)
            await link.arm()
            await link.takeoff(1.5)
            await link.wait_for(above(1.4), 20.0, "take-off to 1.5 m")

            await link.start_setpoint_stream()
            await hold(link, 3.0)
            tel = link.telemetry
            assert tel.mode is FlightMode.GUIDED and 1.2 < tel.pos_local_enu_m[2] < 1.8

            await link.land()
            await link.wait_for(lambda t: not t.armed, 30.0, "landed and auto-disarmed")
            assert link.telemetry.mode is FlightMode.LAND


@asynctest
async def test_velocity_frames_move_the_vehicle_the_right_way() -> None:
    clock = lab_clock()
    with sim_autopilot(Autopilot.ARDUPILOT, clock, ready_after_s=0.0) as sim:
        async with connected(sim, Autopilot.ARDUPILOT, clock) as link:
            await link.set_mode(FlightMode.GUIDED)
            await link.arm()
            await link.takeoff(1.5)
            await link.wait_for(above(1.4), 20.0, "take-off")
            await link.start_setpoint_stream()
            start = link.telemetry.pos_array
            await hold(link, 2.0, (0.5, 0.0, 0.0))  # world +x (ENU east)
            moved = link.telemetry.pos_array - start
            assert moved[0] > 0.6 and abs(moved[1]) < 0.2 and abs(moved[2]) < 0.2

            # body frame: +y is left of the heading
            yaw = link.telemetry.yaw_local_rad
            start = link.telemetry.pos_array
            end = clock.monotonic_s() + 2.0
            while clock.monotonic_s() < end:
                link.set_velocity(VelocitySetpoint((0.0, 0.5, 0.0), SetpointFrame.BODY, yaw_rate_rad_s=0.0))
                await clock.sleep(0.05)
            moved = link.telemetry.pos_array - start
            left = (-math.sin(yaw), math.cos(yaw))
            assert moved[0] * left[0] + moved[1] * left[1] > 0.6


# --------------------------------------------------------------------------- failsafes


@asynctest
async def test_px4_offboard_loss_explicit_stop_then_failsafe() -> None:
    clock = lab_clock()
    with sim_autopilot(Autopilot.PX4, clock, ready_after_s=0.0, params={"MIS_TAKEOFF_ALT": 1.5}) as sim:
        async with connected(sim, Autopilot.PX4, clock, setpoint_timeout_s=0.5) as link:
            await link.arm()
            await link.takeoff(1.5)
            await link.wait_for(above(1.4), 20.0, "take-off")
            await link.start_setpoint_stream()
            feeder = asyncio.ensure_future(hold(link, 1.5))
            await link.set_mode(FlightMode.OFFBOARD)
            await feeder
            await hold(link, 1.5, (1.0, 0.0, 0.0))
            assert link.telemetry.vel_local_enu_m_s[0] > 0.7

            # The caller goes silent: the link sends explicit stops, PX4 stays in OFFBOARD and brakes.
            stops_before = link.stats.stops_sent
            await clock.sleep(2.5)
            tel = link.telemetry
            assert link.stats.stops_sent > stops_before
            assert tel.mode is FlightMode.OFFBOARD
            assert math.hypot(*tel.vel_local_enu_m_s[:2]) < 0.15

            # The stream ends (as when the program exits): PX4 leaves OFFBOARD after COM_OF_LOSS_T.
            await link.stop_setpoint_stream()
            t0 = clock.monotonic_s()
            tel = await link.wait_for(lambda t: t.mode is not FlightMode.OFFBOARD, 3.0, "PX4 leaving OFFBOARD")
            assert 0.8 < clock.monotonic_s() - t0 < 2.0
            assert tel.mode is FlightMode.POSCTL  # COM_OBL_RC_ACT = 0
            assert tel.armed


@asynctest
async def test_ardupilot_silence_brakes_and_stays_guided() -> None:
    clock = lab_clock()
    with sim_autopilot(Autopilot.ARDUPILOT, clock, ready_after_s=0.0) as sim:
        async with connected(sim, Autopilot.ARDUPILOT, clock, setpoint_timeout_s=0.5) as link:
            await link.set_mode(FlightMode.GUIDED)
            await link.arm()
            await link.takeoff(1.5)
            await link.wait_for(above(1.4), 20.0, "take-off")
            await link.start_setpoint_stream()
            await hold(link, 1.5, (0.0, 1.0, 0.0))
            assert link.telemetry.vel_local_enu_m_s[1] > 0.7
            await clock.sleep(2.0)  # silent caller: explicit stop long before GUID_TIMEOUT (3 s)
            tel = link.telemetry
            assert link.stats.stops_sent > 0
            assert tel.mode is FlightMode.GUIDED and math.hypot(*tel.vel_local_enu_m_s[:2]) < 0.15


@asynctest
async def test_px4_offboard_needs_a_stream() -> None:
    clock = lab_clock()
    with sim_autopilot(Autopilot.PX4, clock, ready_after_s=0.0) as sim:
        async with connected(sim, Autopilot.PX4, clock) as link:
            with pytest.raises(LinkError, match="start_setpoint_stream"):
                await link.set_mode(FlightMode.OFFBOARD)
            with pytest.raises(LinkError, match="px4 has no GUIDED mode"):
                await link.set_mode(FlightMode.GUIDED)
            with pytest.raises(LinkError, match="not running"):
                link.set_velocity(VelocitySetpoint((0.1, 0.0, 0.0)))
            with pytest.raises(LinkError, match="not armed"):
                await link.takeoff(1.5)


# --------------------------------------------------------------------------- link problems


@asynctest
async def test_lost_commands_are_retried_and_a_dead_link_times_out() -> None:
    clock = lab_clock()
    with sim_autopilot(Autopilot.ARDUPILOT, clock, ready_after_s=0.0) as sim:
        async with connected(sim, Autopilot.ARDUPILOT, clock, command_timeout_s=3.0) as link:
            sim.kill_link(1.5)  # the first attempts vanish; a retry gets through
            await link.arm()
            assert sim.armed
            await link.disarm()
            sim.kill_link(10.0)
            t0 = clock.monotonic_s()
            with pytest.raises(LinkTimeout, match=r"no COMMAND_ACK for MAV_CMD_COMPONENT_ARM_DISARM after 3 attempts"):
                await link.arm()
            assert 2.9 < clock.monotonic_s() - t0 < 4.0
            assert not sim.armed


@asynctest
async def test_no_heartbeat_times_out_with_a_useful_message() -> None:
    clock = lab_clock()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as silent:
        silent.bind(("127.0.0.1", 0))  # a port where nobody answers
        port = silent.getsockname()[1]
        link = MavlinkLink(link_config(f"udpout:127.0.0.1:{port}", heartbeat_timeout_s=2.0), Autopilot.PX4, clock)
        with pytest.raises(LinkTimeout) as info:
            await link.connect()
    assert str(info.value) == (
        f"no HEARTBEAT on udpout:127.0.0.1:{port} after 2.0 s; is the autopilot/simulator running and link.url right?"
    )
    assert info.value.what == "HEARTBEAT" and info.value.timeout_s == 2.0
    await link.close()  # idempotent after a failed connect


@pytest.mark.parametrize("scheme", ["udpin", "tcpin"])
@asynctest
async def test_port_in_use(scheme: str) -> None:
    kind = socket.SOCK_DGRAM if scheme == "udpin" else socket.SOCK_STREAM
    with socket.socket(socket.AF_INET, kind) as taken:
        taken.bind(("127.0.0.1", 0))
        if kind == socket.SOCK_STREAM:
            taken.listen(1)
        port = taken.getsockname()[1]
        link = MavlinkLink(link_config(f"{scheme}:127.0.0.1:{port}"), Autopilot.PX4, lab_clock())
        with pytest.raises(EndpointError, match=f"port {port} of {scheme}:127.0.0.1:{port} is already in use"):
            await link.connect()


@asynctest
async def test_the_vehicle_is_picked_by_system_id() -> None:
    clock = lab_clock()
    with sim_autopilot(Autopilot.PX4, clock, ready_after_s=0.0, system_id=3) as sim:
        # the configured system id answers: connected to it
        async with connected(sim, Autopilot.PX4, clock, system_id=3) as link:
            assert link.info.system_id == 3
        # another vehicle answers on this link: the error names the id that did
        wrong = MavlinkLink(link_config(sim.client_url, system_id=2, heartbeat_timeout_s=1.0), Autopilot.PX4, clock)
        with pytest.raises(LinkTimeout, match="no HEARTBEAT from system 2 .* system id 3 answered; set link.system_id"):
            await wrong.connect()
        await wrong.close()


@asynctest
async def test_signing() -> None:
    clock = lab_clock()
    with sim_autopilot(Autopilot.ARDUPILOT, clock, ready_after_s=0.0, signing_key=KEY) as sim:
        # Right key: everything works.
        async with connected(sim, Autopilot.ARDUPILOT, clock, signing_key_hex=KEY.hex()) as link:
            await link.arm()
            await link.disarm()
            assert link.stats.packets_rejected == 0
        assert not sim.armed
        # Wrong key: the autopilot's packets are dropped, and the error says why.
        bad = MavlinkLink(
            link_config(sim.client_url, signing_key_hex=bytes(32).hex(), heartbeat_timeout_s=1.5),
            Autopilot.ARDUPILOT,
            clock,
        )
        with pytest.raises(LinkTimeout, match="dropped for a missing or wrong signature"):
            await bad.connect()
        # No key: we hear the (signed) heartbeats, but the autopilot ignores our unsigned commands.
        rejected_before = sim.rejected_messages
        async with connected(sim, Autopilot.ARDUPILOT, clock, command_timeout_s=1.5) as unsigned:
            with pytest.raises(LinkTimeout, match="no COMMAND_ACK"):
                await unsigned.arm()
        assert sim.rejected_messages > rejected_before and not sim.armed


@asynctest
async def test_serial_link_over_a_pty() -> None:
    """A serial endpoint (real pty): heartbeats both ways and STATUSTEXT decoding."""
    master, slave = os.openpty()
    tty.setraw(slave)  # no echo or line editing before pyserial configures the port
    path = os.ttyname(slave)
    ap = mavlink2.MAVLink(None, 1, 1)
    stop = threading.Event()
    heard = []

    def autopilot() -> None:
        rx = mavlink2.MAVLink(None, 1, 1)
        rx.robust_parsing = True
        os.set_blocking(master, False)
        while not stop.is_set():
            os.write(master, bytes(mavlink2.MAVLink_heartbeat_message(2, 12, 1 | 128, 393216, 4, 3).pack(ap)))
            os.write(master, bytes(mavlink2.MAVLink_statustext_message(6, b"Hello from serial\t").pack(ap)))
            try:
                heard.extend(rx.parse_buffer(os.read(master, 4096)) or [])
            except BlockingIOError:
                pass
            stop.wait(0.02)

    thread = threading.Thread(target=autopilot, daemon=True)
    thread.start()
    try:
        link = MavlinkLink(link_config(f"serial:{path}:921600"), Autopilot.PX4, lab_clock())
        async with link:
            tel = await link.wait_for(lambda t: t.mode is FlightMode.OFFBOARD, 2.0, "OFFBOARD heartbeat")
            assert tel.armed
            await link.wait_for(lambda t: "Hello from serial" in link.statustext, 2.0, "status text")
            await link.clock.sleep(2.0)
    finally:
        stop.set()
        thread.join()
        os.close(master)
        os.close(slave)
    ours = [m for m in heard if m.get_type() == "HEARTBEAT"]
    assert ours and ours[0].type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER and ours[0].get_srcComponent() == 191


@asynctest
async def test_external_pose_and_ekf_origin_reach_the_autopilot() -> None:
    from flightkit.frames import Transform
    from flightkit.link.base import ExternalPose, ExternalPoseKind

    clock = lab_clock()
    events: list[tuple[str, str]] = []
    opts = AutopilotOptions(url="udpin:127.0.0.1:0", ready_after_s=0.0, params={"EKF2_EV_CTRL": 15})
    sim = SimAutopilot(
        personality_for(Autopilot.PX4), clock=clock, options=opts, on_event=lambda k, d: events.append((k, d))
    )
    with sim:
        async with connected(sim, Autopilot.PX4, clock, source_component=190) as link:
            await link.set_ekf_origin(47.397742, 8.545594, 488.0)
            truth = sim.truth()
            for i in range(40):
                T = Transform.from_xyz_yaw(truth.pos_enu_m, truth.yaw_rad)
                kind = ExternalPoseKind.ODOMETRY if i % 2 else ExternalPoseKind.VISION_POSITION_ESTIMATE
                await link.send_vision_pose(ExternalPose(clock.time_ns(), T), kind)
                await clock.sleep(0.025)
            await link.wait_for(lambda t: "EKF2 starting vision fusion" in link.statustext, 3.0, "vision fusion")
    assert ("vision", "fusing") in events


@asynctest
async def test_open_link_and_cli_status(capsys: pytest.CaptureFixture[str]) -> None:
    from flightkit.cli.main import main

    clock = lab_clock()
    with sim_autopilot(Autopilot.ARDUPILOT, clock, ready_after_s=0.0) as sim:
        link = open_link(link_config(sim.client_url), Autopilot.ARDUPILOT, clock)
        assert isinstance(link, MavlinkLink)
        # The CLI runs its own event loop on wall time; run it in a thread from this loop.
        code = await asyncio.to_thread(
            main, ["vehicle", "status", "--connect", sim.client_url, "--json", "--listen", "1"]
        )
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert report["autopilot"] == "ardupilot" and report["armed"] is False
    assert report["mode"] == "STABILIZED" and report["system_id"] == 1
    assert report["position_enu_m"] is not None and report["battery_voltage_v"] > 10


def test_cli_status_without_an_autopilot(capsys: pytest.CaptureFixture[str]) -> None:
    from flightkit.cli.main import main

    code = main(["vehicle", "status", "--connect", "udpin:127.0.0.1:0", "--timeout", "0.3"])
    assert code == 1
    err = capsys.readouterr().err
    assert "no HEARTBEAT on udpin:127.0.0.1:0 (local port" in err and "after 0.3 s" in err

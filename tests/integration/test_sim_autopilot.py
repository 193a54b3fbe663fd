"""The simulated autopilot on the wire, as seen by raw pymavlink clients over real UDP: endpoints,
identity, commands, parameters, streams and signing (flight behaviour: test_sim_autopilot_flight.py).

Time runs on ``SimClock(speed=...)``; every wait is on a received message or a state, with a
timeout; timing figures are measured in simulated time (``lab.clock.monotonic_s()``).
"""

from __future__ import annotations

import socket
from collections.abc import Callable

import pytest
from pymavlink import mavutil

from flightkit.clock import SimClock
from flightkit.errors import EndpointError
from flightkit.sim.autopilot import AutopilotOptions
from flightkit.sim.lab import SimLab
from tests.integration.sim_gcs import (
    PX4_POSCTL,
    SPEED,
    Client,
    mav,
    new_client,
)

# ---------------------------------------------------------------- endpoint and identity


def test_port_in_use_is_an_endpoint_error(make_lab: Callable[..., SimLab]) -> None:
    lab = make_lab()
    other = SimLab(autopilot="px4", url=f"udpin:127.0.0.1:{lab.port}", clock=SimClock(SPEED))
    with pytest.raises(EndpointError, match=f"127.0.0.1:{lab.port}.*in use|port"):
        other.start()


def test_heartbeat_identity_px4(make_lab: Callable[..., SimLab], clients: list[Client]) -> None:
    lab = make_lab("px4")
    c = new_client(clients, lab)
    hb = c.wait_heartbeat(lambda m: True)
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 1)
    assert hb.autopilot == mav.MAV_AUTOPILOT_PX4
    assert hb.type == mav.MAV_TYPE_QUADROTOR
    assert hb.base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.custom_mode == PX4_POSCTL
    assert hb.system_status == mav.MAV_STATE_STANDBY
    assert c.conn.WIRE_PROTOCOL_VERSION == "2.0" or hb.get_msgbuf()[0] == 0xFD


def test_heartbeat_identity_ardupilot(make_lab: Callable[..., SimLab], clients: list[Client]) -> None:
    lab = make_lab("ardupilot")
    c = new_client(clients, lab)
    hb = c.wait_heartbeat(lambda m: True)
    assert hb.autopilot == mav.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert hb.custom_mode == 0  # STABILIZE
    assert hb.get_msgbuf()[0] == 0xFD  # MAVLink 2


def test_two_clients_are_both_served(make_lab: Callable[..., SimLab], clients: list[Client]) -> None:
    lab = make_lab("px4")
    a, b = new_client(clients, lab), new_client(clients, lab)
    assert a.wait_heartbeat(lambda m: True) and b.wait_heartbeat(lambda m: True)
    assert a.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    # the other client sees the state change too
    b.wait_heartbeat(lambda m: m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)


def test_udpout_sends_to_a_listening_client() -> None:
    listener = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255, source_component=190)
    port = listener.port.getsockname()[1]
    lab = SimLab(autopilot="px4", url=f"udpout:127.0.0.1:{port}", clock=SimClock(SPEED), ready_after_s=0.0)
    with lab:
        hb = listener.recv_match(type="HEARTBEAT", blocking=True, timeout=3.0)
        assert hb is not None and hb.autopilot == mav.MAV_AUTOPILOT_PX4
        # and it answers what we send back
        listener.mav.command_long_send(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        ack = listener.recv_match(type="COMMAND_ACK", blocking=True, timeout=3.0)
        assert ack is not None and ack.result == mav.MAV_RESULT_ACCEPTED
    listener.close()


# ---------------------------------------------------------------- commands, params, streams


def test_unknown_command_is_unsupported(make_lab: Callable[..., SimLab], clients: list[Client]) -> None:
    c = new_client(clients, make_lab("px4"))
    assert c.command(mav.MAV_CMD_DO_SET_SERVO, 1, 1500) == mav.MAV_RESULT_UNSUPPORTED
    assert c.command(31337) == mav.MAV_RESULT_UNSUPPORTED


def test_request_autopilot_version(make_lab: Callable[..., SimLab], clients: list[Client]) -> None:
    c = new_client(clients, make_lab("px4"))
    assert c.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == mav.MAV_RESULT_ACCEPTED
    ver = c.recv("AUTOPILOT_VERSION")
    for cap in (
        mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2,
        mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED,
        mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT,
        mav.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE,
    ):
        assert ver.capabilities & cap
    assert (ver.flight_sw_version >> 24, (ver.flight_sw_version >> 16) & 0xFF) == (1, 14)


def test_message_interval_changes_rate(make_lab: Callable[..., SimLab], clients: list[Client]) -> None:
    lab = make_lab("px4")
    c = new_client(clients, lab)
    msg_id = mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED
    assert c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 200_000) == mav.MAV_RESULT_ACCEPTED  # 5 Hz
    first = c.recv("LOCAL_POSITION_NED")
    t0 = first.time_boot_ms
    n = 0
    while True:
        m = c.recv("LOCAL_POSITION_NED")
        n += 1
        if m.time_boot_ms - t0 >= 4000:
            break
    rate = n / ((m.time_boot_ms - t0) / 1000.0)
    assert 4.0 <= rate <= 6.0, rate
    assert c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, -1) == mav.MAV_RESULT_ACCEPTED
    c.recv("HEARTBEAT")
    with pytest.raises(AssertionError):
        c.recv("LOCAL_POSITION_NED", timeout_s=0.6)  # 6 s of sim time without one


def test_params_read_set_and_bytewise_ints(make_lab: Callable[..., SimLab], clients: list[Client]) -> None:
    lab = make_lab("px4")
    c = new_client(clients, lab)
    c.conn.mav.param_request_read_send(1, 1, b"COM_OF_LOSS_T", -1)
    pv = c.recv("PARAM_VALUE", lambda m: m.param_id == "COM_OF_LOSS_T")
    assert pv.param_value == pytest.approx(1.0)
    import struct

    wire = struct.unpack("<f", struct.pack("<i", 5))[0]  # PX4 sends INT32 bytewise
    c.conn.mav.param_set_send(1, 1, b"COM_OBL_RC_ACT", wire, mav.MAV_PARAM_TYPE_INT32)
    pv = c.recv("PARAM_VALUE", lambda m: m.param_id == "COM_OBL_RC_ACT")
    assert struct.unpack("<i", struct.pack("<f", pv.param_value))[0] == 5
    assert lab.autopilot.param("COM_OBL_RC_ACT") == 5
    c.conn.mav.param_request_list_send(1, 1)
    names = {c.recv("PARAM_VALUE").param_id for _ in range(len(lab.personality.params))}
    assert {"COM_OF_LOSS_T", "COM_OBL_RC_ACT", "MIS_TAKEOFF_ALT", "EKF2_EV_CTRL"} <= names


def test_timesync_is_answered(make_lab: Callable[..., SimLab], clients: list[Client]) -> None:
    c = new_client(clients, make_lab("px4"))
    c.conn.mav.timesync_send(0, 123456789)
    ts = c.recv("TIMESYNC", lambda m: m.ts1 == 123456789)
    assert ts.tc1 > 0


# ---------------------------------------------------------------- signing


def test_signing_ignores_unsigned_and_signs_outgoing(make_lab: Callable[..., SimLab], clients: list[Client]) -> None:
    key = bytes(range(32))
    lab = make_lab("px4", options=AutopilotOptions(signing_key=key))
    unsigned = new_client(clients, lab)
    # outgoing traffic is signed: an unsigned client can still parse it, and the frame carries a signature
    hb = unsigned.wait_heartbeat(lambda m: True)
    assert hb.get_msgbuf()[2] & mav.MAVLINK_IFLAG_SIGNED
    with pytest.raises(AssertionError):
        unsigned.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1, timeout_s=0.5)
    wrong = new_client(clients, lab, key=bytes(32))
    with pytest.raises(AssertionError):
        wrong.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1, timeout_s=0.5)
    assert not lab.autopilot.armed
    assert lab.autopilot.rejected_messages >= 2
    signed = new_client(clients, lab, key=key)
    assert signed.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    assert lab.autopilot.armed



def test_no_fixed_ports_left_bound(make_lab: Callable[..., SimLab]) -> None:
    lab = make_lab()
    port = lab.port
    lab.stop()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", port))  # the port is free again after stop()
        assert s.getsockname()[1] == port

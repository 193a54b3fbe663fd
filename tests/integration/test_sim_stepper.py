"""One stepper thread ticks every autopilot of a simulated fleet; each vehicle's flight stays its own."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from pymavlink import mavutil

from flightkit.clock import ONE_PROCESS_WALL_STEP_S, SimClock
from flightkit.config import LabConfig
from flightkit.errors import SimError
from flightkit.sim.fleet import SimFleet, fleet_lab_config
from flightkit.sim.stepper import SimStepper

mav = mavutil.mavlink
HOME_AMSL_M = 488.0  # AutopilotOptions.origin_alt_m


def test_one_stepper_flies_one_vehicle_and_leaves_the_other_on_the_ground() -> None:
    clock = SimClock(10.0, max_wall_step_s=ONE_PROCESS_WALL_STEP_S)
    fleet = SimFleet(fleet_lab_config(LabConfig(), 2), clock=clock, ready_after_s=0.0).start()
    conn = None
    try:
        assert fleet.stepper is not None
        loops = [t.name for t in threading.enumerate() if t.name in ("sim-autopilot-loop", "sim-stepper")]
        assert loops.count("sim-stepper") >= 1 and "sim-autopilot-loop" not in loops
        flyer, sitter = fleet.labs["uav1"], fleet.labs["uav2"]
        start2 = sitter.truth().pos_enu_m.copy()
        conn = mavutil.mavlink_connection(flyer.client_url, source_system=255, source_component=190)

        def command(cmd: int, *params: float) -> int:
            assert conn is not None
            p = [*params] + [0.0] * (7 - len(params))
            conn.mav.command_long_send(1, 1, cmd, 0, *p)
            ack = conn.recv_match(type="COMMAND_ACK", condition=f"COMMAND_ACK.command=={cmd}", blocking=True,
                                  timeout=5.0)
            assert ack is not None, f"no COMMAND_ACK for {cmd}"
            return int(ack.result)

        assert command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
        nan = float("nan")
        assert command(mav.MAV_CMD_NAV_TAKEOFF, nan, 0, 0, nan, nan, nan, HOME_AMSL_M + 3.0) == mav.MAV_RESULT_ACCEPTED
        flyer.wait_until(lambda: flyer.truth().pos_enu_m[2] > 2.0, timeout_s=20.0, what="uav1 above 2 m")
        rounds = fleet.stepper.rounds
        flyer.wait_until(lambda: fleet.stepper is not None and fleet.stepper.rounds > rounds + 5, timeout_s=2.0,
                         what="more stepper rounds")
        # the other vehicle was ticked all along (its physics time kept up) and did not move or arm
        assert sitter.truth().time_s == pytest.approx(flyer.truth().time_s, abs=0.3)
        assert sitter.truth().time_s > 1.0
        np.testing.assert_array_equal(sitter.truth().pos_enu_m, start2)
        assert flyer.autopilot.armed and not sitter.autopilot.armed
    finally:
        if conn is not None:
            conn.close()
        fleet.stop()
    assert fleet.stepper is None


def test_a_stepper_needs_autopilots_on_its_own_clock() -> None:
    fleet = SimFleet(fleet_lab_config(LabConfig(), 1), clock=SimClock(5.0), ready_after_s=0.0)
    with pytest.raises(SimError, match="at least one autopilot"):
        SimStepper(fleet.clock, [])
    with pytest.raises(SimError, match="stepper's clock"):
        SimStepper(SimClock(5.0), [fleet.labs["uav1"].autopilot])

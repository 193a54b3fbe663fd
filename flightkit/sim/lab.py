"""The simulated lab: clock, vehicle dynamics and autopilot, behind the real interfaces.

:class:`SimLab` owns one :class:`~flightkit.clock.Clock`, one
:class:`~flightkit.sim.dynamics.QuadDynamics` and one
:class:`~flightkit.sim.autopilot.SimAutopilot` on a real UDP port. Flight code connects to
it exactly as to PX4 or ArduPilot SITL (``lab.client_url``); the mocap publisher and the
camera renderer read the ground truth from :meth:`SimLab.T_world_body`; tests and demos
inject faults (:meth:`SimLab.inject_gust`, :meth:`SimLab.kill_link`) and watch events.

Example::

    with SimLab(autopilot="px4", clock=SimClock(speed=10)) as lab:
        print("connect to", lab.client_url)
        lab.wait_until(lambda: lab.autopilot.armed, timeout_s=30.0, what="armed")
"""
from __future__ import annotations

import logging
import math
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy.typing as npt

from flightkit.clock import ONE_PROCESS_WALL_STEP_S, Clock, SimClock
from flightkit.config import Autopilot, LabConfig
from flightkit.errors import LinkTimeout
from flightkit.frames import Transform
from flightkit.lifetime import Running
from flightkit.sim.autopilot import AutopilotOptions, SimAutopilot
from flightkit.sim.autopilot.server import MAX_TICK_S
from flightkit.sim.dynamics import DynamicsParams, DynamicsState, QuadDynamics
from flightkit.sim.personality import Personality, personality_for

__all__ = ["SimEvent", "SimLab"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class SimEvent:
    """Something that happened in the simulated lab.

    Attributes:
        stamp_s: clock time (``Clock.monotonic_s``).
        kind: ``armed``, ``disarmed``, ``mode``, ``takeoff``, ``airborne``, ``landed``,
            ``failsafe``, ``arm_refused``, ``mode_refused``, ``param``, ``vision``,
            ``link_killed``, ``gust``.
        detail: human-readable detail, e.g. ``"POSCTL -> OFFBOARD (command)"``.
    """

    stamp_s: float
    kind: str
    detail: str = ""


class SimLab(Running):
    """A simulated vehicle with its autopilot, on a clock.

    Args:
        config: lab config; ``vehicle.autopilot`` picks the personality and ``sim`` the
            speed and dynamics (defaults when None).
        autopilot: overrides ``config.vehicle.autopilot`` (``"px4"``/``"ardupilot"``).
        url: where the autopilot listens / sends (default ``udpin:127.0.0.1:14540``);
            ``udpin:127.0.0.1:0`` picks a free port (see :attr:`client_url`).
        clock: defaults to ``SimClock(config.sim.speed)``.
        options: full autopilot options (``url`` and ``heading_offset_rad`` arguments win).
        dynamics_params: overrides the dynamics built from config and personality.
        start_pos_enu_m, start_yaw_rad: where the vehicle stands in the world at start.
        heading_offset_rad: rotation of the autopilot's local frame about world z.
        ready_after_s: estimator convergence time (0 for tests); None keeps the options'.
    """

    def __init__(
        self,
        config: LabConfig | None = None,
        *,
        autopilot: Autopilot | str | None = None,
        url: str | None = None,
        clock: Clock | None = None,
        options: AutopilotOptions | None = None,
        dynamics_params: DynamicsParams | None = None,
        start_pos_enu_m: npt.ArrayLike = (0.0, 0.0, 0.0),
        start_yaw_rad: float = 0.0,
        heading_offset_rad: float | None = None,
        ready_after_s: float | None = None,
    ) -> None:
        self.config = config or LabConfig()
        self.personality: Personality = personality_for(autopilot or self.config.vehicle.autopilot)
        self.clock: Clock = clock or SimClock(self.config.sim.speed, max_wall_step_s=ONE_PROCESS_WALL_STEP_S)
        sim = self.config.sim
        params = dynamics_params or DynamicsParams(
            velocity_time_constant_s=sim.velocity_time_constant_s,
            max_accel_m_s2=sim.max_accel_m_s2,
            wind_gust_m_s=sim.wind_gust_m_s,
            spinup_s=self.personality.spinup_s,
            thrust_ramp_s=self.personality.thrust_ramp_s,
            accel_time_constant_s=self.personality.accel_time_constant_s,
        )
        self.dynamics = QuadDynamics(params, start_pos_enu_m, start_yaw_rad)
        opts = options or AutopilotOptions()
        if opts.battery_endurance_s is None and sim.battery_endurance_s > 0.0:
            opts = replace(opts, battery_endurance_s=sim.battery_endurance_s)
        if url is not None:
            opts = replace(opts, url=url)
        if heading_offset_rad is not None:
            opts = replace(opts, heading_offset_rad=heading_offset_rad)
        if ready_after_s is not None:
            opts = replace(opts, ready_after_s=ready_after_s)
        # a lab sets its vehicle up as docs/hardware.md says; [sim.autopilot_params] and the
        # options' own params override that
        opts = replace(
            opts, params={**self.personality.lab_params, **sim.autopilot_params, **opts.params}
        )
        self.events: list[Callable[[SimEvent], None]] = []
        """Hooks called with every :class:`SimEvent` (from simulator threads; keep them quick)."""
        self.event_log: deque[SimEvent] = deque(maxlen=1000)
        self._cond = threading.Condition()
        self.autopilot = SimAutopilot(
            self.personality, self.dynamics, self.clock, opts, on_event=self._on_event
        )
        self._started = False

    # ------------------------------------------------------------------ lifecycle

    def start(self, *, own_loop: bool = True) -> SimLab:
        """Bind the autopilot's socket and start simulating; returns immediately. With
        ``own_loop=False`` the caller ticks the autopilot (:class:`~flightkit.sim.stepper.SimStepper`).

        Raises:
            EndpointError: the autopilot's port is in use.
        """
        if not self._started:
            self.autopilot.start(own_loop=own_loop)
            self._started = True
        return self

    def stop(self) -> None:
        """Stop simulating and close the socket; idempotent."""
        if self._started:
            self.autopilot.stop()
            self._started = False

    # ------------------------------------------------------------------ endpoints

    @property
    def url(self) -> str:
        """The autopilot's own endpoint (port 0 resolved)."""
        return self.autopilot.url

    @property
    def client_url(self) -> str:
        """The connection string a pymavlink client uses, e.g. ``udpout:127.0.0.1:40123``."""
        return self.autopilot.client_url

    @property
    def port(self) -> int:
        return self.autopilot.bound_address[1]

    # ------------------------------------------------------------------ truth

    def truth(self) -> DynamicsState:
        """The true vehicle state in the world frame."""
        return self.autopilot.truth()

    def T_world_body(self, now_s: float | None = None) -> Transform:
        """Ground-truth body pose in the world at clock time ``now_s`` (default: now).

        The physics runs in ticks; between ticks the pose is extrapolated with the current
        velocity, so a 120 Hz mocap stream sees smooth motion at any sim speed. The
        extrapolation stops where the next tick's step does (``MAX_TICK_S``): after a stall of
        the physics thread the vehicle seems to pause, never to jump (with a shorter cap the
        pose froze early and the tick's catch-up then moved it by more than one sample's worth).
        """
        state, stamp = self.autopilot.truth_stamped()
        now = self.clock.monotonic_s() if now_s is None else now_s
        return state.T_world_body(max(0.0, min(MAX_TICK_S, now - stamp)))

    # ------------------------------------------------------------------ faults

    def inject_gust(self, peak_enu_m_s: npt.ArrayLike, duration_s: float = 2.0) -> None:
        """A wind gust (world ENU, m/s at its peak) starting now."""
        self.autopilot.inject_gust(peak_enu_m_s, duration_s)
        self._on_event("gust", f"{list(peak_enu_m_s)!r} m/s for {duration_s:g} s")  # type: ignore[arg-type]

    def kill_link(self, duration_s: float) -> None:
        """Drop all MAVLink traffic both ways for ``duration_s`` of sim time."""
        self.autopilot.kill_link(duration_s)

    def set_battery_remaining(self, fraction: float | None) -> None:
        """Force the battery charge (0-1), e.g. to trigger a supervisor's low-battery rule."""
        self.autopilot.set_battery_remaining(fraction)

    # ------------------------------------------------------------------ events

    def _on_event(self, kind: str, detail: str) -> None:
        event = SimEvent(self.clock.monotonic_s(), kind, detail)
        with self._cond:
            self.event_log.append(event)
            self._cond.notify_all()
        for hook in list(self.events):
            try:
                hook(event)
            except Exception:
                logger.exception("SimLab event hook %r failed", hook)

    def wait_until(self, predicate: Callable[[], bool], timeout_s: float, what: str) -> None:
        """Block until ``predicate()`` is true; ``timeout_s`` is in this lab's clock time.

        Raises:
            LinkTimeout: not true within ``timeout_s``.
        """
        deadline = self.clock.monotonic_s() + timeout_s
        step = 0.02 * (self.clock.speed if math.isfinite(self.clock.speed) else 1.0)
        while not predicate():
            if self.clock.monotonic_s() >= deadline:
                raise LinkTimeout(
                    f"simulated lab: {what} not reached within {timeout_s:g} s (sim time)", what, timeout_s
                )
            self.clock.sleep_blocking(step)

    def __repr__(self) -> str:
        state = f"on {self.url}" if self._started else "stopped"
        return f"SimLab({self.personality.autopilot.value}, {self.clock!r}, {state})"

"""Flying a whole plan in one call: :func:`fly_plan` (the CLI and ``make demo`` use it).

Preflight, arm (or wait for the pilot), take off, hold, the pattern, hold, land, with the
:class:`~trajectories.runner.FlightRunner` on the lab's link and mocap source (opened here
unless given), a flight log, and a summary whatever happens.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

from flightkit.clock import Clock, WallClock
from flightkit.config import LabConfig
from flightkit.errors import MocapError, SafetyAbort
from flightkit.link.base import VehicleLink
from flightkit.mocap.base import MocapSource
from trajectories.base import Pattern
from trajectories.flightlog import FlightLog, FlightSummary
from trajectories.plan import Plan
from trajectories.runner import FlightRunner, pattern_in_fence
from trajectories.status import Status

__all__ = ["fly_plan", "open_lab_mocap"]

logger = logging.getLogger(__name__)


async def fly_plan(
    plan: Plan,
    lab: LabConfig,
    *,
    link: VehicleLink | None = None,
    mocap: MocapSource | None = None,
    clock: Clock | None = None,
    arm: bool = False,
    log_path: str | Path | None = None,
    on_status: Callable[[Status], None] | None = None,
    handle_signals: bool = False,
) -> FlightSummary:
    """Fly a whole plan: preflight, arm (or wait for the pilot), take off, hold, pattern, hold, land.

    Opens the link (``lab.link``) and mocap source (``lab.mocap``) unless given. Blocks until
    the flight ends; a fault does not raise but ends the flight (after the safety reaction)
    and shows in the summary's ``outcome`` and ``faults``.

    Args:
        log_path: flight log file; None writes ``<log_dir>/<plan>-<time>.csv``; "" disables it.
        handle_signals: make SIGINT/SIGTERM land the vehicle (CLI use).

    Raises:
        MocapBodyMissing: the body is not visible at start (names the visible ones).
        SafetyAbort: a preflight check failed (reason "preflight").
        LinkError, ConfigError: as raised by the link and the plan.
    """
    clock = clock or WallClock()
    plan = plan.with_lab_defaults(lab)
    pattern = plan.build_pattern()
    async with contextlib.AsyncExitStack() as stack:
        if link is None:
            from flightkit.link import open_link

            link = await stack.enter_async_context(open_link(lab.link, lab.vehicle.autopilot, clock))
        if mocap is None:
            mocap = await stack.enter_async_context(open_lab_mocap(lab, clock))
        assert link is not None and mocap is not None
        log = None
        if log_path != "":
            path = Path(log_path) if log_path else _default_log_path(plan)
            log = FlightLog(
                path,
                {
                    "plan": plan.name,
                    "source": plan.source_path,
                    "pattern": plan.pattern.__class__.__name__,
                    "controller": _jsonable(plan.controller),
                    "autopilot": lab.vehicle.autopilot.value,
                    "body": lab.mocap.body,
                },
            )
        runner = FlightRunner(
            link,
            mocap,
            body=lab.mocap.body,
            clock=clock,
            settings=plan.settings,
            controller=plan.controller,
            safety=plan.safety,
            log=log,
            on_status=on_status,
            name=plan.name,
            predict_latency_s=lab.mocap.predict_latency_ms / 1000.0,
        )
        sig_ctx = runner.signals_land() if handle_signals else contextlib.nullcontext()
        try:
            with sig_ctx:
                await _fly_sequence(runner, plan, pattern, arm)
        except SafetyAbort as exc:
            if exc.reason == "preflight":
                raise
            logger.warning("flight ended early: %s", exc)
        finally:
            summary = runner.finish()
            await runner.close()
            if log is not None:
                log.close(summary)
        return summary
    raise AssertionError("unreachable")  # pragma: no cover


async def _fly_sequence(runner: FlightRunner, plan: Plan, pattern: Pattern, arm: bool) -> None:
    s = plan.settings
    if plan.safety.check_plan_in_fence:
        bad = pattern_in_fence(pattern, plan.safety)
        if bad is not None:
            raise SafetyAbort(
                "preflight",
                f"preflight failed: the {pattern.name} leaves the geofence "
                f"{plan.safety.geofence.describe()} at t={bad.t_s:.1f} s; shrink it or move the fence",
            )
    await runner.preflight()
    await runner.start(arm)
    try:
        await runner.takeoff(s.takeoff_height_m)
        await runner.hold(s.hold_before_s)
        await runner.fly(pattern)
        await runner.hold(s.hold_after_s)
        await runner.land()
    except (asyncio.CancelledError, KeyboardInterrupt):
        if runner.airborne and not runner.ended:
            runner.interrupt()
            with contextlib.suppress(SafetyAbort):  # the landing reports "interrupted"; the caller cancelled
                await asyncio.shield(runner.land())
        raise


def open_lab_mocap(lab: LabConfig, clock: Clock) -> MocapSource:
    """The mocap source ``lab.mocap`` names, not yet started (enter it with ``async with``).

    Uses :func:`flightkit.mocap.open_mocap` (bus or motioncapture, per ``lab.mocap.source``)
    with the vehicle's bus namespace (``lab.vehicle.namespace``).

    Raises:
        MocapError: no mocap backend is available; pass a source (e.g. a
            :class:`~flightkit.sim.mocap.SimMocapSource`) instead.
    """
    import flightkit.mocap as mocap_pkg

    opener = getattr(mocap_pkg, "open_mocap", None)
    if opener is None:
        raise MocapError(
            f"no mocap backend for mocap.source = {lab.mocap.source.value!r} is available in this install; "
            "pass a MocapSource (mocap=...) or fly the simulator with --connect sim"
        )
    from flightkit.bus.keys import Keys

    return cast(MocapSource, opener(lab.mocap, lab.bus, Keys(lab.vehicle.namespace), clock))


def _default_log_path(plan: Plan) -> Path:
    folder = Path(plan.settings.log_dir or "flightlogs")
    return folder / f"{plan.name}-{time.strftime('%Y%m%d-%H%M%S')}.csv"


def _jsonable(obj: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        out[f.name] = v.value if hasattr(v, "value") else v
    return out

"""Pose reporting jobs: report recorded or live poses to a mapping server, or run the server.

``flightkit report`` and ``flightkit mapserver`` call these. Every pose reported is in the world
frame: recordings and bus streams are placed there by the frame each pose names.
"""

from __future__ import annotations

import asyncio
import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from estimation.report.link_session import SessionStats
from estimation.report.mapserver import MapServer, parse_orders
from estimation.report.reporter import (
    PoseSample,
    Reporter,
    ReporterConfig,
    bus_pose_samples,
    mocap_samples,
    read_mcap_samples,
    read_tum_samples,
    replay_samples,
)
from flightkit.bus.keys import Keys
from flightkit.clock import Clock, WallClock
from flightkit.config import LabConfig, MocapSourceKind
from flightkit.errors import ConfigError
from flightkit.frames import WorldFrames
from flightkit.settings import load_section, load_toml

__all__ = ["MapServer", "ReportOutcome", "ReporterConfig", "parse_orders", "report_poses", "reporter_config"]


def reporter_config(config_path: str | None, overrides: Mapping[str, Any]) -> ReporterConfig:
    """The ``[report]`` table of ``config_path`` (defaults without one) with ``overrides``
    (``port``, ``baud``, ``rate_hz``, ``robot_id``, ``name``; None values are ignored).

    Raises:
        ConfigError: no port, or a value out of range.
    """
    cfg = ReporterConfig()
    if config_path:
        table = load_toml(config_path).get("report", {})
        cfg = load_section(ReporterConfig, table, path=config_path, prefix="report")
    cfg = dataclasses.replace(cfg, **{k: v for k, v in overrides.items() if v is not None})
    where = config_path or "<command line>"
    if not cfg.port:
        raise ConfigError(where, "report.port", "no serial port given", "pass --port PORT")
    if not 1 <= cfg.robot_id <= 254:
        raise ConfigError(where, "report.robot_id", f"{cfg.robot_id} is out of range", "use 1..254")
    if not cfg.rate_hz > 0:
        raise ConfigError(where, "report.rate_hz", f"{cfg.rate_hz} is not positive", "pass --rate 20")
    return cfg


@dataclass(frozen=True, slots=True)
class ReportOutcome:
    """What a report run did: poses offered, the server's name, the session's counters."""

    offered: int
    server: str
    stats: SessionStats


def _file_samples(path: Path, topic: str | None, lab: LabConfig | None) -> list[PoseSample]:
    if not path.exists():
        raise ConfigError("<command line>", "--source", f"{str(path)!r} is not bus, mocap or a file", "check the path")
    if path.suffix == ".mcap":
        return read_mcap_samples(path, topic)
    return read_tum_samples(path)


async def report_poses(
    cfg: ReporterConfig,
    source: str,
    lab: LabConfig,
    *,
    topic: str | None = None,
    speed: float = 1.0,
    duration_s: float | None = None,
    clock: Clock | None = None,
) -> ReportOutcome:
    """Report poses to the mapping server on ``cfg.port`` until the source ends or ``duration_s``.

    Args:
        source: ``mocap`` (the lab's mocap source, ``[mocap]``), ``bus`` (a PoseStamped stream on
            the bus: ``topic`` as a key, else the mocap poses on the bus), or a ``.tum``/``.txt``
            /``.mcap`` file replayed at ``speed``.
        topic: the PoseStamped topic of an MCAP file (default: the only one), or the bus key.

    Raises:
        ConfigError: a missing file. ProtocolError: no server answered. FrameError: a pose in a
            frame that cannot be placed in the world.
    """
    clk = clock or WallClock()
    samples = [] if source in ("bus", "mocap") else _file_samples(Path(source), topic, lab)
    async with Reporter.from_config(cfg, clock=clk) as rep:
        if source in ("bus", "mocap"):
            n = await _run_live(rep, source, lab, cfg, clk, topic, duration_s)
        else:
            await asyncio.to_thread(rep.wait_connected, 10.0)
            n = await rep.run(replay_samples(samples, clk, speed=speed), cfg.rate_hz, until_s=duration_s)
            await asyncio.to_thread(rep.wait_delivered, 5.0)
        return ReportOutcome(n, rep.endpoint.session.peer_name or "the server", rep.stats)


async def _run_live(
    rep: Reporter, source: str, lab: LabConfig, cfg: ReporterConfig, clock: Clock, topic: str | None,
    duration_s: float | None,
) -> int:
    from flightkit.mocap import open_mocap

    keys = Keys(lab.vehicle.namespace)
    if source == "bus" and topic:
        from flightkit.bus.session import open_session

        session = open_session(lab.bus)
        try:
            frames = WorldFrames(lab.mocap.T_world_mocap.to_transform())
            return int(await rep.run(bus_pose_samples(session, topic, frames), cfg.rate_hz, until_s=duration_s))
        finally:
            session.close()
    mocap_cfg = lab.mocap
    if source == "bus":
        mocap_cfg = dataclasses.replace(mocap_cfg, source=MocapSourceKind.BUS)
    async with open_mocap(mocap_cfg, lab.bus, keys, clock) as mocap:
        return int(await rep.run(mocap_samples(mocap, lab.mocap.body), cfg.rate_hz, until_s=duration_s))

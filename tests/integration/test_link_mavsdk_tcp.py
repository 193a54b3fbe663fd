"""MavsdkLink over TCP, as to ArduPilot SITL's ``tcp:5760``: the simulator behind a real TCP<->UDP
byte relay. MAVSDK's first HEARTBEAT races its own asynchronous TCP connect and fails; that one
line must not reach the log as an error (issue 19)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading
from collections.abc import Iterator

import pytest

from flightkit.clock import ONE_PROCESS_WALL_STEP_S, SimClock
from flightkit.config import Autopilot, LinkBackend, LinkConfig
from flightkit.link.mavsdk import MavsdkLink
from flightkit.sim.lab import SimLab

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(60)]


@contextlib.contextmanager
def tcp_relay(udp_port: int) -> Iterator[int]:
    """A TCP server on loopback whose one client's bytes go to ``udp_port`` and back; yields its port."""
    server = socket.create_server(("127.0.0.1", 0))
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", 0))
    clients: list[socket.socket] = []

    def to_udp(conn: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := conn.recv(4096):
                udp.sendto(data, ("127.0.0.1", udp_port))

    def serve() -> None:
        with contextlib.suppress(OSError):
            conn, _ = server.accept()
            clients.append(conn)
            threading.Thread(target=to_udp, args=(conn,), daemon=True).start()
            while True:
                data, _ = udp.recvfrom(4096)
                conn.sendall(data)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield server.getsockname()[1]
    finally:
        for s in (server, udp, *clients):
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            s.close()
        thread.join(timeout=2.0)


def test_connecting_over_tcp_logs_no_mavsdk_error(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG, logger="flightkit.link.mavsdk.core")
    clock = SimClock(1.0, max_wall_step_s=ONE_PROCESS_WALL_STEP_S)
    lab = SimLab(autopilot="ardupilot", url="udpin:127.0.0.1:0", clock=clock, ready_after_s=0.0).start()

    async def go() -> None:
        with tcp_relay(lab.port) as port:
            cfg = LinkConfig(url=f"tcp:127.0.0.1:{port}", backend=LinkBackend.MAVSDK, heartbeat_timeout_s=5.0)
            async with MavsdkLink(cfg, Autopilot.ARDUPILOT, clock) as link:
                assert link.info.system_id == 1
                assert await link.read_params(["GUID_TIMEOUT"]) == {"GUID_TIMEOUT": 3.0}

    try:
        asyncio.run(go())
    finally:
        lab.stop()
    core = [r for r in caplog.records if r.name == "flightkit.link.mavsdk.core"]
    assert core, "MAVSDK's log lines should reach flightkit.link.mavsdk.core"
    errors = [r.getMessage() for r in core if r.levelno >= logging.ERROR]
    assert errors == []

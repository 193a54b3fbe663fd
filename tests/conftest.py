"""Shared test options and fixtures."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--hardware", action="store_true", default=False, help="run tests that need real hardware")


# Integration tests that run the simulator, Zenoh, ptys or subprocesses against wall-clock
# timeouts and tracking bounds. On a shared 2-vCPU VM a scheduler stall of 100 ms can push one
# of them over a bound, so each is retried up to twice; `-ra` lists every rerun, so a flaky test
# stays visible, and a real fault fails all three attempts.
TIMED_MODULES = (
    "test_bus", "test_capture_cli", "test_capture_sim", "test_capture_sources", "test_closed_loop",
    "test_demo", "test_examples", "test_fly_faults", "test_fly_patterns", "test_link_mavlink", "test_link_mavsdk",
    "test_mocap", "test_mocap_simulated", "test_report_pty", "test_sim_autopilot",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    retry = pytest.mark.flaky(reruns=2, reruns_delay=1)
    for item in items:
        if item.module is not None and item.module.__name__.rsplit(".", 1)[-1] in TIMED_MODULES:
            item.add_marker(retry)
    if config.getoption("--hardware"):
        return
    skip = pytest.mark.skip(reason="needs real hardware; run with --hardware")
    for item in items:
        if "hardware" in item.keywords:
            item.add_marker(skip)


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def shared_data() -> Path:
    """The team's real recorded sequences (../shared/data), read in place."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA


def wait(predicate: Callable[[], object], timeout_s: float, what: str) -> None:
    """Poll ``predicate`` until it is true; AssertionError naming ``what`` after ``timeout_s`` (wall)."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.001)


@pytest.fixture
def sessions() -> Iterator[tuple[object, object]]:
    """Two Zenoh sessions joined on a private loopback port: (listener, connector)."""
    from flightkit.bus.session import open_session
    from flightkit.config import BusConfig

    port = free_tcp_port()
    a = open_session(BusConfig(listen=(f"tcp/127.0.0.1:{port}",)))
    b = open_session(BusConfig(connect=(f"tcp/127.0.0.1:{port}",)))
    try:
        yield a, b
    finally:
        b.close()
        a.close()

"""Clock exchange between two bus sessions: the remote clock's offset from NTP-style stamps."""

from __future__ import annotations

import pytest

from flightkit.bus.clock_exchange import ClockProbe, ClockServer
from flightkit.bus.keys import Keys
from flightkit.clock import WallClock
from flightkit.errors import BusError
from tests.integration.test_bus import pair


class ShiftedClock(WallClock):
    """Wall time plus a fixed offset: another host's clock."""

    def __init__(self, offset_ns: int) -> None:
        self.offset_ns = offset_ns

    def time_ns(self) -> int:
        return super().time_ns() + self.offset_ns


def test_probe_measures_the_remote_clock_offset() -> None:
    keys = Keys("uav1")
    with pair() as (a, b, _):
        with ClockServer(a, keys, "vehicle", ShiftedClock(3_000_000)) as server:
            probe = ClockProbe(b, keys, "vehicle", WallClock())
            probe.wait_for_server(timeout_s=10.0)  # the queryable is routed a moment after it is declared
            for _ in range(39):
                ex = probe.exchange(timeout_s=2.0)
                assert ex.rtt_ns >= 0
            est = probe.estimate()
            assert server.answered >= 40
            assert est.kept <= est.exchanges == 40
            # the offset is exact up to the asymmetry of the loopback path, bounded by half a round trip
            assert est.offset_ns == pytest.approx(3_000_000, abs=est.uncertainty_ns + 200_000)
            assert est.rtt_min_ns < 50_000_000
        with pytest.raises(BusError, match="no clock reply"):
            ClockProbe(b, keys, "ground", WallClock()).exchange(timeout_s=0.3)

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


def test_a_two_host_recording_carries_the_hosts_clock_offset(tmp_path) -> None:
    """A vehicle whose clock runs 250 ms ahead publishes poses; the ground station records them
    with its clock watch on: the recording holds the vehicle's offset, which puts the vehicle's
    bus times on the recorder's time base."""
    from capture.bus_recorder import BusRecorder
    from flightkit.bus.clock_exchange import ClockWatch
    from flightkit.bus.streams import PosePublisher
    from flightkit.datasets.mcap_reader import RecordingReader
    from flightkit.frames import Transform
    from tests.conftest import wait

    keys, offset_ns = Keys("uav1"), 250_000_000
    vehicle_clock = ShiftedClock(offset_ns)
    out = tmp_path / "two_hosts.mcap"
    with pair() as (a, b, _):
        with ClockServer(a, keys, "vehicle", vehicle_clock):
            pub = PosePublisher(a, keys, "uav1", clock=vehicle_clock)
            watch = ClockWatch(b, keys, "ground", WallClock(), interval_s=3600.0)  # rounds driven below
            rec = BusRecorder(b, out, ["uav1/mocap/**"], compression="none", clock_watch=watch)
            try:
                wait(lambda: watch.exchange_round(timeout_s=0.5) > 0, 10, "the vehicle's clock server")
                for _ in range(40):
                    pub.publish(vehicle_clock.time_ns(), Transform.from_xyz_yaw([0.0, 0.0, 1.0], 0.0))
                    watch.exchange_round(timeout_s=2.0)
                rec.wait_for(lambda st: st.get("uav1/mocap/uav1/pose") is not None
                             and st["uav1/mocap/uav1/pose"].count >= 40, 10)
            finally:
                rec.stop()
                pub.close()
    reader = RecordingReader(out)
    est = reader.clock_offsets()["vehicle"]
    assert reader.metadata["clock_offsets"]["local_host"] == "ground"
    assert est.exchanges >= 40
    assert est.offset_ns == pytest.approx(offset_ns, abs=est.uncertainty_ns + 200_000)
    for m in reader.messages(["/uav1/mocap/uav1/pose"]):
        # the vehicle put it on the bus before the ground station logged it, on one time base
        on_ground = est.remote_to_local_ns(m.publish_time_ns)
        assert 0 <= m.log_time_ns - on_ground < 50_000_000
        assert m.publish_time_ns - m.log_time_ns > offset_ns - 50_000_000  # raw: 250 ms apart

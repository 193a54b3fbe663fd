"""The MCAP recorder writes ROS 2-profile files, survives crashes and full disks."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from capture.recorder import Compression, Recorder, StreamSample
from flightkit.datasets.mcap_recovery import recover, scan
from flightkit.errors import CaptureError, DatasetError

STRING_SCHEMA = "string data\n"


def schema_for(msgtype: str) -> str:
    assert msgtype == "std_msgs/msg/String"
    return STRING_SCHEMA


def cdr_string(text: str) -> bytes:
    raw = text.encode() + b"\x00"
    return b"\x00\x01\x00\x00" + len(raw).to_bytes(4, "little") + raw


def sample(i: int, topic: str = "uav1/test/chatter", size: int = 0) -> StreamSample:
    text = f"msg {i}" + "x" * size
    return StreamSample(
        topic, "std_msgs/msg/String", cdr_string(text), i, 1_000_000_000 + i * 1000, 1_000_000_000 + i * 1000
    )


@pytest.mark.parametrize("compression", [Compression.NONE, Compression.ZSTD, Compression.LZ4])
def test_round_trip_with_mcap_and_rosbags(tmp_path: Path, compression: Compression) -> None:
    out = tmp_path / "run.mcap"
    rec = Recorder(out, schema_for, compression=compression, metadata={"calibration": {"fx": "320"}}, chunk_size=4096)
    for i in range(500):
        assert rec.offer(sample(i))
    for i in range(0, 100, 2):  # every other message: 49 gaps of one
        rec.offer(sample(i, topic="uav1/test/sparse"))
    report = rec.close()
    assert report.error == ""
    assert report.streams["uav1/test/chatter"].count == 500
    assert report.streams["uav1/test/sparse"].missed == 49
    with out.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 550
        header = reader.get_header()
        assert header.profile == "ros2"
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta["calibration"] == {"fx": "320"}
        assert "version" in meta["flightkit"]
        channel = next(c for c in summary.channels.values() if c.topic == "/uav1/test/chatter")
        assert channel.message_encoding == "cdr"
        assert "reliability" in channel.metadata["offered_qos_profiles"]
    with AnyReader([out]) as ar:
        conns = [c for c in ar.connections if c.topic == "/uav1/test/chatter"]
        texts = [ar.deserialize(raw, c.msgtype).data for c, _, raw in ar.messages(connections=conns)]
    assert texts == [f"msg {i}" for i in range(500)]


def test_refuses_to_overwrite(tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    out.write_bytes(b"precious")
    with pytest.raises(CaptureError, match="exists"):
        Recorder(out, schema_for)
    assert out.read_bytes() == b"precious"
    Recorder(out, schema_for, allow_overwrite=True).close()
    assert scan(out).complete


def test_split_by_size(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "run.mcap", schema_for, split_size_mb=0.05, chunk_size=8192)
    for i in range(400):
        rec.offer(sample(i, size=500))
    report = rec.close()
    assert len(report.files) >= 3
    total = 0
    for f in report.files:
        assert f.name.startswith("run_") and scan(f).complete
        with f.open("rb") as fh:
            total += make_reader(fh).get_summary().statistics.message_count  # type: ignore[union-attr]
    assert total == 400


WRITER_SCRIPT = textwrap.dedent(
    """
    import os, resource, signal, sys, time
    sys.path.insert(0, {root!r})
    from capture.recorder import Recorder, StreamSample
    from tests.integration.test_recorder import sample, schema_for
    mode = sys.argv[2]
    if mode == "fsize":
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (300_000, 300_000))
    rec = Recorder(sys.argv[1], schema_for, chunk_size=20_000, chunk_max_age_s=0.05)
    for i in range(100_000):
        rec.offer(sample(i, size=200))
        if mode == "kill" and i == 3000:
            time.sleep(0.5)  # let a few chunks reach the disk
            print("READY", flush=True)
            time.sleep(60)
        if rec.stopped:
            break
    report = rec.close()
    print("ERROR:", report.error, flush=True)
    """
)


def run_writer(tmp_path: Path, mode: str) -> subprocess.Popen[str]:
    root = str(Path(__file__).resolve().parents[2])
    script = tmp_path / "writer.py"
    script.write_text(WRITER_SCRIPT.format(root=root))
    return subprocess.Popen(
        [sys.executable, str(script), str(tmp_path / "run.mcap"), mode],
        stdout=subprocess.PIPE,
        text=True,
        cwd=root,
    )


def test_full_disk_stops_cleanly_and_leaves_a_valid_file(tmp_path: Path) -> None:
    proc = run_writer(tmp_path, "fsize")
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0, out
    assert "disk full" in out
    res = scan(tmp_path / "run.mcap")
    assert res.complete
    assert (tmp_path / "run.mcap").stat().st_size <= 300_000
    with AnyReader([tmp_path / "run.mcap"]) as ar:
        texts = [ar.deserialize(raw, c.msgtype).data for c, _, raw in ar.messages()]
    assert len(texts) > 100
    assert texts == [f"msg {i}" + "x" * 200 for i in range(len(texts))]  # a gap-free prefix


def test_sigkill_then_recover(tmp_path: Path) -> None:
    proc = run_writer(tmp_path, "kill")
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == "READY"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    proc.stdout.close()
    crashed = tmp_path / "run.mcap"
    before = scan(crashed)
    assert not before.complete and before.chunks
    report = recover(crashed, tmp_path / "fixed.mcap")
    assert report.messages == before.message_count > 100
    assert "salvaged" in report.summary()
    with AnyReader([tmp_path / "fixed.mcap"]) as ar:
        texts = [ar.deserialize(raw, c.msgtype).data for c, _, raw in ar.messages()]
    assert texts == [f"msg {i}" + "x" * 200 for i in range(report.messages)]
    with pytest.raises(DatasetError, match="exists"):
        recover(crashed, tmp_path / "fixed.mcap")


def test_capture_info_and_recover_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import json

    from flightkit.cli.main import main

    out = tmp_path / "run.mcap"
    rec = Recorder(out, schema_for)
    for i in range(100):
        if i not in range(40, 50):  # a 10-message silence and 10 missed sequence numbers
            rec.offer(sample(i))
    rec.close()
    assert main(["capture", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    (stream,) = info["streams"]
    assert stream["topic"] == "/uav1/test/chatter" and stream["count"] == 90
    assert stream["missed_seq"] == 10 and stream["gaps"] == 1
    assert stream["rate_hz"] == pytest.approx(89 / 99e-6)  # 90 stamps over 99 us
    assert main(["capture", "info", str(out)]) == 0
    assert "/uav1/test/chatter" in capsys.readouterr().out
    # a bad file gives one line and exit code 1
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file")
    assert main(["capture", "info", str(bad)]) == 1
    assert "capture recover" in capsys.readouterr().err
    assert main(["capture", "recover", str(out), "-o", str(tmp_path / "fixed.mcap")]) == 0
    assert "already complete" in capsys.readouterr().out

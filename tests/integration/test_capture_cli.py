"""`flightkit record` as a separate process: publisher and recorder over Zenoh on loopback,
SIGTERM finalises, SIGKILL is recovered, a file-size limit stops it with a valid file."""

from __future__ import annotations

import os
import re
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from flightkit.cli.main import main as flightkit_main
from flightkit.datasets.mcap_recovery import scan
from tests.conftest import REPO_ROOT, free_tcp_port

PY = sys.executable


def record_cmd(out: Path, port: int, *extra: str) -> list[str]:
    return [PY, "-m", "flightkit", "record", "-o", str(out), "--listen", f"tcp/127.0.0.1:{port}",
            "--topics", "uav1/**", "--quiet", *extra]


def publisher(port: int, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [PY, "-m", "capture.sources.synthetic", "--connect", f"tcp/127.0.0.1:{port}", "--width", "320",
         "--height", "240", *extra],
        cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )


def wait_messages(path: Path, count: int, timeout_s: float, proc: subprocess.Popen[str]) -> int:
    """Poll the growing file (complete chunks only) until it holds ``count`` messages."""
    deadline = time.monotonic() + timeout_s
    while True:
        n = scan(path).message_count if path.exists() and path.stat().st_size > 8 else 0
        if n >= count:
            return n
        if proc.poll() is not None:
            raise AssertionError(f"recorder exited early: {proc.communicate()}")
        if time.monotonic() > deadline:
            raise AssertionError(f"only {n} of {count} messages reached {path} within {timeout_s} s")
        time.sleep(0.05)


def counts(path: Path) -> dict[str, int]:
    with path.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None and summary.statistics is not None
    return {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}


def test_two_processes_sigterm_finalises(tmp_path: Path) -> None:
    port = free_tcp_port()
    out = tmp_path / "run.mcap"
    rec = subprocess.Popen(record_cmd(out, port, "--compression", "lz4", "--config", str(write_lab(tmp_path))),
                           cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    pub = publisher(port, "--frames", "40", "--camera-hz", "40", "--mocap-hz", "200")
    pub_out, pub_err = pub.communicate(timeout=60)
    assert pub.returncode == 0, pub_err
    m = re.search(r"published (\d+) frames and (\d+) poses", pub_out)
    assert m, pub_out
    frames, poses = int(m.group(1)), int(m.group(2))
    assert frames == 40
    wait_messages(out, 4 * frames + poses, 30, rec)
    rec.send_signal(signal.SIGTERM)
    stdout, stderr = rec.communicate(timeout=30)
    assert rec.returncode == 0, stderr
    assert "stopped by SIGTERM" in stdout and "missed 0" in stdout
    c = counts(out)
    assert c["/uav1/camera/color/image"] == frames and c["/uav1/camera/depth/camera_info"] == frames
    assert c["/uav1/mocap/uav1/pose"] == poses
    with out.open("rb") as fh:
        reader = make_reader(fh)
        meta = {x.name: x.metadata for x in reader.iter_metadata()}
        seqs = [msg.sequence for _s, _c, msg in reader.iter_messages(topics=["/uav1/camera/color/image"])]
    assert seqs == list(range(1, frames + 1))
    assert meta["config"]["vehicle"] and "T_body_camera" in meta["extrinsics"]
    # capture info reads it back through the CLI.
    assert flightkit_main(["capture", "info", str(out), "--json"]) == 0


def write_lab(tmp: Path) -> Path:
    p = tmp / "lab.toml"
    p.write_text('[vehicle]\nnamespace = "uav1"\n[capture]\ncompression = "zstd"\n')
    return p


def test_refuses_to_overwrite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run.mcap"
    out.write_bytes(b"keep me")
    rc = flightkit_main(["record", "-o", str(out), "--listen", f"tcp/127.0.0.1:{free_tcp_port()}",
                         "--duration", "0.1", "--quiet"])
    assert rc == 1 and "exists" in capsys.readouterr().err
    assert out.read_bytes() == b"keep me"


def test_sigkill_then_recover(tmp_path: Path) -> None:
    port = free_tcp_port()
    out = tmp_path / "crash.mcap"
    rec = subprocess.Popen(record_cmd(out, port, "--compression", "zstd"), cwd=REPO_ROOT,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    pub = publisher(port, "--duration", "30", "--camera-hz", "30", "--mocap-hz", "240")
    try:
        seen = wait_messages(out, 300, 60, rec)
        rec.send_signal(signal.SIGKILL)
        rec.communicate(timeout=10)
    finally:
        pub.kill()
        pub.communicate()
    with pytest.raises(Exception):  # noqa: B017 - the torn file has no summary
        with out.open("rb") as fh:
            make_reader(fh).get_summary()  # type: ignore[union-attr]
            list(make_reader(fh).iter_messages())
    fixed = tmp_path / "fixed.mcap"
    assert flightkit_main(["capture", "recover", str(out), "-o", str(fixed)]) == 0
    c = counts(fixed)
    assert sum(c.values()) >= seen
    with fixed.open("rb") as fh:
        seqs = [m.sequence for _s, _c, m in make_reader(fh).iter_messages(topics=["/uav1/mocap/uav1/pose"])]
    assert len(seqs) > 100 and seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # all before the last chunk


def test_file_size_limit_stops_with_a_valid_file(tmp_path: Path) -> None:
    port = free_tcp_port()
    out = tmp_path / "full.mcap"
    limit = 12 << 20  # three 4 MiB chunks

    def limit_fsize() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    rec = subprocess.Popen(record_cmd(out, port, "--compression", "none"), cwd=REPO_ROOT,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=limit_fsize)
    pub = publisher(port, "--duration", "30", "--camera-hz", "30")
    try:
        stdout, stderr = rec.communicate(timeout=60)
    finally:
        pub.kill()
        pub.communicate()
    assert rec.returncode == 1, (stdout, stderr)
    assert "disk full" in stderr
    assert out.stat().st_size <= limit
    c = counts(out)
    assert c["/uav1/camera/color/image"] > 5
    with out.open("rb") as fh:
        n = sum(1 for _ in make_reader(fh).iter_messages())
    assert n == sum(c.values())


@pytest.mark.netns
def test_two_hosts_in_network_namespaces_through_a_router(tmp_path: Path) -> None:
    """Vehicle and ground station in separate network namespaces, joined by a veth pair; the
    recorder (ground) listens as a router, the publisher (vehicle) connects as a client."""
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    tag = f"fk{os.getpid() % 100000}"
    veh, gnd = f"{tag}v", f"{tag}g"

    def ip(*a: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(["ip", *a], capture_output=True, text=True)

    r = ip("netns", "add", veh)
    if r.returncode != 0:
        pytest.skip(f"cannot create network namespaces here: {r.stderr.strip()}")
    try:
        ip("netns", "add", gnd)
        steps = [
            ("link", "add", f"{tag}a", "type", "veth", "peer", "name", f"{tag}b"),
            ("link", "set", f"{tag}a", "netns", veh), ("link", "set", f"{tag}b", "netns", gnd),
            ("-n", veh, "addr", "add", "10.77.0.1/24", "dev", f"{tag}a"),
            ("-n", gnd, "addr", "add", "10.77.0.2/24", "dev", f"{tag}b"),
            ("-n", veh, "link", "set", f"{tag}a", "up"), ("-n", gnd, "link", "set", f"{tag}b", "up"),
            ("-n", veh, "link", "set", "lo", "up"), ("-n", gnd, "link", "set", "lo", "up"),
        ]
        for st in steps:
            res = ip(*st)
            if res.returncode != 0:
                pytest.skip(f"cannot set up the namespaces ({' '.join(st)}): {res.stderr.strip()}")
        out = tmp_path / "netns.mcap"
        lab = tmp_path / "ground.toml"
        lab.write_text('[bus]\nmode = "router"\nlisten = ["tcp/10.77.0.2:7447"]\n')
        rec = subprocess.Popen(
            ["ip", "netns", "exec", gnd, PY, "-m", "flightkit", "record", "-o", str(out), "--config", str(lab),
             "--quiet"], cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        assert rec.stderr is not None
        first = rec.stderr.readline()  # printed once the router session is open
        assert "recording" in first, first + rec.communicate()[1]
        pub = subprocess.run(
            ["ip", "netns", "exec", veh, PY, "-m", "capture.sources.synthetic", "--mode", "client", "--connect",
             "tcp/10.77.0.2:7447", "--width", "320", "--height", "240", "--frames", "30", "--wait-subscribers", "20"],
            cwd=REPO_ROOT, capture_output=True, text=True, timeout=90,
        )
        assert pub.returncode == 0, pub.stderr
        frames, poses = (int(x) for x in re.search(r"published (\d+) frames and (\d+) poses", pub.stdout).groups())  # type: ignore[union-attr]
        wait_messages(out, 4 * frames + poses, 30, rec)
        rec.send_signal(signal.SIGINT)
        _, err = rec.communicate(timeout=30)
        assert rec.returncode == 0, err
        c = counts(out)
        assert c["/uav1/camera/color/image"] == frames and c["/uav1/mocap/uav1/pose"] == poses
    finally:
        ip("netns", "del", veh)
        ip("netns", "del", gnd)

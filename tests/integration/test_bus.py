"""The bus over real Zenoh sessions on loopback (unique free ports per test), a real
subprocess publisher, and real MCAP files read by independent ROS 2 readers."""

from __future__ import annotations

import asyncio
import json
import secrets
import socket
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import numpy as np
import pytest
import zenoh

from flightkit.bus.image_msgs import CameraInfo, Image
from flightkit.bus.msg_base import Header
from flightkit.bus.pose_msgs import Odometry, PoseStamped, TFMessage, TransformStamped
from flightkit.bus.pubsub import _ATTACHMENT_V1 as _ATTACHMENT
from flightkit.bus.pubsub import _MAGIC_V1 as _MAGIC
from flightkit.bus.pubsub import BusPublisher, BusSample, BusSubscriber, cdr_encoding
from flightkit.bus.session import build_zenoh_config, bus_session, open_session, session_locators
from flightkit.config import BusConfig, BusMode
from flightkit.errors import BusError
from tests.conftest import REPO_ROOT, free_tcp_port

pytestmark = pytest.mark.timeout(60)


def wait_until(pred: Callable[[], bool], timeout_s: float = 5.0, what: str = "condition") -> None:
    """Poll shared state until ``pred()`` holds (no fixed sleeps)."""
    deadline = time.monotonic() + timeout_s
    ev = threading.Event()
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        ev.wait(0.005)


def link_up(sub_side: zenoh.Session, pub_side: zenoh.Session, timeout_s: float = 5.0) -> None:
    """Wait until data published on ``pub_side`` reaches ``sub_side``.

    Zenoh reports a matching subscriber as soon as the declaration arrived, but samples sent
    in the first few milliseconds after two peers connect can still be lost; so probe.
    """
    key = f"probe/{secrets.token_hex(4)}"
    got = threading.Event()
    sub = sub_side.declare_subscriber(key, lambda _s: got.set())
    pub = pub_side.declare_publisher(key)
    deadline = time.monotonic() + timeout_s
    while not got.wait(0.005):
        assert time.monotonic() < deadline, "the two sessions never connected"
        pub.put(b"")
    pub.undeclare()
    sub.undeclare()


def deliver(pub: BusPublisher, sub: BusSubscriber, stamp_ns: int, timeout_s: float = 5.0) -> BusSample:
    """Publish a pose until ``sub`` receives one (a fresh declaration can take a few ms to route)."""
    deadline = time.monotonic() + timeout_s
    while True:
        pub.publish(PoseStamped(Header(stamp_ns, "m")))
        try:
            first = sub.get(timeout_s=0.02)
        except TimeoutError:
            assert time.monotonic() < deadline, f"nothing from {pub.key} reached {sub.key_expr}"
            continue
        while (later := sub.try_get()) is not None:  # keep the newest, leave the queue empty
            first = later
        return first


def prime(put: Callable[[], None], sub: BusSubscriber, key: str, timeout_s: float = 5.0) -> None:
    """Put until ``sub`` has received something on ``key``, then empty its queue."""
    deadline = time.monotonic() + timeout_s
    while sub.received(key) == 0:
        assert time.monotonic() < deadline, f"nothing reached {key}"
        put()
        threading.Event().wait(0.002)
    while sub.try_get() is not None:
        pass


@contextmanager
def pair() -> Iterator[tuple[zenoh.Session, zenoh.Session, int]]:
    """Two peers: a listens on a free loopback port, b connects to it."""
    port = free_tcp_port()
    a = open_session(BusConfig(listen=(f"tcp/127.0.0.1:{port}",)))
    try:
        b = open_session(BusConfig(connect=(f"tcp/127.0.0.1:{port}",), listen=("tcp/127.0.0.1:0",)))
        try:
            link_up(a, b)
            yield a, b, port
        finally:
            b.close()
    finally:
        a.close()


def test_pose_stream_between_two_sessions_in_order() -> None:
    async def main() -> None:
        with pair() as (a, b, _):
            with (
                BusSubscriber(a, "uav1/mocap/*/pose") as sub,
                BusPublisher(b, "uav1/mocap/uav1/pose", PoseStamped, reliable=True, express=True) as pub,
            ):
                first = deliver(pub, sub, 0)
                for i in range(50):
                    pub.publish(PoseStamped(Header(1_000 + i, "mocap"), (float(i), 0.0, 1.0)))
                got = []
                async for s in sub:
                    got.append(s)
                    if len(got) == 50:
                        break
                assert [s.seq for s in got] == list(range(first.seq + 1, first.seq + 51))
                key, msgtype, seq, stamp_ns, payload, bus_ns, stamp_source = got[7]
                assert (key, msgtype, seq, stamp_ns, stamp_source) == (
                    "uav1/mocap/uav1/pose",
                    PoseStamped.TYPE,
                    first.seq + 8,
                    1_007,
                    "host",
                )
                assert abs(bus_ns - time.time_ns()) < 60 * 10**9  # put on the bus now (wall clock)
                assert PoseStamped.decode(payload).position_m == (7.0, 0.0, 1.0)
                assert sub.missed() == 0 and sub.received("uav1/mocap/uav1/pose") == 51
                with pytest.raises(TimeoutError, match="no message on"):
                    await sub.recv(timeout_s=0.05)

    asyncio.run(main())


def test_default_config_peers_find_each_other_without_multicast() -> None:
    cfg = BusConfig(well_known_port=free_tcp_port())
    assert cfg.mode is BusMode.PEER and not cfg.multicast_scouting
    with ExitStack() as stack:
        s1 = open_session(cfg)
        stack.callback(s1.close)
        s2 = open_session(cfg)
        stack.callback(s2.close)
        s3 = open_session(cfg)
        stack.callback(s3.close)
        well_known = f"tcp/127.0.0.1:{cfg.well_known_port}"
        assert any(link.endswith(well_known) for link in session_locators(s2)), session_locators(s2)
        # s2 and s3 (both joiners) talk to each other.
        link_up(s3, s2)  # the two joiners reach each other (through the mesh gossip builds)
        sub = stack.enter_context(BusSubscriber(s3, "lab/**"))
        pub = stack.enter_context(BusPublisher(s2, "lab/x", PoseStamped))
        assert deliver(pub, sub, 1).stamp_ns == 1
        # The first process exits: the others keep talking, and a newcomer takes the port over.
        s1.close()
        assert deliver(pub, sub, 2).stamp_ns == 2
        s4 = open_session(cfg)
        stack.callback(s4.close)
        with socket.socket() as probe, pytest.raises(OSError):  # s4 took the well-known port over
            probe.bind(("127.0.0.1", cfg.well_known_port))
        sub4 = stack.enter_context(BusSubscriber(s4, "lab/**"))
        assert deliver(pub, sub4, 3, timeout_s=15.0).stamp_ns == 3  # s2 reconnects to the port (Zenoh retries)
        wait_until(lambda: len(s4.info.peers_zid()) == 2, timeout_s=15.0, what="s3 to reconnect too")


def test_sequence_gaps_are_counted_per_key_and_stream() -> None:
    with pair() as (a, b, _):
        with BusSubscriber(a, "t/**") as sub:
            raw = b.declare_publisher("t/a", encoding=cdr_encoding(PoseStamped.TYPE))
            raw_b = b.declare_publisher("t/b")
            payload = bytes(PoseStamped(Header(0, "m")).encode())
            primes = iter(range(1, 10_000))  # stream 99: consecutive, so priming adds no gap
            prime(lambda: raw.put(payload, attachment=_ATTACHMENT.pack(_MAGIC, next(primes), 0, 99)), sub, "t/a")
            prime(lambda: raw_b.put(b"\x00\x01\x00\x00"), sub, "t/b")
            r0 = sub.received()
            # stream 7 on t/a: 1 2 5 6 9 -> 4 missed; stream 8 on t/a starts at 100 (no gap)
            for seq in (1, 2, 5, 6, 9):
                raw.put(payload, attachment=_ATTACHMENT.pack(_MAGIC, seq, seq * 10, 7))
            for seq in (100, 101):
                raw.put(payload, attachment=_ATTACHMENT.pack(_MAGIC, seq, 0, 8))
            # t/b: a foreign publisher without our attachment -> seq -1, nothing counted
            raw_b.put(b"\x00\x01\x00\x00")
            wait_until(lambda: sub.received() == r0 + 8, what="8 samples")
            assert sub.missed("t/a") == 4
            assert sub.missed("t/b") == 0 and sub.missed() == 4
            foreign = [s for s in (sub.get(1.0) for _ in range(8)) if s.key == "t/b"][0]
            assert (foreign.seq, foreign.msgtype, foreign.stamp_ns) == (-1, "", 0)
            raw.undeclare()
            raw_b.undeclare()


def test_full_queue_drops_the_oldest_and_counts_it() -> None:
    with pair() as (a, b, _):
        with BusSubscriber(a, "q", maxlen=5) as sub, BusPublisher(b, "q", PoseStamped) as pub:
            first = deliver(pub, sub, 0)
            r0, o0 = sub.received(), sub.overflowed
            for i in range(20):
                pub.publish(PoseStamped(Header(i, "m")))
            wait_until(lambda: sub.received() == r0 + 20, what="20 samples")
            assert sub.overflowed - o0 == 15 and sub.missed() == 0
            assert [sub.get(1.0).seq for _ in range(5)] == [first.seq + k for k in (16, 17, 18, 19, 20)]
            assert sub.try_get() is None


def test_publisher_policies() -> None:
    with pair() as (_, b, _port):
        img = BusPublisher(b, "uav1/camera/color/image", Image, reliable=False, drop_when_congested=True)
        pose = BusPublisher(b, "uav1/mocap/uav1/pose", PoseStamped, express=True)
        assert img._pub.congestion_control == zenoh.CongestionControl.DROP
        assert img._pub.reliability == zenoh.Reliability.BEST_EFFORT
        assert pose._pub.congestion_control == zenoh.CongestionControl.BLOCK
        assert pose._pub.reliability == zenoh.Reliability.RELIABLE
        assert str(pose._pub.encoding) == "application/cdr;geometry_msgs/msg/PoseStamped"
        with pytest.raises(BusError, match="sends sensor_msgs/msg/Image, not PoseStamped"):
            img.publish(PoseStamped(Header()))
        img.close()
        img.close()
        with pytest.raises(BusError, match="is closed"):
            img.put(b"", 0)
        pose.close()


_CHILD = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from flightkit.bus.image_msgs import Image
    from flightkit.bus.msg_base import Header
    from flightkit.bus.pose_msgs import PoseStamped
    from flightkit.bus.pubsub import BusPublisher
    from flightkit.bus.session import open_session
    from flightkit.config import BusConfig

    port, n_pose, n_img = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
    s = open_session(BusConfig(connect=(f"tcp/127.0.0.1:{port}",), listen=("tcp/127.0.0.1:0",)))
    pose = BusPublisher(s, "uav1/mocap/uav1/pose", PoseStamped, express=True)
    img = BusPublisher(s, "uav1/camera/color/image", Image, reliable=False, drop_when_congested=True)
    # handshake: probe until the parent acknowledges, so no sample is sent before the link is up
    acked = []
    ack = s.declare_subscriber("probe/ack", lambda _s: acked.append(1))
    probe = s.declare_publisher("probe/child")
    deadline = time.monotonic() + 10
    while not (acked and pose.has_subscribers and img.has_subscribers):
        if time.monotonic() > deadline:
            sys.exit("no subscriber")
        probe.put(b"")
        time.sleep(0.01)
    for i in range(n_pose):
        pose.publish(PoseStamped(Header(i, "mocap"), (float(i), 2.0, 3.0)))
    buf = bytearray()
    frame = np.empty((480, 848, 3), np.uint8)
    for i in range(n_img):
        frame[...] = i
        img.publish(Image.from_array(Header(i, "cam"), frame, "rgb8"), out=buf)
    print("done", flush=True)
    sys.stdin.read()  # keep the session open until the parent has everything
    s.close()
    """
)


def test_subprocess_publisher_to_in_process_subscriber() -> None:
    port = free_tcp_port()
    n_pose, n_img = 300, 20

    async def main() -> None:
        s = open_session(BusConfig(listen=(f"tcp/127.0.0.1:{port}",)))
        poses = BusSubscriber(s, "uav1/mocap/*/pose", maxlen=1000)
        images = BusSubscriber(s, "uav1/camera/*/image", maxlen=100)
        ack = s.declare_publisher("probe/ack")
        probe = s.declare_subscriber("probe/child", lambda _s: ack.put(b""))
        proc = subprocess.Popen(  # noqa: ASYNC220 - started once; the test waits on Zenoh, not the pipe
            [sys.executable, "-c", _CHILD, str(port), str(n_pose), str(n_img)],
            cwd=REPO_ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            got = [await poses.recv(timeout_s=15.0) for _ in range(n_pose)]
            assert [g.seq for g in got] == list(range(1, n_pose + 1))
            assert PoseStamped.decode(got[-1].payload).position_m == (n_pose - 1.0, 2.0, 3.0)
            assert proc.stdout is not None and (await asyncio.to_thread(proc.stdout.readline)).strip() == "done"
            wait_until(lambda: images.received() + images.missed() >= n_img, timeout_s=10.0, what="images")
            frames = [images.try_get() for _ in range(images.received())]
            assert frames and all(f is not None for f in frames)
            for f in frames:
                assert f is not None
                im = Image.decode(f.payload)
                arr = im.array()
                assert arr.shape == (480, 848, 3) and (im.height, im.width, im.encoding) == (480, 848, "rgb8")
                assert int(arr[0, 0, 0]) == f.seq - 1 == im.header.stamp_ns and int(arr.max()) == int(arr.min())
            assert images.received() + images.missed() == n_img  # DROP may drop; every loss is counted
        finally:
            if proc.stdin:
                proc.stdin.close()
            proc.wait(timeout=10)
            if proc.stdout:
                proc.stdout.close()
            poses.close()
            images.close()
            probe.undeclare()
            ack.undeclare()
            s.close()
        assert proc.returncode == 0

    asyncio.run(main())


def test_mcap_with_our_schemas_opens_in_mcap_ros2_and_rosbags(tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from mcap.writer import Writer
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.highlevel import AnyReader

    path = tmp_path / "bus.mcap"
    pose = PoseStamped(Header(1_700_000_000_000_000_123, "mocap"), (1.0, 2.0, 3.0), (0.0, 0.0, 0.6, 0.8))
    img = Image.from_array(Header(1_700_000_000_000_000_456, "cam"), np.full((4, 6, 3), 9, np.uint8), "rgb8")
    info = CameraInfo.from_intrinsics(Header(7, "cam"), 6, 4, 3.0, 3.0, 2.5, 1.5)
    tf = TFMessage((TransformStamped(Header(8, "world"), "body", (1.0, 0.0, 0.0)),))
    odom = Odometry(Header(9, "world"), "body", (4.0, 5.0, 6.0))
    msgs = [("/pose", pose), ("/image", img), ("/info", info), ("/tf", tf), ("/odom", odom)]
    with path.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="ros2", library="flightkit-test")
        for i, (topic, msg) in enumerate(msgs):
            sid = w.register_schema(name=msg.TYPE, encoding="ros2msg", data=msg.SCHEMA.encode())
            cid = w.register_channel(topic=topic, message_encoding="cdr", schema_id=sid)
            w.add_message(cid, log_time=1000 + i, publish_time=1000 + i, data=bytes(msg.encode()), sequence=i)
        w.finish()

    with path.open("rb") as fh:
        decoded = {
            ch.topic: m for _, ch, _, m in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages()
        }
    assert decoded["/pose"].pose.orientation.z == 0.6 and decoded["/pose"].header.stamp.nanosec == 123
    assert bytes(decoded["/image"].data) == bytes([9]) * 72 and decoded["/image"].step == 18
    assert list(decoded["/info"].k) == list(info.k)
    assert decoded["/tf"].transforms[0].child_frame_id == "body"
    assert decoded["/odom"].pose.pose.position.z == 6.0

    with AnyReader([path]) as reader:
        seen = {}
        for conn, _t, raw in reader.messages():
            seen[conn.topic] = reader.deserialize(raw, conn.msgtype)
    assert seen["/pose"].pose.position.y == 2.0 and seen["/pose"].header.frame_id == "mocap"
    assert seen["/image"].encoding == "rgb8" and seen["/image"].data.tobytes() == bytes([9]) * 72
    assert seen["/tf"].transforms[0].transform.translation.x == 1.0
    assert seen["/odom"].child_frame_id == "body"


# ----------------------------------------------------------------------------- configuration and errors


def test_bad_endpoints_and_busy_ports_raise_bus_errors() -> None:
    with pytest.raises(BusError, match="is not a Zenoh locator"):
        open_session(BusConfig(listen=("127.0.0.1:7447",)))
    with pytest.raises(BusError, match="cannot open the Zenoh session"):
        open_session(BusConfig(listen=("tcp/127.0.0.1:notaport",)))
    port = free_tcp_port()
    with open_session(BusConfig(listen=(f"tcp/127.0.0.1:{port}",))):
        with pytest.raises(BusError, match="Address already in use"):
            open_session(BusConfig(listen=(f"tcp/127.0.0.1:{port}",)))


def test_tls_settings_are_checked_and_written(tmp_path: Path) -> None:
    with pytest.raises(BusError, match="need bus.tls_root_ca"):
        build_zenoh_config(BusConfig(listen=("tls/127.0.0.1:7447",)))
    with pytest.raises(BusError, match="does not exist"):
        build_zenoh_config(BusConfig(listen=("tls/127.0.0.1:7447",), tls_root_ca=str(tmp_path / "ca.pem")))
    for name in ("ca.pem", "cert.pem", "key.pem"):
        (tmp_path / name).write_text("-----BEGIN CERTIFICATE-----\n")
    with pytest.raises(BusError, match="go together"):
        build_zenoh_config(BusConfig(tls_root_ca=str(tmp_path / "ca.pem"), tls_cert=str(tmp_path / "cert.pem")))
    conf = build_zenoh_config(
        BusConfig(
            mode=BusMode.CLIENT,
            connect=("tls/gs.lab:7447",),
            tls_root_ca=str(tmp_path / "ca.pem"),
            tls_cert=str(tmp_path / "cert.pem"),
            tls_key=str(tmp_path / "key.pem"),
        )
    )
    tls = json.loads(conf.get_json("transport/link/tls"))
    assert tls["root_ca_certificate"] == str(tmp_path / "ca.pem")
    assert tls["connect_certificate"] == str(tmp_path / "cert.pem") and tls["enable_mtls"] is True
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tls/gs.lab:7447"]


def test_zenoh_config_file_is_merged_and_access_control_applies(tmp_path: Path) -> None:
    port = free_tcp_port()
    conf_file = tmp_path / "zenoh.json5"
    conf_file.write_text(
        textwrap.dedent(
            f"""
            {{
              // a user's Zenoh config: where to listen, and an ACL that hides uav1/secret/**
              listen: {{ endpoints: ["tcp/127.0.0.1:{port}"] }},
              access_control: {{
                enabled: true,
                default_permission: "allow",
                rules: [{{ id: "no_secret", messages: ["put", "declare_subscriber"], flows: ["egress", "ingress"],
                           permission: "deny", key_exprs: ["uav1/secret/**"] }}],
                subjects: [{{ id: "everyone" }}],
                policies: [{{ rules: ["no_secret"], subjects: ["everyone"] }}],
              }},
            }}
            """
        )
    )
    with pytest.raises(BusError, match="cannot load Zenoh config file"):
        open_session(BusConfig(zenoh_config_file=str(tmp_path / "missing.json5")))
    with open_session(BusConfig(zenoh_config_file=str(conf_file))) as router_side:
        with open_session(BusConfig(connect=(f"tcp/127.0.0.1:{port}",), listen=("tcp/127.0.0.1:0",))) as other:
            secret = BusSubscriber(router_side, "uav1/secret/**")  # declared first: routed first if allowed
            ok = BusSubscriber(router_side, "uav1/public/**")
            pub_secret = BusPublisher(other, "uav1/secret/x", PoseStamped)
            pub_ok = BusPublisher(other, "uav1/public/x", PoseStamped)
            deliver(pub_ok, ok, 0)
            for i in range(5):
                pub_secret.publish(PoseStamped(Header(i, "m")))
                pub_ok.publish(PoseStamped(Header(i, "m")))
            wait_until(lambda: ok.received("uav1/public/x") >= 6, what="public samples")
            assert secret.received() == 0  # denied by the file's ACL
            for x in (ok, secret, pub_ok, pub_secret):
                x.close()


def test_the_port_variable_replaces_only_the_default_well_known_port(monkeypatch: pytest.MonkeyPatch) -> None:
    from flightkit.bus.session import PORT_ENV, well_known_port

    port = free_tcp_port()
    monkeypatch.setenv(PORT_ENV, str(port))
    assert well_known_port(BusConfig()) == port
    assert well_known_port(BusConfig(well_known_port=port + 1)) == port + 1  # a config's own port wins
    with ExitStack() as stack:  # two default sessions meet on the variable's port
        s1 = stack.enter_context(bus_session())
        s2 = stack.enter_context(bus_session())
        assert any(link.endswith(f"tcp/127.0.0.1:{port}") for link in session_locators(s2)), session_locators(s2)
        link_up(s2, s1)
    monkeypatch.setenv(PORT_ENV, "seventy")
    with pytest.raises(BusError, match="FLIGHTKIT_BUS_PORT='seventy' is not a TCP port"):
        open_session(BusConfig())

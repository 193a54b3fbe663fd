"""CDR codecs of the bus messages (flightkit.bus.pose_msgs, image_msgs, msg_base): round-trips,
and bytes cross-checked against rosbags.

rosbags (``rosbags.typesys``) is an independent CDR implementation with the real ROS 2
Humble message definitions: our payloads must equal its serialisation byte for byte, it
must read ours, and our ``ros2msg`` schema texts must parse to its field definitions.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from flightkit.bus.cdr import CdrReader, CdrWriter
from flightkit.bus.image_msgs import CameraInfo, CompressedImage, Image
from flightkit.bus.msg_base import Header
from flightkit.bus.msgs import MESSAGE_TYPES, decode_message
from flightkit.bus.pose_msgs import Odometry, PoseStamped, TFMessage, TransformStamped
from flightkit.errors import BusError
from flightkit.frames import Transform

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types


def ros_header(stamp_ns: int, frame_id: str):  # type: ignore[no-untyped-def]
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id)


def ros_bytes(msg: object, msgtype: str) -> bytes:
    return bytes(TS.serialize_cdr(msg, msgtype))


def ros_pose(p: tuple[float, ...], q: tuple[float, ...]):  # type: ignore[no-untyped-def]
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
        orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )


# ----------------------------------------------------------------------------- PoseStamped

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False)
frame_ids = st.text(alphabet="abcdefghijklmnopqrstuvwxyz_/0123456789", max_size=12)
stamps = st.integers(min_value=0, max_value=2**31 * 1_000_000_000 - 1)


@settings(max_examples=60, deadline=None)
@given(stamps, frame_ids, st.tuples(finite, finite, finite), st.tuples(finite, finite, finite, finite))
def test_pose_stamped_matches_rosbags_bytes(
    stamp_ns: int, frame: str, p: tuple[float, ...], q: tuple[float, ...]
) -> None:
    ours = PoseStamped(Header(stamp_ns, frame), p, q)  # type: ignore[arg-type]
    ref = T["geometry_msgs/msg/PoseStamped"](header=ros_header(stamp_ns, frame), pose=ros_pose(p, q))
    assert bytes(ours.encode()) == ros_bytes(ref, PoseStamped.TYPE)
    assert PoseStamped.decode(bytes(ours.encode())) == ours


def test_pose_stamped_transform_round_trip() -> None:
    T_a_b = Transform.from_xyz_euler_deg([1.0, -2.0, 0.5], "xyz", [10.0, -20.0, 135.0])
    msg = PoseStamped.from_transform(1_700_000_000_123_456_789, "mocap", T_a_b)
    back = PoseStamped.decode(msg.encode())
    assert back.header == Header(1_700_000_000_123_456_789, "mocap")
    assert back.to_transform().almost_equal(T_a_b, 1e-12, 1e-12)


def test_rosbags_reads_our_pose() -> None:
    msg = PoseStamped(Header(5_000_000_007, "world"), (1.0, 2.0, 3.0), (0.0, 0.0, 0.6, 0.8))
    ref = TS.deserialize_cdr(bytes(msg.encode()), PoseStamped.TYPE)
    assert (ref.header.stamp.sec, ref.header.stamp.nanosec, ref.header.frame_id) == (5, 7, "world")
    assert (ref.pose.position.x, ref.pose.position.z, ref.pose.orientation.w) == (1.0, 3.0, 0.8)


# ----------------------------------------------------------------------------- images


@pytest.mark.parametrize(
    ("encoding", "shape", "dtype"),
    [
        ("rgb8", (48, 85, 3), np.uint8),
        ("bgr8", (5, 7, 3), np.uint8),
        ("mono8", (31, 17), np.uint8),
        ("mono16", (12, 9), np.uint16),
        ("16UC1", (12, 9), np.uint16),
        ("32FC1", (6, 11), np.float32),
        ("rgba8", (3, 3, 4), np.uint8),
    ],
)
def test_image_matches_rosbags_and_round_trips(encoding: str, shape: tuple[int, ...], dtype: type) -> None:
    rng = np.random.default_rng(1)
    arr = (rng.random(shape) * 1000).astype(dtype)
    img = Image.from_array(Header(42_000_000_001, "cam"), arr, encoding)
    payload = img.encode()
    ref = T["sensor_msgs/msg/Image"](
        header=ros_header(42_000_000_001, "cam"),
        height=shape[0],
        width=shape[1],
        encoding=encoding,
        is_bigendian=0,
        step=img.step,
        data=arr.reshape(-1).view(np.uint8),
    )
    assert bytes(payload) == ros_bytes(ref, Image.TYPE)
    back = Image.decode(bytes(payload))
    out = back.array()
    assert out.dtype == np.dtype(dtype) and out.shape == arr.shape
    np.testing.assert_array_equal(out, arr)


def test_image_decode_is_a_view_and_encode_reuses_the_buffer() -> None:
    arr = np.arange(480 * 848 * 3, dtype=np.uint32).astype(np.uint8).reshape(480, 848, 3)
    img = Image.from_array(Header(1, "cam"), arr, "rgb8")
    buf = bytearray()
    first = img.encode(buf)
    assert first is buf
    addr = np.frombuffer(buf, np.uint8).__array_interface__["data"][0]
    arr2 = arr[::-1].copy()
    second = Image.from_array(Header(2, "cam"), arr2, "rgb8").encode(buf)
    assert second is buf and np.frombuffer(buf, np.uint8).__array_interface__["data"][0] == addr
    payload = bytes(buf)
    back = Image.decode(payload)
    view = back.array()
    assert not view.flags.owndata and view.base is not None  # no copy of the pixels
    np.testing.assert_array_equal(view, arr2)


def test_image_with_padded_rows() -> None:
    # A 3x4 mono8 image with step 6 (2 bytes of padding per row), as some drivers send.
    rows = np.arange(18, dtype=np.uint8).reshape(3, 6)
    ref = T["sensor_msgs/msg/Image"](
        header=ros_header(0, "c"), height=3, width=4, encoding="mono8", is_bigendian=0, step=6, data=rows.reshape(-1)
    )
    back = Image.decode(ros_bytes(ref, Image.TYPE))
    np.testing.assert_array_equal(back.array(), rows[:, :4])


def test_image_from_noncontiguous_and_bigendian_arrays() -> None:
    base = np.arange(10 * 12, dtype=np.uint16).reshape(10, 12)
    crop = base[2:8, 3:9]  # not contiguous
    back = Image.decode(Image.from_array(Header(), crop, "mono16").encode()).array()
    np.testing.assert_array_equal(back, crop)
    be = base.astype(">u2")
    back = Image.decode(Image.from_array(Header(), be, "16UC1").encode()).array()
    np.testing.assert_array_equal(back, base)


def test_image_rejects_mismatched_encoding() -> None:
    with pytest.raises(BusError, match="does not fit image encoding 'rgb8'"):
        Image.from_array(Header(), np.zeros((4, 4), np.uint8), "rgb8")
    with pytest.raises(BusError, match="not supported"):
        Image.from_array(Header(), np.zeros((4, 4), np.uint8), "weird9")


def test_compressed_image_matches_rosbags() -> None:
    data = bytes(range(200)) * 3
    ours = CompressedImage(Header(3, "cam"), "jpeg", data)
    ref = T["sensor_msgs/msg/CompressedImage"](
        header=ros_header(3, "cam"), format="jpeg", data=np.frombuffer(data, np.uint8)
    )
    assert bytes(ours.encode()) == ros_bytes(ref, CompressedImage.TYPE)
    back = CompressedImage.decode(bytes(ours.encode()))
    assert back.format == "jpeg" and back.data.tobytes() == data


# ----------------------------------------------------------------------------- camera info, tf, odometry


def test_camera_info_matches_rosbags_and_round_trips() -> None:
    ours = CameraInfo.from_intrinsics(
        Header(9, "cam_left"),
        640,
        480,
        320.0,
        321.0,
        319.5,
        239.5,
        d=(0.1, -0.05, 0.001, 0.0, 0.0),
        baseline_tx=-16.0,
    )
    ours = dataclasses.replace(ours, roi=(1, 2, 3, 4, True))
    ref = T["sensor_msgs/msg/CameraInfo"](
        header=ros_header(9, "cam_left"),
        height=480,
        width=640,
        distortion_model="plumb_bob",
        d=np.array(ours.d),
        k=np.array(ours.k),
        r=np.array(ours.r),
        p=np.array(ours.p),
        binning_x=0,
        binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=1, y_offset=2, height=3, width=4, do_rectify=True),
    )
    assert bytes(ours.encode()) == ros_bytes(ref, CameraInfo.TYPE)
    assert CameraInfo.decode(ours.encode()) == ours


def test_tf_message_matches_rosbags_and_round_trips() -> None:
    a = TransformStamped(Header(1, "world"), "body", (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0))
    b = TransformStamped.from_transform(
        2, "body", "camera", Transform.from_xyz_euler_deg([0.08, 0.0, -0.02], "xz", [135.0, 90.0])
    )
    ours = TFMessage((a, b))
    ros_tfs = []
    for t in (a, b):
        ros_tfs.append(
            T["geometry_msgs/msg/TransformStamped"](
                header=ros_header(t.header.stamp_ns, t.header.frame_id),
                child_frame_id=t.child_frame_id,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](*t.translation_m),
                    rotation=T["geometry_msgs/msg/Quaternion"](*t.quat_xyzw),
                ),
            )
        )
    ref = T["tf2_msgs/msg/TFMessage"](transforms=ros_tfs)
    assert bytes(ours.encode()) == ros_bytes(ref, TFMessage.TYPE)
    assert TFMessage.decode(ours.encode()) == ours
    assert TFMessage.decode(TFMessage().encode()) == TFMessage()


def test_odometry_matches_rosbags_and_round_trips() -> None:
    cov = tuple(float(i) for i in range(36))
    ours = Odometry(
        Header(77, "odom"),
        "base_link",
        (1.0, 2.0, 3.0),
        (0.0, 0.0, 0.6, 0.8),
        cov,
        (0.1, 0.2, 0.3),
        (0.01, 0.02, 0.03),
        tuple(reversed(cov)),
    )
    ref = T["nav_msgs/msg/Odometry"](
        header=ros_header(77, "odom"),
        child_frame_id="base_link",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=ros_pose((1.0, 2.0, 3.0), (0.0, 0.0, 0.6, 0.8)), covariance=np.array(cov)
        ),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](
                linear=T["geometry_msgs/msg/Vector3"](0.1, 0.2, 0.3),
                angular=T["geometry_msgs/msg/Vector3"](0.01, 0.02, 0.03),
            ),
            covariance=np.array(tuple(reversed(cov))),
        ),
    )
    assert bytes(ours.encode()) == ros_bytes(ref, Odometry.TYPE)
    assert Odometry.decode(ours.encode()) == ours


# ----------------------------------------------------------------------------- schemas and errors


@pytest.mark.parametrize("msgtype", sorted(MESSAGE_TYPES))
def test_schema_text_parses_to_the_ros2_definitions(msgtype: str) -> None:
    cls = MESSAGE_TYPES[msgtype]
    parsed = get_types_from_msg(cls.SCHEMA, msgtype)
    assert msgtype in parsed
    for name, (_consts, fields) in parsed.items():
        _ref_consts, ref_fields = TS.fielddefs[name]
        assert [f[0] for f in fields] == [f[0] for f in ref_fields], name
        assert fields == ref_fields, name


def test_schema_lists_each_dependency_once() -> None:
    text = TFMessage.SCHEMA
    assert text.startswith("geometry_msgs/TransformStamped[] transforms\n")
    deps = [line[5:] for line in text.splitlines() if line.startswith("MSG: ")]
    assert len(deps) == len(set(deps))
    assert set(deps) == {
        "geometry_msgs/TransformStamped",
        "std_msgs/Header",
        "builtin_interfaces/Time",
        "geometry_msgs/Transform",
        "geometry_msgs/Vector3",
        "geometry_msgs/Quaternion",
    }
    assert ("=" * 80 + "\nMSG: std_msgs/Header\n") in text


def test_decode_errors_are_bus_errors() -> None:
    payload = bytes(PoseStamped(Header(1, "mocap")).encode())
    with pytest.raises(BusError, match="disagree on the message type"):
        PoseStamped.decode(payload[:-8])
    with pytest.raises(BusError, match="little-endian CDR header"):
        PoseStamped.decode(b"\x00\x00\x00\x00" + payload[4:])
    with pytest.raises(BusError, match="fewer than the 4-byte CDR header"):
        PoseStamped.decode(b"\x00")
    with pytest.raises(BusError, match="known types"):
        decode_message("foo_msgs/msg/Bar", payload)
    assert isinstance(decode_message(PoseStamped.TYPE, payload), PoseStamped)


def test_writer_alignment_counts_from_after_the_header() -> None:
    w = CdrWriter()
    w.u8(1)
    w.f64(math.pi)  # 7 bytes of padding after the u8, not 3
    assert len(w.buf) == 4 + 16
    r = CdrReader(bytes(w.buf))
    assert r.u8() == 1 and r.f64() == math.pi and r.remaining == 0

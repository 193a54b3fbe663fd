"""TOML configuration validated into frozen dataclasses.

One TOML file describes a lab set-up (vehicle link, mocap, bus, simulator, camera). It is
read with :mod:`tomllib` and validated at load time: unknown keys, wrong types and
out-of-range values raise :class:`~flightkit.errors.ConfigError` naming the file, the key,
the bad value and the fix.

The loader is generic (:mod:`flightkit.settings`): any frozen dataclass whose fields carry
:func:`~flightkit.settings.setting` metadata can be loaded with
:func:`~flightkit.settings.load_section`; capability packages (trajectories, capture,
estimation) describe their own sections the same way.

Example ``lab.toml``::

    [vehicle]
    namespace = "uav1"
    autopilot = "px4"

    [link]
    url = "udpout:127.0.0.1:14540"
    backend = "pymavlink"

    [mocap]
    source = "bus"
    body = "uav1"
    [mocap.T_world_mocap]
    translation_m = [0.0, 0.0, 0.0]
    rpy_deg = [0.0, 0.0, 90.0]
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from flightkit.errors import ConfigError
from flightkit.frames import Transform
from flightkit.settings import load_section, load_toml, setting

__all__ = [
    "Autopilot",
    "BusConfig",
    "BusMode",
    "CAPABILITY_SECTIONS",
    "CameraConfig",
    "FleetVehicleConfig",
    "LabConfig",
    "LinkBackend",
    "LinkConfig",
    "MocapConfig",
    "MocapSourceKind",
    "SimConfig",
    "TransformConfig",
    "VehicleConfig",
    "load_config",
]

T = TypeVar("T")


class Autopilot(enum.Enum):
    """Which autopilot firmware the vehicle runs."""

    PX4 = "px4"
    ARDUPILOT = "ardupilot"


class LinkBackend(enum.Enum):
    """Which library talks MAVLink for us."""

    PYMAVLINK = "pymavlink"
    MAVSDK = "mavsdk"


class MocapSourceKind(enum.Enum):
    """Where mocap poses come from."""

    BUS = "bus"  # a Zenoh topic (the simulator publishes there, so do mocap bridges)
    MOTIONCAPTURE = "motioncapture"  # the motioncapture library: vicon, optitrack, qualisys, vrpn, mock, ...


class BusMode(enum.Enum):
    """Zenoh session mode."""

    PEER = "peer"
    CLIENT = "client"
    ROUTER = "router"


@dataclass(frozen=True, slots=True)
class TransformConfig:
    """A rigid transform in config: translation plus one rotation form.

    Give at most one of ``rpy_deg`` (extrinsic roll, pitch, yaw about x, y, z, degrees),
    ``quat_wxyz`` or ``euler_deg`` with ``euler_seq`` (scipy convention, e.g. ``"xz"`` for
    "rotate about x, then about z" in the fixed frame).
    """

    translation_m: tuple[float, ...] = setting((0.0, 0.0, 0.0), length=3, help="x, y, z in metres")
    rpy_deg: tuple[float, ...] | None = setting(None, length=3, help="roll, pitch, yaw in degrees")
    quat_wxyz: tuple[float, ...] | None = setting(None, length=4, help="unit quaternion w, x, y, z")
    euler_seq: str = setting("", help="scipy Euler sequence such as 'xz' (lower case = extrinsic)")
    euler_deg: tuple[float, ...] | None = setting(None, help="angles in degrees for euler_seq")

    def to_transform(self) -> Transform:
        t = np.asarray(self.translation_m, dtype=np.float64)
        if self.quat_wxyz is not None:
            return Transform.from_quat_wxyz(t, self.quat_wxyz)
        if self.euler_deg is not None:
            return Transform.from_xyz_euler_deg(t, self.euler_seq, self.euler_deg)
        if self.rpy_deg is not None:
            return Transform.from_xyz_euler_deg(t, "xyz", self.rpy_deg)
        return Transform(translation=t)

    @staticmethod
    def _check(obj: TransformConfig, path: str, key: str) -> None:
        given = [n for n in ("rpy_deg", "quat_wxyz", "euler_deg") if getattr(obj, n) is not None]
        if len(given) > 1:
            raise ConfigError(path, key, f"both {given[0]} and {given[1]} given", "give one rotation form only")
        if obj.quat_wxyz is not None:
            n = math.sqrt(sum(x * x for x in obj.quat_wxyz))
            if abs(n - 1.0) > 1e-3:
                raise ConfigError(
                    path, f"{key}.quat_wxyz", f"norm is {n:.4f}, not 1", "give a unit quaternion", obj.quat_wxyz
                )
        if obj.euler_deg is not None and (not obj.euler_seq or len(obj.euler_seq) != len(obj.euler_deg)):
            raise ConfigError(
                path,
                f"{key}.euler_seq",
                f"sequence {obj.euler_seq!r} does not match {len(obj.euler_deg)} angles",
                "give one axis letter per angle, e.g. euler_seq = 'xz' with two angles",
                obj.euler_seq,
            )


@dataclass(frozen=True, slots=True)
class VehicleConfig:
    namespace: str = setting("uav1", help="bus namespace of this vehicle, e.g. 'uav1'")
    autopilot: Autopilot = setting(Autopilot.PX4, help="px4 or ardupilot")


@dataclass(frozen=True, slots=True)
class LinkConfig:
    url: str = setting("udpout:127.0.0.1:14540", help="MAVLink connection string")
    system_id: int = setting(0, min=0, max=255, help="the autopilot's MAVLink system id (0: the first heard)")
    backend: LinkBackend = setting(LinkBackend.PYMAVLINK, help="pymavlink or mavsdk")
    baud: int = setting(57600, min=1200, max=4_000_000, help="serial baud rate")
    source_system: int = setting(255, min=1, max=255, help="our MAVLink system id")
    source_component: int = setting(191, min=1, max=255, help="our MAVLink component id (191 = onboard computer)")
    heartbeat_timeout_s: float = setting(5.0, min=0.1, max=120.0, help="how long to wait for the autopilot")
    command_timeout_s: float = setting(3.0, min=0.1, max=60.0, help="how long to wait for COMMAND_ACK")
    setpoint_rate_hz: float = setting(50.0, min=2.0, max=500.0, help="setpoint stream rate")
    setpoint_timeout_s: float = setting(0.5, min=0.05, max=10.0, help="caller silence before an explicit stop")
    pose_telemetry_hz: float = setting(
        -1.0, min=-1.0, max=200.0,
        help="rate the pymavlink link asks for the autopilot's own position and attitude; 0: off; -1 (auto): 50 Hz, "
        "none for a fleet (it flies on mocap)",
    )
    signing_key_hex: str = setting("", help="MAVLink 2 signing key: 64 hex digits (32 bytes); empty = off")


@dataclass(frozen=True, slots=True)
class MocapConfig:
    source: MocapSourceKind = setting(MocapSourceKind.BUS, help="bus or motioncapture")
    body: str = setting("uav1", help="rigid body name of the vehicle")
    system_type: str = setting("vicon", help="motioncapture system: vicon, optitrack, qualisys, vrpn, mock, ...")
    hostname: str = setting("", help="mocap server address for the motioncapture library")
    options: dict[str, str] = setting(default_factory=dict, help="extra motioncapture options (strings)")
    T_world_mocap: TransformConfig = setting(default_factory=TransformConfig, help="mocap frame in the world")
    stale_after_s: float = setting(0.2, min=0.001, max=10.0, help="pose age that counts as stale")
    predict_latency_ms: float = setting(
        0.0, min=0.0, max=200.0,
        help="known mocap latency: the runner's controller tracks the pose predicted this far ahead (0: off)",
    )


@dataclass(frozen=True, slots=True)
class BusConfig:
    mode: BusMode = setting(BusMode.PEER, help="peer, client or router")
    connect: tuple[str, ...] = setting((), help="Zenoh endpoints to connect to, e.g. 'tcp/192.168.1.10:7447'")
    listen: tuple[str, ...] = setting((), help="Zenoh endpoints to listen on")
    well_known_port: int = setting(7447, min=1, max=65535, help="loopback port of the embedded default")
    multicast_scouting: bool = setting(False, help="multicast discovery (off: explicit endpoints only)")
    tls_root_ca: str = setting("", help="PEM file of the CA for tls/ endpoints")
    tls_cert: str = setting("", help="PEM certificate for tls/ endpoints")
    tls_key: str = setting("", help="PEM private key for tls/ endpoints")
    zenoh_config_file: str = setting("", help="a full Zenoh JSON5 config (access control etc.) to start from")

    def with_endpoints(self, connect: Sequence[str] | None = None, listen: Sequence[str] | None = None) -> BusConfig:
        """This config with the command line's ``--connect`` / ``--listen`` endpoints (None keeps the config's)."""
        out = self
        if connect:
            out = dataclasses.replace(out, connect=tuple(connect))
        if listen:
            out = dataclasses.replace(out, listen=tuple(listen))
        return out


@dataclass(frozen=True, slots=True)
class SimConfig:
    """The simulated lab. Its mocap system sits where ``[mocap.T_world_mocap]`` says the lab's
    does, and publishes in that (mocap) frame, so consumers must apply the calibration.

    Known errors for calibration to find (all off by default): the camera's time offset and
    clock drift, the mocap's latency, and a camera mount that differs from the configured one
    (``flightkit.sim.timing_errors``, ``docs/calibration.md``)."""

    speed: float = setting(1.0, min=0.01, max=1000.0, help="simulated seconds per wall second")
    mocap_rate_hz: float = setting(120.0, min=1.0, max=1000.0, help="simulated mocap rate")
    mocap_noise_m: float = setting(0.0, min=0.0, max=1.0, help="std-dev of mocap position noise")
    velocity_time_constant_s: float = setting(0.25, min=0.01, max=5.0, help="velocity tracking lag")
    max_accel_m_s2: float = setting(4.0, min=0.1, max=50.0, help="acceleration limit")
    wind_gust_m_s: float = setting(0.0, min=0.0, max=20.0, help="peak wind gust speed")
    battery_endurance_s: float = setting(
        0.0, min=0.0, max=36000.0, help="armed time on a full battery, s (0 = the firmware's: ArduPilot 450, PX4 1200)"
    )
    camera_time_offset_ms: float = setting(
        0.0, min=-1000.0, max=1000.0, help="how late the simulated camera stamps its frames, ms"
    )
    camera_drift_ppm: float = setting(
        0.0, min=-1000.0, max=1000.0, help="how fast the simulated camera clock runs, ppm"
    )
    mocap_latency_ms: float = setting(
        0.0, min=0.0, max=500.0, help="capture-to-stamp delay of the simulated mocap poses, ms"
    )
    true_T_body_camera: TransformConfig | None = setting(
        None, help="where the simulated camera really is mounted (default: camera.T_body_camera)"
    )
    autopilot_params: dict[str, float] = setting(
        default_factory=dict,
        help="parameters of the simulated autopilot over the lab set-up of docs/hardware.md, e.g. FS_GCS_ENABLE = 0",
    )


@dataclass(frozen=True, slots=True)
class CameraConfig:
    """The vehicle's camera: resolution, rate, pinhole intrinsics and mounting.

    Intrinsics default to a 90-degree horizontal field of view when ``fx`` is 0.
    ``T_body_camera`` maps OpenCV camera coordinates (x right, y down, z forward) into the
    FLU body frame; the default is the lab's own mount (135 degrees about x, then 90
    degrees about z, both about the fixed body axes).
    """

    enabled: bool = setting(True, help="publish camera streams from the simulator")
    width_px: int = setting(640, min=160, max=1920, help="image width in pixels")
    height_px: int = setting(480, min=120, max=1080, help="image height in pixels")
    rate_hz: float = setting(30.0, min=0.5, max=120.0, help="frame rate")
    fx_px: float = setting(0.0, min=0.0, max=10000.0, help="focal length x in pixels (0 = 90 deg HFOV)")
    fy_px: float = setting(0.0, min=0.0, max=10000.0, help="focal length y in pixels (0 = same as fx)")
    cx_px: float = setting(-1.0, min=-1.0, max=10000.0, help="principal point x (-1 = image centre)")
    cy_px: float = setting(-1.0, min=-1.0, max=10000.0, help="principal point y (-1 = image centre)")
    stereo_baseline_m: float = setting(0.05, min=0.001, max=2.0, help="stereo baseline")
    depth_max_m: float = setting(10.0, min=0.1, max=65.0, help="depth beyond this is reported invalid (0)")
    T_body_camera: TransformConfig = setting(
        default_factory=lambda: TransformConfig(
            translation_m=(0.08, 0.0, -0.02), euler_seq="xz", euler_deg=(135.0, 90.0)
        ),
        help="camera pose in the body frame",
    )

    def intrinsics(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) in pixels with the defaults resolved."""
        fx = self.fx_px if self.fx_px > 0 else self.width_px / 2.0  # tan(45 deg) = 1
        fy = self.fy_px if self.fy_px > 0 else fx
        cx = self.cx_px if self.cx_px >= 0 else (self.width_px - 1) / 2.0
        cy = self.cy_px if self.cy_px >= 0 else (self.height_px - 1) / 2.0
        return fx, fy, cx, cy


@dataclass(frozen=True, slots=True)
class FleetVehicleConfig:
    """One vehicle of a fleet: a ``[[vehicles]]`` entry; an empty field takes the lab's value."""

    name: str = setting("", help="the vehicle's bus namespace, e.g. 'uav2' (required)")
    body: str = setting("", help="its mocap rigid body (default: the name)")
    url: str = setting("", help="its MAVLink connection string (default: link.url)")
    system_id: int = setting(0, min=0, max=255, help="its autopilot's MAVLink system id (0: the first heard)")
    autopilot: str = setting("", help="px4 or ardupilot (default: vehicle.autopilot)")
    backend: str = setting("", help="pymavlink or mavsdk (default: link.backend)")
    start_m: tuple[float, ...] = setting((), help="simulated lab only: where it stands at start, world x, y, z")
    geofence_min_m: tuple[float, ...] = setting((), help="its own geofence corner (default: the plan's)")
    geofence_max_m: tuple[float, ...] = setting((), help="its own geofence corner (default: the plan's)")

    @staticmethod
    def _check(obj: FleetVehicleConfig, path: str, key: str) -> None:
        def bad(field_: str, problem: str, fix: str, value: object) -> ConfigError:
            return ConfigError(path, f"{key}.{field_}", problem, fix, value)

        if not obj.name:
            raise bad("name", "missing vehicle name", "add name = 'uav2' (its bus namespace)", obj.name)
        if obj.autopilot and obj.autopilot not in {a.value for a in Autopilot}:
            raise bad("autopilot", f"unknown autopilot {obj.autopilot!r}", "use 'px4' or 'ardupilot'", obj.autopilot)
        if obj.backend and obj.backend not in {b.value for b in LinkBackend}:
            raise bad("backend", f"unknown backend {obj.backend!r}", "use 'pymavlink' or 'mavsdk'", obj.backend)
        for name in ("start_m", "geofence_min_m", "geofence_max_m"):
            v = getattr(obj, name)
            if v and len(v) != 3:
                raise bad(name, f"expected 3 numbers, got {len(v)}", "give [x, y, z] in metres", v)
        if bool(obj.geofence_min_m) != bool(obj.geofence_max_m):
            raise bad("geofence_max_m", "a geofence needs both corners", "give geofence_min_m and geofence_max_m", None)


@dataclass(frozen=True, slots=True)
class LabConfig:
    """A whole lab set-up, as loaded from one TOML file.

    A fleet lab lists its vehicles as ``[[vehicles]]`` entries (:class:`FleetVehicleConfig`);
    :meth:`fleet` gives one config per vehicle. Without entries the lab has one vehicle.
    """

    vehicle: VehicleConfig = setting(default_factory=VehicleConfig)
    link: LinkConfig = setting(default_factory=LinkConfig)
    mocap: MocapConfig = setting(default_factory=MocapConfig)
    bus: BusConfig = setting(default_factory=BusConfig)
    sim: SimConfig = setting(default_factory=SimConfig)
    camera: CameraConfig = setting(default_factory=CameraConfig)
    source_path: str = setting("<defaults>", help="where this config came from (set by the loader)")
    capability_tables: dict[str, Any] = field(default_factory=dict, metadata={"init_only_loader": True})
    vehicles: tuple[FleetVehicleConfig, ...] = field(default=(), metadata={"init_only_loader": True})

    def fleet(self) -> tuple[LabConfig, ...]:
        """One config per vehicle (this one when the lab lists no ``[[vehicles]]``): the lab's with
        that vehicle's namespace, mocap body, link and autopilot."""
        if not self.vehicles:
            return (self,)
        out = []
        for v in self.vehicles:
            link = dataclasses.replace(
                self.link,
                url=v.url or self.link.url,
                system_id=v.system_id,
                backend=LinkBackend(v.backend) if v.backend else self.link.backend,
            )
            vehicle = VehicleConfig(
                namespace=v.name, autopilot=Autopilot(v.autopilot) if v.autopilot else self.vehicle.autopilot
            )
            mocap = dataclasses.replace(self.mocap, body=v.body or v.name)
            out.append(dataclasses.replace(self, vehicle=vehicle, link=link, mocap=mocap, vehicles=()))
        return tuple(out)

    def check_shared_links(self) -> None:
        """Before connecting: vehicles naming one link URL must each give a system id and use pymavlink.

        Raises:
            ConfigError: naming the vehicle and what to change.
        """
        configs = self.fleet()
        by_url: dict[str, list[int]] = {}
        for i, c in enumerate(configs):
            by_url.setdefault(c.link.url.strip(), []).append(i)
        for url, idx in by_url.items():
            if len(idx) < 2:
                continue
            for i in idx:
                c = configs[i]
                if c.link.backend is LinkBackend.MAVSDK:
                    raise ConfigError(
                        self.source_path, f"vehicles[{i}].backend", f"{c.vehicle.namespace} shares {url} with "
                        "other vehicles", "the MAVSDK backend opens one connection per vehicle; use backend = "
                        "pymavlink for a shared radio", c.link.backend.value,
                    )
                if not c.link.system_id:
                    raise ConfigError(
                        self.source_path, f"vehicles[{i}].system_id", f"{c.vehicle.namespace} shares {url} with "
                        "other vehicles but names no system id", "give each vehicle on a shared link its "
                        "autopilot's system id (SYSID_THISMAV / MAV_SYS_ID)", 0,
                    )

    def vehicle_entry(self, name: str) -> FleetVehicleConfig | None:
        """The ``[[vehicles]]`` entry named ``name`` (None in a one-vehicle lab or when absent)."""
        return next((v for v in self.vehicles if v.name == name), None)

    def section(self, name: str, cls: type[T]) -> T:
        """Validate a capability table (e.g. ``[report]``) into ``cls``; defaults when absent.

        Capability packages (trajectories, capture, estimation) own their sections; the core
        only carries the raw table, so the layering stays one-way.
        """
        if name not in CAPABILITY_SECTIONS:
            raise ConfigError(
                self.source_path,
                name,
                "is not a registered capability section",
                f"use one of {', '.join(CAPABILITY_SECTIONS)} (or register it in CAPABILITY_SECTIONS)",
                name,
            )
        return load_section(cls, self.capability_tables.get(name, {}), path=self.source_path, prefix=name)


# Top-level tables that belong to capability packages: accepted by load_config and handed over
# raw (LabConfig.section validates them with the owner's dataclass).
CAPABILITY_SECTIONS = ("control", "safety", "report", "capture", "estimation", "mapframe")

def load_config(path: str | Path | None = None, table: Mapping[str, Any] | None = None) -> LabConfig:
    """Load a lab config from a TOML file (or an in-memory table); no argument gives defaults."""
    if path is not None:
        data = load_toml(path)
        src = str(path)
    else:
        data = dict(table or {})
        src = "<dict>"
    data = {k: v for k, v in data.items() if k not in ("source_path", "capability_tables")}
    extra = {k: data.pop(k) for k in list(data) if k in CAPABILITY_SECTIONS}
    for name, table in extra.items():
        if not isinstance(table, Mapping):
            raise ConfigError(src, name, f"expected a table, got {table!r}", f"write it as [{name}]", table)
    vehicles = _load_vehicles(data.pop("vehicles", []), src)
    cfg = load_section(LabConfig, data, path=src)
    return dataclasses.replace(cfg, source_path=src, capability_tables=extra, vehicles=vehicles)


def _load_vehicles(entries: Any, path: str) -> tuple[FleetVehicleConfig, ...]:
    """Validate the ``[[vehicles]]`` array: each entry, then unique names, bodies and links."""
    if not isinstance(entries, list) or not all(isinstance(e, Mapping) for e in entries):
        raise ConfigError(
            path, "vehicles", "expected an array of tables", "write each vehicle as [[vehicles]]", entries
        )
    out = tuple(
        load_section(FleetVehicleConfig, e, path=path, prefix=f"vehicles[{i}]") for i, e in enumerate(entries)
    )
    seen: dict[object, int] = {}
    for i, v in enumerate(out):
        for what, ident in (("name", v.name), ("body", v.body or v.name), ("link", (v.url, v.system_id))):
            if v.url == "" and what == "link":
                continue  # the lab's link.url: told apart by system_id below if needed
            first = seen.setdefault((what, ident), i)
            if first != i:
                raise ConfigError(
                    path,
                    f"vehicles[{i}].{'url' if what == 'link' else what}",
                    f"vehicles[{first}] and vehicles[{i}] have the same {what} {ident!r}",
                    "give every vehicle its own name, mocap body and MAVLink connection (url or system_id)",
                    ident,
                )
    return out

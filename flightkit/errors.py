"""The one exception tree of flightkit.

::

    FlightkitError
    ├── ConfigError            bad TOML: names file, key, value and the fix
    │   └── PlanError          a pattern or plan that cannot be flown as given (parameters, geofence)
    ├── LinkError              anything between us and the autopilot
    │   ├── EndpointError      a connection string we cannot open (bad syntax, port in use)
    │   ├── LinkTimeout        nothing answered in time (heartbeat, COMMAND_ACK, state change)
    │   └── CommandRejected    the autopilot answered "no" (carries its reason and STATUSTEXT)
    ├── FrameError             a pose in a frame that cannot be placed in the world
    ├── TransformError         an array that is not a 3-vector or rigid transform (also a ValueError)
    ├── SetpointError          a setpoint that is out of range or malformed
    ├── MocapError             mocap source failures
    │   └── MocapBodyMissing   the rigid body is not visible (carries the bodies that are)
    ├── BusError               Zenoh session or encoding problems
    ├── CaptureError           recording, recovery, export
    ├── DatasetError           an unreadable or incomplete dataset folder / recording
    ├── EstimationError        visual odometry and evaluation
    ├── CalibrationError       a time offset / hand-eye / clock estimate the data cannot support
    ├── SafetyAbort            the supervisor ended a flight (carries the fault)
    ├── SimError               the simulated lab got impossible parameters or a call out of order
    └── ProtocolError          the serial/BLE pose-reporting protocol

Every message says what is wrong, the value involved and what to do about it. Context is
kept in public attributes so callers can react without parsing text.

Library code raises only these (``tests/unit/test_errors_raised.py`` scans for bare
``ValueError`` / ``RuntimeError``), value types' ``__post_init__`` included: a value built in
Python with wrong fields raises the error of its domain (a :class:`ConfigError` names the class
in angle brackets as its ``path``, e.g. ``"<SessionConfig>"``). Only :class:`TransformError`
is also a ``ValueError``: it is the argument check of numeric functions, where numpy's
convention is ``ValueError``.
"""

from __future__ import annotations

__all__ = [
    "BusError",
    "CalibrationError",
    "CaptureError",
    "CommandRejected",
    "ConfigError",
    "DatasetError",
    "EndpointError",
    "EstimationError",
    "FlightkitError",
    "FrameError",
    "LinkError",
    "LinkTimeout",
    "MocapBodyMissing",
    "MocapError",
    "PlanError",
    "ProtocolError",
    "SafetyAbort",
    "SetpointError",
    "SimError",
    "TransformError",
]


class FlightkitError(Exception):
    """Base class of every error flightkit raises on purpose."""


class ConfigError(FlightkitError):
    """A configuration value is missing, unknown, of the wrong type or out of range.

    Attributes:
        path: the file (or "<dict>" for in-memory config).
        key: dotted key, e.g. ``"link.url"``.
        value: the offending value (None when missing).
        fix: what the user should do.
    """

    def __init__(self, path: str, key: str, problem: str, fix: str, value: object = None) -> None:
        self.path = path
        self.key = key
        self.value = value
        self.problem = problem
        self.fix = fix
        super().__init__(f"{path}: {key}: {problem}; {fix}")


class PlanError(ConfigError):
    """A pattern or plan cannot be flown as given: its parameters make no flight (a
    non-positive speed, corners that coincide, laps that do not close) or it leaves the
    geofence.

    Raised by the pattern classes of ``trajectories`` when built in Python and by the runner;
    a plan file's loader re-raises a pattern's as a :class:`ConfigError` naming the file and
    ``pattern.<key>``. ``PlanError("message")`` alone is fine where no single key is at fault.

    Attributes:
        pattern: the pattern's name, e.g. ``"circle"`` ("" when not known; ``path`` is then
            ``"<plan>"``).
        key, value, problem, fix: as :class:`ConfigError` (key "" when no single key is at fault).
    """

    def __init__(self, problem: str, fix: str = "", *, pattern: str = "", key: str = "", value: object = None) -> None:
        self.pattern = pattern
        super().__init__(pattern or "<plan>", key, problem, fix, value)
        where = ": ".join(part for part in (pattern, key) if part)
        text = f"{where}: {problem}" if where else problem
        self.args = (f"{text}; {fix}" if fix else text,)


class LinkError(FlightkitError):
    """Communication with the autopilot failed."""


class EndpointError(LinkError):
    """A connection string is malformed or cannot be opened (e.g. the port is in use)."""


class LinkTimeout(LinkError):
    """Nothing (or not the expected answer) arrived before a timeout.

    Attributes:
        what: what we waited for, e.g. ``"HEARTBEAT"``.
        timeout_s: how long we waited.
    """

    def __init__(self, message: str, what: str = "", timeout_s: float = 0.0) -> None:
        self.what = what
        self.timeout_s = timeout_s
        super().__init__(message)


class CommandRejected(LinkError):
    """The autopilot refused a command.

    Attributes:
        command: the MAVLink command or operation name, e.g. ``"MAV_CMD_COMPONENT_ARM_DISARM"``.
        result: the autopilot's result name, e.g. ``"TEMPORARILY_REJECTED"``.
        statustext: the STATUSTEXT lines the autopilot sent around the refusal (may be empty).
    """

    def __init__(self, command: str, result: str, statustext: tuple[str, ...] = (), hint: str = "") -> None:
        self.command = command
        self.result = result
        self.statustext = statustext
        reason = f" ({'; '.join(statustext)})" if statustext else ""
        tail = f"; {hint}" if hint else ""
        super().__init__(f"autopilot refused {command}: {result}{reason}{tail}")


class FrameError(FlightkitError):
    """A pose names a frame (``frame_id``) that cannot be placed in the world.

    Attributes:
        frame_id: the frame named.
        known: the frames that can be placed.
    """

    def __init__(self, frame_id: str, known: tuple[str, ...]) -> None:
        self.frame_id = frame_id
        self.known = known
        super().__init__(
            f"poses in frame {frame_id!r} cannot be placed in the world (known frames: {', '.join(known)}); "
            "publish them in one of these frames or give that frame's transform to the world"
        )


class TransformError(FlightkitError, ValueError):
    """An array is not the 3-vector, rotation or rigid transform a function needs (its shape,
    or values that are not finite). Also a ``ValueError``, as numpy's own shape errors are."""


class SetpointError(FlightkitError):
    """A setpoint is malformed or outside the configured limits."""


class MocapError(FlightkitError):
    """The motion-capture source failed."""


class MocapBodyMissing(MocapError):
    """The requested rigid body is not in the mocap stream.

    Attributes:
        body: the requested body name.
        visible: the body names that are visible.
    """

    def __init__(self, body: str, visible: tuple[str, ...]) -> None:
        self.body = body
        self.visible = visible
        seen = ", ".join(visible) if visible else "none"
        super().__init__(
            f"mocap body {body!r} is not visible (visible bodies: {seen}); "
            "check the body name in the config and that the markers are tracked"
        )


class BusError(FlightkitError):
    """The message bus (Zenoh) failed or a message could not be encoded/decoded."""


class CaptureError(FlightkitError):
    """Recording, recovery or export failed."""


class DatasetError(FlightkitError):
    """A dataset folder or recording cannot be read (unknown layout, missing files)."""


class EstimationError(FlightkitError):
    """Visual odometry or its evaluation failed."""


class CalibrationError(FlightkitError):
    """A calibration (time offset, drift, hand-eye, clock offset) cannot be estimated from the data given.

    Attributes:
        quantity: what was being estimated, e.g. ``"time offset"`` or ``"T_body_camera"``.
    """

    def __init__(self, message: str, quantity: str = "") -> None:
        self.quantity = quantity
        super().__init__(message)


class SafetyAbort(FlightkitError):
    """The safety supervisor ended a flight.

    Attributes:
        reason: short machine-readable fault name, e.g. ``"mocap_stale"``.
    """

    def __init__(self, reason: str, message: str) -> None:
        self.reason = reason
        super().__init__(message)


class SimError(FlightkitError):
    """The simulated lab (clock, dynamics, autopilot, synthetic sequences) was given parameters
    it cannot simulate, or was used out of order (e.g. before it was started)."""


class ProtocolError(FlightkitError):
    """The pose-reporting protocol failed (bad frame, handshake failure, link lost)."""

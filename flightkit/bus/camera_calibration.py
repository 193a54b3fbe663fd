"""A camera's calibration on request: ``<ns>/camera/<name>/calibration``, a Zenoh queryable.

A camera's publisher answers it with :meth:`~flightkit.bus.streams.CameraModel.as_metadata` (JSON of
strings), which carries what ``sensor_msgs/CameraInfo`` cannot: the rolling shutter's ``readout_s``.
The recorder asks once, at a camera's first camera_info (:mod:`capture.bus_recorder`); a camera that
does not answer (another driver, an older flightkit) is recorded without a readout.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable, Mapping
from typing import Self

import zenoh

from flightkit.errors import BusError

__all__ = ["CALIBRATION_SUFFIX", "CalibrationServer", "ask_calibration", "calibration_key"]

logger = logging.getLogger(__name__)

CALIBRATION_SUFFIX = "calibration"
"""The last chunk of a camera's calibration key, in place of ``camera_info``."""


def calibration_key(info_key: str) -> str:
    """The calibration key beside a camera_info key: ``uav1/camera/color/camera_info`` ->
    ``uav1/camera/color/calibration``.

    Raises:
        BusError: ``info_key`` does not end in ``/camera_info``.
    """
    head, sep, last = info_key.strip("/").rpartition("/")
    if not sep or last != "camera_info":
        raise BusError(f"{info_key!r} is not a camera_info key; give one such as 'uav1/camera/color/camera_info'")
    return f"{head}/{CALIBRATION_SUFFIX}"


class CalibrationServer:
    """Answer queries on ``key`` with ``fields`` as a JSON object of strings.

    Args:
        session: an open Zenoh session.
        key: the calibration key (:func:`calibration_key`).
        fields: the camera's calibration as strings (e.g. ``CameraModel.as_metadata()``).

    Close with :meth:`close` (or ``with``).

    Raises:
        BusError: Zenoh refuses the key.
    """

    def __init__(self, session: zenoh.Session, key: str, fields: Mapping[str, str]) -> None:
        self.key = key
        self._payload = json.dumps({str(k): str(v) for k, v in fields.items()}, sort_keys=True).encode()
        self.answered = 0
        try:
            self._q: zenoh.Queryable[None] | None = session.declare_queryable(key, self._on_query)
        except zenoh.ZError as exc:
            raise BusError(f"cannot serve a camera calibration on {key!r}: {exc}; use a key without wildcards") from exc

    def _on_query(self, query: zenoh.Query) -> None:
        try:
            query.reply(self.key, self._payload)
            self.answered += 1
        except Exception:  # a query whose asker went away
            logger.debug("calibration query on %s could not be answered", self.key, exc_info=True)

    def close(self) -> None:
        """Undeclare the queryable; idempotent."""
        q, self._q = self._q, None
        if q is not None:
            try:
                q.undeclare()
            except zenoh.ZError:  # the session is already closed
                pass

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def ask_calibration(
    session: zenoh.Session, key: str, on_done: Callable[[dict[str, str]], None], timeout_s: float = 2.0
) -> None:
    """Query ``key`` and call ``on_done`` once, on a Zenoh thread, with the first well-formed
    answer's fields (``{}`` when no camera answers within ``timeout_s``). Returns immediately; may
    be called from a Zenoh callback."""
    lock = threading.Lock()
    got: dict[str, str] = {}
    done: list[bool] = []

    def on_reply(reply: zenoh.Reply) -> None:
        if reply.ok is None:
            return
        try:
            data = json.loads(reply.ok.payload.to_bytes())
        except ValueError:
            logger.warning("the calibration answer on %s is not JSON; ignored", key)
            return
        if not isinstance(data, dict):
            logger.warning("the calibration answer on %s is not a JSON object; ignored", key)
            return
        with lock:
            if not got:
                got.update({str(k): str(v) for k, v in data.items()})

    def on_finished() -> None:
        with lock:
            if done:
                return
            done.append(True)
            fields = dict(got)
        on_done(fields)

    try:
        session.get(key, zenoh.handlers.Callback(on_reply, on_finished), timeout=timeout_s)
    except zenoh.ZError as exc:
        logger.warning("cannot ask %s for its calibration (%s); going on without it", key, exc)
        on_finished()

"""The thread every live capture source runs on: start/stop, published counts, errors, pacing.

A source subclasses :class:`SourceThread`, implements :meth:`SourceThread._run_loop` (which
returns when the source is exhausted or :attr:`SourceThread.stopping` is set) and calls
:meth:`SourceThread._count` after each published item. Blocking libraries (OpenCV,
pyrealsense2, libmotioncapture) live only on that thread (STYLE 6).
"""
from __future__ import annotations

import logging
import threading
from typing import Self

from flightkit.clock import Clock, sleep_until
from flightkit.errors import CaptureError
from flightkit.lifetime import Running

__all__ = ["SourceThread"]

logger = logging.getLogger(__name__)

class SourceThread(Running):
    """One daemon thread publishing a source; ``with`` starts and stops it.

    Attributes:
        published: items published so far (frames, poses or messages: the source says which).
        finished: True once the source ran out (end of a file) or stopped.
        error: the exception that ended the thread early (None while fine).
    """

    thread_name = "capture-source"
    what = "items"

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.published = 0
        self.error: BaseException | None = None
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._done = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ to implement

    def _run_loop(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def keys(self) -> list[str]:  # pragma: no cover - abstract
        """The bus keys the source publishes on."""
        raise NotImplementedError

    def _close_outputs(self) -> None:
        """Undeclare publishers; called by :meth:`stop` after the thread ended."""

    # ------------------------------------------------------------------ for subclasses

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def _count(self, n: int = 1) -> None:
        with self._cond:
            self.published += n
            self._cond.notify_all()

    def _sleep_until(self, deadline_s: float) -> bool:
        """Sleep on the clock until ``deadline_s`` (clock seconds); False if stopped first."""
        return sleep_until(self.clock, deadline_s, self._stop)

    def _pause(self, duration_s: float) -> bool:
        """Sleep ``duration_s`` of clock time; False if stopped first."""
        return self._sleep_until(self.clock.monotonic_s() + duration_s)

    # ------------------------------------------------------------------ public

    @property
    def finished(self) -> bool:
        return self._done.is_set()

    def start(self) -> Self:
        """Start the thread; returns immediately."""
        if self._thread is None:
            self._stop.clear()
            self._done.clear()
            self._thread = threading.Thread(target=self._main, name=self.thread_name, daemon=True)
            self._thread.start()
        return self

    def _main(self) -> None:
        try:
            self._run_loop()
        except Exception as exc:  # a closed session, a driver failure: keep it for the caller
            if not self._stop.is_set():
                logger.error("%s stopped: %s", self.thread_name, exc)
                with self._cond:
                    self.error = exc
        finally:
            with self._cond:
                self._done.set()
                self._cond.notify_all()

    def wait_published(self, count: int, timeout_s: float) -> int:
        """Block until ``count`` items were published (wall-clock timeout); returns the count.

        Raises:
            CaptureError: the thread failed, the source ended short of ``count``, or the
                timeout passed.
        """
        with self._cond:
            self._cond.wait_for(
                lambda: self.published >= count or self.error is not None or self._done.is_set(), timeout_s
            )
            if self.published >= count:
                return self.published
            if self.error is not None:
                raise CaptureError(f"{self.thread_name} stopped: {self.error}") from self.error
            if self._done.is_set():
                raise CaptureError(
                    f"{self.thread_name} ended after {self.published} of {count} {self.what}; the source ran out"
                )
            raise CaptureError(
                f"{self.thread_name} published {self.published} of {count} {self.what} within {timeout_s:g} s; "
                "is the source delivering and the clock running?"
            )

    def wait_finished(self, timeout_s: float) -> int:
        """Block until the source ran out (end of file); returns the count published.

        Raises:
            CaptureError: the thread failed or did not finish within ``timeout_s`` (wall clock).
        """
        if not self._done.wait(timeout_s):
            raise CaptureError(
                f"{self.thread_name} did not finish within {timeout_s:g} s ({self.published} {self.what} so far)"
            )
        if self.error is not None:
            raise CaptureError(f"{self.thread_name} stopped: {self.error}") from self.error
        return self.published

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the thread and undeclare the publishers; idempotent."""
        self._stop.set()
        t, self._thread = self._thread, None
        if t is not None:
            # A blocking driver call may not return (a stalled device): the daemon is abandoned.
            t.join(timeout=timeout_s)
        self._close_outputs()

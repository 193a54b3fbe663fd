"""Lifetimes: one convention for everything that owns a thread, a socket, a port or a file.

- Objects that run on their own threads (simulated lab, publishers, capture sources, serial
  transports, the mapping server) have ``start() -> Self``, which returns at once, and an
  idempotent ``stop()``; they derive from :class:`Running`, which makes them usable both as
  ``with obj:`` and ``async with obj:`` (``start`` on entry, ``stop`` on exit).
- Objects that live on the event loop (vehicle links, mocap sources, bus subscriptions read
  with ``await``) open and close asynchronously and are used with ``async with`` only.

A ``stop()`` must be safe to call twice and from a ``finally``; it never raises for an object
that did not start.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from types import TracebackType
from typing import Self

__all__ = ["Running"]


class Running(ABC):
    """``start()``/``stop()`` plus ``with`` and ``async with`` for thread-owning objects."""

    @abstractmethod
    def start(self) -> Self:
        """Start the object's work; returns at once."""

    @abstractmethod
    def stop(self) -> None:
        """Stop the work and release what the object holds; idempotent."""

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    async def __aenter__(self) -> Self:
        return self.start()

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

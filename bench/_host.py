"""What the host did to this VM while a benchmark ran: CPU time stolen by the hypervisor.

On a virtual machine the host can deschedule a vCPU for milliseconds at a time (``steal`` in
/proc/stat). No code in the guest can make up for that, so timing benchmarks print how much
was stolen while each row ran: a p99 from a row with steal measured the host, not us.
"""

from __future__ import annotations

import os

_TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")


def steal_s() -> float:
    """CPU seconds stolen from this machine (all CPUs) since boot; 0.0 where Linux does not say."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            fields = f.readline().split()
    except OSError:
        return 0.0
    return int(fields[8]) * _TICK_S if fields[0] == "cpu" and len(fields) > 8 else 0.0


class StealMeter:
    """``with StealMeter() as m: ...`` then ``m.ms``: milliseconds stolen during the block."""

    def __enter__(self) -> StealMeter:
        self._t0 = steal_s()
        self.ms = 0.0
        return self

    def __exit__(self, *exc: object) -> None:
        self.ms = (steal_s() - self._t0) * 1e3

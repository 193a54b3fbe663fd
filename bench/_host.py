"""What the host did to this VM while a benchmark ran: CPU time stolen by the hypervisor, and
busy time of the whole machine and of another process (a benchmark's simulator, say).

On a virtual machine the host can deschedule a vCPU for milliseconds at a time (``steal`` in
/proc/stat). No code in the guest can make up for that, so timing benchmarks print how much
was stolen while each row ran: a p99 from a row with steal measured the host, not us.
"""

from __future__ import annotations

import os

_TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")


def pin_one_cpu(cpu: int | None = None) -> None:
    """Run this process on one CPU: ``cpu``, or the last one it may use (where Linux allows)."""
    if hasattr(os, "sched_setaffinity"):
        cpus = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpus[-1] if cpu is None else cpu})


def _cpu_fields() -> list[str]:
    """The all-CPU line of /proc/stat, split (``cpu user nice system idle iowait irq softirq steal ...``)."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            return f.readline().split()
    except OSError:
        return []


def steal_s() -> float:
    """CPU seconds stolen from this machine (all CPUs) since boot; 0.0 where Linux does not say."""
    fields = _cpu_fields()
    return int(fields[8]) * _TICK_S if fields and fields[0] == "cpu" and len(fields) > 8 else 0.0


def busy_s() -> float:
    """CPU seconds every core of this machine has spent busy (not idle, not waiting for I/O) since boot."""
    ticks = [int(x) for x in _cpu_fields()[1:9]]
    return (sum(ticks) - ticks[3] - ticks[4]) * _TICK_S if len(ticks) == 8 else 0.0


def process_cpu_s(pid: int) -> float:
    """CPU seconds (user + system, all its threads, ended ones too) that process ``pid`` has used."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) * _TICK_S


class StealMeter:
    """``with StealMeter() as m: ...`` then ``m.ms``: milliseconds stolen during the block."""

    def __enter__(self) -> StealMeter:
        self._t0 = steal_s()
        self.ms = 0.0
        return self

    def __exit__(self, *exc: object) -> None:
        self.ms = (steal_s() - self._t0) * 1e3

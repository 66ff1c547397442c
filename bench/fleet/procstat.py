"""CPU time and resident memory of processes, from ``/proc`` (Linux)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

TICK = os.sysconf("SC_CLK_TCK")
MIB = 2**20


@dataclass(frozen=True)
class Usage:
    cpu_s: float
    """User + system CPU seconds since the process started (all its threads)."""
    rss: int
    """Resident set size, bytes."""
    rss_peak: int
    """Peak resident set size so far (``VmHWM``), bytes."""


def usage(pid: int) -> Usage:
    """Raises ``OSError`` when the process is gone."""
    stat = Path(f"/proc/{pid}/stat").read_text()
    fields = stat[stat.rindex(")") + 2 :].split()  # the name may hold spaces and parens
    cpu = (int(fields[11]) + int(fields[12])) / TICK  # utime, stime: fields 14 and 15
    rss = peak = 0
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            rss = int(line.split()[1]) * 1024
        elif line.startswith("VmHWM:"):
            peak = int(line.split()[1]) * 1024
    return Usage(cpu, rss, peak)


def machine_busy_s() -> tuple[float, float]:
    """(busy, total) CPU seconds of the whole machine since boot, all cores together
    (idle and iowait count as not busy)."""
    first = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
    ticks = [int(x) for x in first[:8]]  # user nice system idle iowait irq softirq steal
    total = sum(ticks)
    return (total - ticks[3] - ticks[4]) / TICK, total / TICK

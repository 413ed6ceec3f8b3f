"""How busy the CPU is with other work, read before torch loads, to choose OpenMP's wait policy.

OpenMP threads that finish a parallel region early spin (busy-wait) for the others by default (GNU OpenMP, which
torch's Linux wheels use: a spin count of 300,000 before they sleep). On an idle machine that is the fastest way to
wait; when another process keeps a core busy, the spinning threads compete with it and with each other for the
cores, and every region waits for a descheduled thread. Measured (2026-11-25, 2 cores, `nerfpipe train` on a 64 px
rgba scene, 400 steps, torch's 2 threads, median of 3-5 whole runs; the fox scene, 200 steps):

| machine | OpenMP default | OMP_WAIT_POLICY=PASSIVE |
|---|---|---|
| idle, 64 px scene | 19.2 s | 22.7 s (+18 %) |
| idle, fox | 39.9 s | 44.5 s (+12 %) |
| one other process keeping a core busy, 64 px scene | 57.9 s | 29.3 s (2.0x faster) |

(GOMP_SPINCOUNT=20000 instead: as the default when idle, 76.6 s with the busy core.) So neither policy is right for
both; the CLI samples the CPU for `SAMPLE_SECONDS` before a stage imports torch and asks for the passive policy when
other processes keep at least `BUSY_CORES` cores busy (`wait_policy`). A user's own OMP_WAIT_POLICY always wins.
Linux only (/proc/stat); elsewhere nothing changes.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

__all__ = ["BUSY_CORES", "SAMPLE_SECONDS", "busy_cores", "wait_policy"]

SAMPLE_SECONDS = 0.2
"""How long the CPU is sampled (one look at /proc/stat before and after)."""
BUSY_CORES = 0.5
"""Cores kept busy by other processes from which the passive policy is chosen (the measured case: one core)."""


def _cpu_times(stat: Path) -> tuple[float, float] | None:
    """(busy, total) jiffies of all cores from /proc/stat's first line; None where it cannot be read."""
    try:
        fields = stat.read_text().splitlines()[0].split()
    except (OSError, IndexError):
        return None
    if not fields or fields[0] != "cpu" or len(fields) < 5:
        return None
    values = [float(v) for v in fields[1:]]
    idle = values[3] + (values[4] if len(values) > 4 else 0.0)  # idle + iowait
    return sum(values) - idle, sum(values)


def busy_cores(seconds: float = SAMPLE_SECONDS, stat: Path = Path("/proc/stat")) -> float | None:
    """Cores' worth of CPU time the whole machine used over the next `seconds` (this process sleeps meanwhile, so
    it is other processes' use); None where /proc/stat is not available."""
    before = _cpu_times(stat)
    if before is None:
        return None
    time.sleep(seconds)
    after = _cpu_times(stat)
    if after is None or after[1] <= before[1]:
        return None
    return (os.cpu_count() or 1) * (after[0] - before[0]) / (after[1] - before[1])


def wait_policy(environ: dict[str, str] | os._Environ, torch_loaded: bool) -> str | None:
    """Set OMP_WAIT_POLICY=PASSIVE in `environ` when other processes keep BUSY_CORES or more busy; returns the
    policy set, or None (torch already loaded: too late to matter; the user's own setting; an idle machine)."""
    if torch_loaded or "OMP_WAIT_POLICY" in environ:
        return None
    busy = busy_cores()
    if busy is None or busy < BUSY_CORES:
        return None
    environ["OMP_WAIT_POLICY"] = "PASSIVE"
    return "PASSIVE"

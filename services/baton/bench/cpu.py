"""How busy the machine's cores were over a window of a run: the contention beside a number.

The benchmarks run every part of a testbed as a process on one machine (20
and more processes on CI's 2 cores), so a handover's delay beyond its
physical limit is partly the work it must do and partly its wait for a core.
``CpuSampler`` reads the kernel's count of busy and idle time for all cores
(``/proc/stat``'s ``cpu`` line) every ``SAMPLE_S`` on a thread of its own,
and ``busy`` gives the share of the cores' time that was busy between two
wall-clock instants (a handover's decision and its first request, as the
drone records them). The kernel counts in ticks of 10 ms per core, so a
window shorter than about 0.2 s is not given (None).

``process_usage`` reads one process's CPU time and memory (``/proc/PID``), and
``child_pids`` the processes it started: what ``baton bench fleet`` charges to
a station and its mission programs.
"""

from __future__ import annotations

import bisect
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

SAMPLE_S = 0.02
# A window shorter than this holds too few ticks to say anything.
MIN_WINDOW_S = 0.2
PROC_STAT = Path("/proc/stat")
# The kernel counts a process's CPU time in these ticks per second.
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


def read_cpu_ticks(path: Path = PROC_STAT) -> tuple[int, int] | None:
    """(busy, total) ticks of all cores since boot; None where the kernel does not say."""
    try:
        with path.open() as stat:
            fields = stat.readline().split()
    except OSError:
        return None
    if not fields or fields[0] != "cpu":
        return None
    # user nice system idle iowait irq softirq steal (guest time is in user already)
    ticks = [int(value) for value in fields[1:9]]
    idle = ticks[3] + ticks[4]
    total = sum(ticks)
    return total - idle, total


class CpuSampler:
    """Samples the cores' busy time while it is entered (``with CpuSampler() as cpu``)."""

    def __init__(self, every_s: float = SAMPLE_S) -> None:
        self.every_s = every_s
        self._times: list[float] = []
        self._ticks: list[tuple[int, int]] = []
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, name="cpu sampler", daemon=True)

    def __enter__(self) -> CpuSampler:
        ticks = read_cpu_ticks()
        if ticks is not None:  # a window that starts now has a sample at its start
            self.record(time.time(), ticks)
        self._thread.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._stopping.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stopping.wait(self.every_s):
            ticks = read_cpu_ticks()
            if ticks is None:
                return
            self.record(time.time(), ticks)

    def record(self, at: float, ticks: tuple[int, int]) -> None:
        """One sample: the (busy, total) ticks counted at wall-clock time ``at``."""
        self._times.append(at)
        self._ticks.append(ticks)

    def busy(self, start: float, end: float) -> float | None:
        """The share of all cores' time that was busy from ``start`` to ``end`` (wall
        clock, seconds), from the last sample at or before ``start`` to the first at
        or after ``end``; None if the samples do not cover the window or it is too short."""
        if end - start < MIN_WINDOW_S:
            return None
        first = bisect.bisect_right(self._times, start) - 1
        last = bisect.bisect_left(self._times, end)
        if first < 0 or last >= len(self._times):
            return None
        busy = self._ticks[last][0] - self._ticks[first][0]
        total = self._ticks[last][1] - self._ticks[first][1]
        return busy / total if total > 0 else None


@dataclass(frozen=True)
class ProcessUsage:
    """One process's CPU time so far (user and system, seconds), its resident set, and
    its proportional share of it (PSS: each page shared with other processes, such as
    the interpreter's and the libraries' code, counted in equal parts; 0 where the
    kernel does not say)."""

    cpu_s: float
    rss_bytes: int
    pss_bytes: int


def process_usage(pid: int, proc: Path = Path("/proc")) -> ProcessUsage | None:
    """What process ``pid`` has used, from ``/proc/PID/stat`` and ``status``; None once
    it is gone (or where the kernel does not say)."""
    try:
        stat = (proc / str(pid) / "stat").read_text()
        status = (proc / str(pid) / "status").read_text()
    except OSError:
        return None
    try:
        rollup = (proc / str(pid) / "smaps_rollup").read_text()
    except OSError:
        rollup = ""
    # The command name (field 2) is in parentheses and may hold spaces: count after it.
    fields = stat[stat.rindex(")") + 2 :].split()
    utime, stime = int(fields[11]), int(fields[12])
    return ProcessUsage(
        (utime + stime) / CLOCK_TICKS, _kib_field(status, "VmRSS:"), _kib_field(rollup, "Pss:")
    )


def _kib_field(text: str, name: str) -> int:
    """The bytes of a ``/proc`` line ``name  N kB``; 0 without one."""
    for line in text.splitlines():
        if line.startswith(name):
            return int(line.split()[1]) * 1024
    return 0


def child_pids(pid: int, proc: Path = Path("/proc")) -> list[int]:
    """The processes ``pid`` started that still run (its mission programs)."""
    children: list[int] = []
    try:
        for task in (proc / str(pid) / "task").iterdir():
            children += [int(c) for c in (task / "children").read_text().split()]
    except OSError:
        return []
    return children

"""A process's memory, from /proc (Linux): what the memory tests measure."""

from __future__ import annotations

from pathlib import Path


def _status_bytes(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) * 1024
    raise AssertionError(f"no {field} for process {pid}")


def rss_bytes(pid: int) -> int:
    """The resident set size of process ``pid``."""
    return _status_bytes(pid, "VmRSS")


def peak_rss_bytes(pid: int) -> int:
    """The largest resident set size process ``pid`` has had (VmHWM)."""
    return _status_bytes(pid, "VmHWM")

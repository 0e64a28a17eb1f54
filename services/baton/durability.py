"""What a part does when its durable file stops taking writes: pure decisions.

The controller's log file (``controller/history.py``) and the drone's state
file (``drone/store.py``) are SQLite files; a write to either can fail (the
disk full, a file past its size limit, an I/O error, a file system remounted
read-only). The drivers turn a failed write into ``write_failed`` and a write
that succeeds after failures into ``write_succeeded``; these functions keep the
file's health and say, once, what a person must read. The rules:

- A failure is said once, as an ERROR naming the file and the error, when it
  begins; the failed writes after it are counted, not logged again (a log that
  repeats a line every half second buries it).
- A controller's log file is append-only, whole up to a log number: after its
  first failed write the controller writes nothing more to it (a later write
  that succeeded would leave a gap the file could not state) and keeps every
  later message in memory, still replicating; the file stays whole up to the
  log number stated when it failed (``whole_up_to``).
- The drone's state file is rewritten by every request: a write that succeeds
  after the failed ones (replayed in order) makes it whole again, so the drone
  recovers. While it cannot write, it refuses new requests (``drone_refusal``):
  a request executed with no record of it on disk could be executed again by
  the drone restarted from that file.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import grpc

from baton.rpc.errors import StatusError


@dataclass(frozen=True)
class FileHealth:
    """Whether a durable file takes writes, and since when it does not."""

    path: str
    error: str = ""  # the first failed write's error; "" while writes succeed
    failed_write: str = ""  # what that write was ("log message 12", "request 40")
    failed_at: float = 0.0  # Unix seconds
    failures: int = 0  # failed writes since (the first included)
    whole_up_to: int = 0  # a log file: every log message up to this one is in it

    @property
    def durable(self) -> bool:
        """Writes reach the file."""
        return not self.error


@dataclass(frozen=True)
class Report:
    """Effect: a line for the part's log (``level`` is ``error`` or ``info``)."""

    level: str
    text: str
    fields: dict[str, Any] = field(default_factory=dict)


def write_failed(
    health: FileHealth,
    what: str,
    error: str,
    now: float,
    consequence: str,
    whole_up_to: int = 0,
    began: float | None = None,
) -> tuple[FileHealth, list[Report]]:
    """A write (``what``) failed with ``error``: the first is reported, with what the
    part does about it (``consequence``), the rest counted. ``whole_up_to`` (a log
    file) is taken from the first failure only: what the file holds whole does not
    change while nothing more is written to it. ``began``: when a failure seen only
    now happened (a checkpoint's, on its own thread); the report says how late."""
    if not health.durable:
        return replace(health, failures=health.failures + 1), []
    failed = replace(
        health,
        error=error,
        failed_write=what,
        failed_at=now if began is None else began,
        failures=1,
        whole_up_to=whole_up_to,
    )
    return failed, [
        Report(
            "error",
            f"cannot write {health.path}: {what} failed: {error}; {consequence}",
            {
                "file": health.path,
                "write": what,
                "error": error,
                "said_after_s": round(now - failed.failed_at, 3),
            },
        )
    ]


def write_succeeded(health: FileHealth, now: float) -> tuple[FileHealth, list[Report]]:
    """A write succeeded: a file that had failed is durable again (the drone's state
    file, whose failed writes were replayed before this one)."""
    if health.durable:
        return health, []
    recovered = FileHealth(health.path)
    return recovered, [
        Report(
            "info",
            f"{health.path} takes writes again: durable again",
            {
                "file": health.path,
                "failed_writes": health.failures,
                "failed_for_s": round(now - health.failed_at, 3),
            },
        )
    ]


def held_whole(whole_up_to: int) -> str:
    """What a log file holds whole, in words."""
    return f"log messages 1-{whole_up_to}" if whole_up_to else "no log message"


def drone_refusal(health: FileHealth) -> StatusError | None:
    """The refusal of a new request while the drone cannot write its state file."""
    if health.durable:
        return None
    return StatusError(
        grpc.StatusCode.UNAVAILABLE,
        f"the drone cannot write its state file {health.path}: {health.error}; it refuses "
        "new requests so that none can be executed twice after a restart (it takes them "
        "again once a write succeeds)",
    )

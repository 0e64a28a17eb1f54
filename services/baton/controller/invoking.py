"""What the answer to a drone call means, as pure functions: the entry to log, a
refusal for the core to judge, or the same request again after a pause.

The runtime's ``ControllerNode`` (over ``DroneSession.invoke``) and the
simulation's ``SimController`` (over its virtual drone link) both ask here.

The rules:

- A reply is logged with the drone's epoch and signature (``authenticity``).
- A refusal that names the drone's master goes to the core
  (``ControllerCore.request_refused``), and the call is asked again in the
  state that follows: nothing is logged for it.
- UNAVAILABLE (the drone unreachable, its vehicle not connected) executed
  nothing: the same request number is sent again, so the drone's duplicate
  detection keeps it safe, after a pause that doubles from ``RETRY_FIRST_S`` up
  to ``RETRY_MAX_S``, for at most the configuration's ``drone_retry_limit``.
- Any other failure, or UNAVAILABLE past that limit, is the call's outcome: it
  is logged with its status, and every replica's program sees the same.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import grpc

from baton.controller.core import ControllerCore, CoreEffect, DroneRefusal
from baton.v1 import ring_pb2

RETRY_FIRST_S, RETRY_MAX_S = 0.2, 2.0


@dataclass(frozen=True)
class Sent:
    """A drone call as it was sent: its request number, method, request and digest, and
    the epoch of the mastership it was sent in."""

    reqnr: int
    method: str
    request: bytes
    digest: bytes
    epoch: int

    def entry(self) -> ring_pb2.LogEntry:
        """The log entry for this call, without its outcome yet."""
        return ring_pb2.LogEntry(
            reqnr=self.reqnr,
            method=self.method,
            request_digest=self.digest,
            request=self.request,
        )


@dataclass(frozen=True)
class Outcome:
    """What a failed call comes to: an ``entry`` to log, or a ``pause`` (seconds) before
    the same request goes again, or neither (the state changed: ask again); and what
    the core decided of a refusal."""

    entry: ring_pb2.LogEntry | None = None
    pause: float | None = None
    effects: list[CoreEffect] = field(default_factory=list)


def replied(sent: Sent, payload: bytes, epoch: int, signature: bytes) -> ring_pb2.LogEntry:
    """The entry for the drone's reply."""
    entry = sent.entry()
    entry.reply, entry.drone_epoch, entry.drone_signature = payload, epoch, signature
    return entry


def retry_pause(attempts: int, waited: float, limit_s: float) -> float:
    """The pause before the next try after ``attempts`` pauses, within the limit."""
    delay = min(RETRY_MAX_S, RETRY_FIRST_S * 2**attempts)
    return min(delay, max(0.0, limit_s - waited))


def failed(
    core: ControllerCore,
    sent: Sent,
    code: grpc.StatusCode,
    details: str,
    refusal: DroneRefusal | None,
    waited: float,
    limit_s: float,
    attempts: int,
) -> Outcome:
    """What the drone's failure ``code`` means (the module's rules); ``waited``: seconds
    since the first try, ``attempts``: the pauses so far."""
    if refusal is not None:
        return Outcome(
            effects=core.request_refused(sent.epoch, refusal, sent.reqnr, sent.method, details)
        )
    if code is grpc.StatusCode.UNAVAILABLE and waited < limit_s:
        return Outcome(pause=retry_pause(attempts, waited, limit_s))
    entry = sent.entry()
    entry.status_code, entry.status_message = code.value[0], details
    return Outcome(entry=entry)

"""One call of the mission program, answered: the loop both drivers run (sans I/O).

``CallFlow.run`` is a generator, in the manner of h11: it yields what it needs
done and is sent the result, and returns the log entry whose reply (or status)
the program must see. It holds the order of the call's turns; the decisions
are the core's (``ControllerCore.settle``, ``answer``, ``logged``) and
``invoking``'s (a drone call's outcome). ``ProgramCalls`` (asyncio, the
runtime) and ``SimController`` (virtual time, the simulation) carry out what
it yields; neither holds a turn of its own.

The rules:

- First every call the program gave up on while this controller waited is
  settled from the log (``settle``); the call waits for a change until it is.
- Then the core says where the answer comes from (``answer``): the log, or a
  wait for a change (``Hold``), or the Clock, or the drone.
- A drone call is sent while this controller is ACTIVE and its session's
  Connect stream is up, in the session's epoch; without a session, or not
  ACTIVE, the core is asked again; with the stream down, it waits for it.
- A drone call's failure is judged by ``invoking.failed``: a refusal goes to
  the core and the call is asked again; UNAVAILABLE is sent again after a
  pause, up to the retry limit; anything else is the outcome.
- What the Clock or the drone answered is logged if the request is still ours
  (``logged``); a handover that overtook it asks the core again (footnote 2).

Every ``Apply`` is carried out before the flow goes on; a driver stops the
call there when the mission failed or the program starts again (``Fail``,
``ReplayAgain``), and checks that after every wait too.
"""

from __future__ import annotations

from collections.abc import Generator, Sequence
from dataclasses import dataclass

import grpc

from baton.controller.core import Answer, AskClock, ControllerCore, CoreEffect, DroneRefusal, Hold
from baton.controller.invoking import Sent, failed, replied
from baton.controller.protocol import State
from baton.v1 import ring_pb2


@dataclass(frozen=True)
class Apply:
    """Carry out the core's effects (``ControllerNode.apply``); sent back: None."""

    effects: Sequence[CoreEffect]


@dataclass(frozen=True)
class WaitForChange:
    """Wait for the node's next change; sent back: None."""


@dataclass(frozen=True)
class ReadClock:
    """The Clock's reply (Now at once, Sleep after its time); sent back: its bytes."""

    method: str
    request: bytes


@dataclass(frozen=True)
class LookAtSession:
    """How the drone session is now; sent back: a ``SessionSeen``."""


@dataclass(frozen=True)
class SessionSeen:
    """The drone session as the driver sees it: whether there is one, whether its
    Connect stream is up, its epoch; and the time (for the retry limit)."""

    present: bool
    connected: bool
    epoch: int
    now: float


@dataclass(frozen=True)
class WaitConnected:
    """Wait until the session's Connect stream is up, or the next change; sent back: None."""


@dataclass(frozen=True)
class Invoke:
    """Send ``sent`` to the drone, to fail after ``timeout_s``; sent back: an ``Invoked``."""

    sent: Sent
    timeout_s: float


@dataclass(frozen=True)
class Invoked:
    """The drone's answer to an ``Invoke``: its reply (payload, epoch, signature), or the
    failure's code, details and the refusal it names; and the time it came."""

    now: float
    reply: tuple[bytes, int, bytes] | None = None
    code: grpc.StatusCode = grpc.StatusCode.OK
    details: str = ""
    refusal: DroneRefusal | None = None


@dataclass(frozen=True)
class Pause:
    """The drone was unavailable: wait ``seconds`` before sending request ``reqnr`` again.
    ``attempts``: the pauses before this one; ``waited``: seconds since the first try."""

    seconds: float
    reqnr: int
    method: str
    details: str
    waited: float
    attempts: int


@dataclass(frozen=True)
class RetriesEnded:
    """Request ``reqnr`` was re-sent and its failure is now its outcome; sent back: None."""

    reqnr: int
    waited: float


Io = (
    Apply
    | WaitForChange
    | ReadClock
    | LookAtSession
    | WaitConnected
    | Invoke
    | Pause
    | RetriesEnded
)
Flow = Generator[Io, object, ring_pb2.LogEntry]


class CallFlow:
    """One call of the program, ``method`` with ``request``, answered through ``core``;
    a drone call that finds the drone unavailable is re-sent for at most ``retry_limit_s``."""

    def __init__(
        self, core: ControllerCore, method: str, request: bytes, retry_limit_s: float
    ) -> None:
        self.core, self.method, self.request = core, method, request
        self.retry_limit_s = retry_limit_s
        # The request being answered (0: none yet): a give-up is logged for it.
        self.reqnr = 0

    def gave_up(self, code: grpc.StatusCode) -> list[CoreEffect]:
        """The program gave up on the call here (``ControllerCore.gave_up``)."""
        return self.core.gave_up(self.reqnr, self.method, self.request, code)

    def settle(self) -> Generator[Io, object, None]:
        """Gives the log's entry to each call the program gave up on while this controller
        waited (``ControllerCore.settle``), waiting for changes until it has."""
        while True:
            done, effects = self.core.settle()
            if effects:
                yield Apply(effects)
            if done:
                return
            yield WaitForChange()

    def run(self) -> Flow:
        """The call's turns, up to the entry the program sees."""
        yield from self.settle()
        while True:
            step, effects = self.core.answer(self.method, self.request)
            self.reqnr = 0 if isinstance(step, Answer) else step.reqnr
            if effects:  # nothing to apply wakes nobody: a call that waits must not wake itself
                yield Apply(effects)
            if isinstance(step, Answer):
                return step.entry
            if isinstance(step, Hold):
                yield WaitForChange()
                continue
            if isinstance(step, AskClock):
                reply = yield ReadClock(self.method, self.request)
                assert isinstance(reply, bytes)
                entry: ring_pb2.LogEntry | None = step.entry(self.method, self.request, reply)
            else:
                entry = yield from self._invoke(step.reqnr, step.digest)
            if entry is None:
                continue  # the state changed: asked again
            logged, effects = self.core.logged(step.reqnr, entry)
            if effects:
                yield Apply(effects)
            if logged is not None:
                return logged

    def _invoke(self, reqnr: int, digest: bytes) -> Generator[Io, object, ring_pb2.LogEntry | None]:
        """Sends the request until it has an outcome (``invoking.failed``'s rules); None
        when the state changed (no session, not ACTIVE, or a refusal the core judged)."""
        started: float | None = None
        attempts = 0
        while True:
            seen = yield LookAtSession()
            assert isinstance(seen, SessionSeen)
            started = seen.now if started is None else started
            if not seen.present or self.core.protocol.state is not State.ACTIVE:
                return None
            if not seen.connected:
                yield WaitConnected()
                continue
            sent = Sent(reqnr, self.method, self.request, digest, seen.epoch)
            timeout_s = max(1.0, self.retry_limit_s - (seen.now - started))
            answer = yield Invoke(sent, timeout_s)
            assert isinstance(answer, Invoked)
            if answer.reply is not None:
                return replied(sent, *answer.reply)
            waited = answer.now - started
            outcome = failed(
                self.core,
                sent,
                answer.code,
                answer.details,
                answer.refusal,
                waited,
                self.retry_limit_s,
                attempts,
            )
            if outcome.pause is not None:
                yield Pause(outcome.pause, reqnr, self.method, answer.details, waited, attempts)
                attempts += 1
                continue
            if outcome.entry is None:  # a refusal: the core judged it
                yield Apply(outcome.effects)
            elif attempts:
                yield RetriesEnded(reqnr, waited)
            return outcome.entry

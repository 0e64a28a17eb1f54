"""One Invoke on the drone, admitted, executed and booked: the turns both drivers run.

``RequestFlow.run`` is a generator, as ``controller/call_flow.py``'s: it
yields what it needs done and is sent the result, and returns what the
caller is answered. It holds the order of a request's turns under the
execution lock; the decisions are ``DroneCore``'s (``holds``, ``admit``,
``unreachable``, ``sending``, ``acknowledged``, ``served``, ``failed``).
``Invocations`` (the service, over MAVSDK) and ``SimDrone`` (the
simulation, over its vehicle) carry out what it yields.

The rules, in order:

- A request of a paused mission waits, not admitted (``Parked``).
- Admission may refuse it (``DroneCore.admit`` raises StatusError: nothing
  booked, the number unused) or answer it from the reply cache
  (``Duplicate``).
- Otherwise its intent is stored before anything reaches the vehicle
  (``Begin``): a restart finds it cut off.
- It is executed unless refused after admission (a failsafe, a bound), its
  payload does not parse, or it needs the vehicle and the vehicle is not
  there (``unreachable``: UNAVAILABLE, the number stays unused).
- The command the vehicle gets is noted as it is sent (``sending``), and
  what the vehicle then expects once it acknowledged (``acknowledged``).
- Its outcome, reply or failure, is booked (``served``, ``failed``) and the
  booking's effects applied (``Booking``) before the caller is answered.
"""

from __future__ import annotations

from collections.abc import Generator, Sequence
from dataclasses import dataclass

from baton.digest import request_digest
from baton.drone.core import DroneCore
from baton.drone.dedupe import CachedReply
from baton.drone.effects import DroneEffect
from baton.drone.store import Intent
from baton.rpc.errors import StatusError
from baton.v1 import drone_pb2


@dataclass(frozen=True)
class FirstOfMaster:
    """The request is its new master's first (for the log); sent back: None."""

    record: drone_pb2.HandoverRecord


@dataclass(frozen=True)
class Begin:
    """Store the request's intent, with what the admission keeps, in one transaction,
    before anything is executed; sent back: None."""

    intent: Intent
    kept: Sequence[CachedReply]


@dataclass(frozen=True)
class Parse:
    """Whether the payload parses; sent back: None, or the StatusError refusing it."""


@dataclass(frozen=True)
class LookAtVehicle:
    """Whether the vehicle is connected; sent back: a ``VehicleSeen``."""


@dataclass(frozen=True)
class VehicleSeen:
    connected: bool
    where: str  # how the refusal names the vehicle's link


@dataclass(frozen=True)
class Send:
    """The command is about to reach the vehicle; sent back: the time it does."""


@dataclass(frozen=True)
class Now:
    """The time (the booking's); sent back: a float."""


@dataclass(frozen=True)
class Execute:
    """Run the request on the vehicle, the camera or the telemetry; ``action``: the mode it
    commands (``DroneCore.sending``). Sent back: an ``Executed``."""

    action: str | None


@dataclass(frozen=True)
class Executed:
    """What the execution came to, and the time: the reply, or the failure (the vehicle
    refused, or never acknowledged: it may have acted)."""

    now: float
    reply: bytes = b""
    error: StatusError | None = None


@dataclass(frozen=True)
class Acknowledged:
    """The vehicle acknowledged the command; ``changed``: what it is expected to do
    changed (the state file keeps it); ``leg_before``: the operator's leg before it (the
    state file keeps a new one). Sent back: None."""

    changed: bool
    leg_before: bytes | None


@dataclass(frozen=True)
class Booking:
    """Apply the booking's effects (``DroneService.apply``); sent back: None."""

    effects: list[DroneEffect]
    error: StatusError | None


@dataclass(frozen=True)
class Parked:
    """Not admitted: the mission is paused, and the request waits for the resume."""


@dataclass(frozen=True)
class Duplicate:
    """Answered from the reply cache."""

    cached: CachedReply


@dataclass(frozen=True)
class Replied:
    """Executed and booked: ``reply``, in ``epoch``, to the request of ``digest`` (what
    the reply's signature covers)."""

    reply: bytes
    epoch: int
    digest: bytes


@dataclass(frozen=True)
class Failed:
    """Booked as failed (or refused with nothing booked: ``booked`` False)."""

    error: StatusError
    booked: bool


Io = FirstOfMaster | Begin | Parse | LookAtVehicle | Send | Execute | Acknowledged | Now | Booking
Outcome = Parked | Duplicate | Replied | Failed
Flow = Generator[Io, object, Outcome]


class RequestFlow:
    """Request ``request``, received at ``received_at``, through ``core``."""

    def __init__(
        self, core: DroneCore, request: drone_pb2.InvokeRequest, received_at: float
    ) -> None:
        self.core, self.request, self.received_at = core, request, received_at
        self.digest = request_digest(request.method, request.payload)
        self.reply = b""  # what the vehicle answered, once executed

    def run(self) -> Flow:
        """The request's turns, up to what its caller is answered. ``DroneCore.admit``'s
        refusal (StatusError) and a broken invariant propagate from the first turn."""
        core, request = self.core, self.request
        if core.holds(request):
            return Parked()
        admitted = core.admit(request, self.digest, self.received_at)
        if admitted.first is not None:
            yield FirstOfMaster(admitted.first)
        if admitted.cached is not None:
            return Duplicate(admitted.cached)
        if admitted.intent is not None:
            yield Begin(admitted.intent, admitted.kept)
        error = admitted.refused
        if error is None:
            error = yield from self._execute()
        return (yield from self._book(error))

    def _execute(self) -> Generator[Io, object, StatusError | None]:
        """Executes the request: its failure, or None with ``self.reply`` set."""
        core, method = self.core, self.request.method
        refused = yield Parse()
        if refused is not None:
            assert isinstance(refused, StatusError)
            return refused
        seen = yield LookAtVehicle()
        assert isinstance(seen, VehicleSeen)
        unreachable = core.unreachable(method, seen.connected, seen.where)
        if unreachable is not None:
            return unreachable
        now = yield Send()
        assert isinstance(now, float)
        done = yield Execute(core.sending(method, now))
        assert isinstance(done, Executed)
        if done.error is not None:
            return done.error
        leg = core.operator.leg
        yield Acknowledged(core.acknowledged(method, self.request.payload, done.now), leg)
        self.reply = done.reply
        return None

    def _book(self, error: StatusError | None) -> Generator[Io, object, Outcome]:
        core, request = self.core, self.request
        cid, reqnr, method = request.controller_id, request.reqnr, request.method
        now = yield Now()
        assert isinstance(now, float)
        if error is not None:
            booked = core.books(error)
            effects = core.failed(cid, reqnr, method, self.digest, self.received_at, now, error)
            yield Booking(effects, error)
            return Failed(error, booked)
        effects = core.served(cid, reqnr, method, self.digest, self.reply, self.received_at, now)
        yield Booking(effects, None)
        return Replied(self.reply, core.seq.epoch, self.digest)

"""The Invoke path of the drone service: a request admitted, executed and booked.

A driver of ``request_flow.RequestFlow`` (``DroneCore``'s request events in
their order, which the simulation runs too): each request runs under the
service's execution lock as a task of its own, so what the vehicle did is
always booked whatever its caller does; the outcome is saved (``store.py``)
before the reply leaves, and the effects of the booking (a scripted switch, a
preparation) are applied by the service (``DroneService.apply``).
"""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import grpc

from baton.authenticity import Signer, signed_reply
from baton.drone.dedupe import CachedReply
from baton.drone.effects import DroneEffect, Switched
from baton.drone.invariants import INVARIANT_EXIT, InvariantBroken
from baton.drone.request_flow import (
    Acknowledged,
    Begin,
    Booking,
    Duplicate,
    Execute,
    Executed,
    Failed,
    FirstOfMaster,
    Io,
    LookAtVehicle,
    Now,
    Parked,
    Parse,
    RequestFlow,
    Send,
    VehicleSeen,
)
from baton.rpc.errors import StatusError
from baton.rpc.outcomes import failure_of
from baton.tasks import TaskSet
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

if TYPE_CHECKING:
    from baton.drone.service import DroneService

# The durable commanded state's key of the mission's cruise speed (store.py).
SPEED_KEY = "speed_m_s"


@dataclass
class _Parsed:
    """The request's payload as its method's message, once parsed."""

    message: Any = None


def _retrieve_exception(task: asyncio.Task[Any]) -> None:
    """Marks a shielded request's failure as seen when its caller is gone (no asyncio warning)."""
    if not task.cancelled():
        task.exception()


class Invocations:
    """Invoke and InvokeStream for one ``DroneService``."""

    def __init__(self, service: DroneService) -> None:
        self.service = service
        # The invocations running to their end, held while their callers may be gone.
        self._running = TaskSet()
        # The reqnr after which the last switch fell (``Race``'s notice-first hold).
        self.handed_over_after = 0

    async def stream(
        self, calls: AsyncIterator[drone_pb2.InvokeCall], context: grpc.aio.ServicerContext
    ) -> None:
        """Invoke's calls as messages on one stream: each is executed as Invoke
        executes it and answered when it completes, its failure in its outcome.

        Calls run concurrently as their Invokes would (the sequencer's lock
        orders them); their outcomes are written one at a time. When the
        caller half-closes, the stream ends once every call has its outcome;
        when it goes away, what is still running runs to its end
        (``invoke``) and its outcome is dropped, as a cancelled Invoke's is.
        """
        answering = TaskSet()
        writing = asyncio.Lock()
        log = self.service.log

        async def answer(call: drone_pb2.InvokeCall, received_at: float) -> None:
            outcome = drone_pb2.InvokeOutcome(call=call.call)
            try:
                outcome.reply.CopyFrom(await self.for_caller(context, call.request, received_at))
            except StatusError as err:
                outcome.failure.CopyFrom(failure_of(err))
            except Exception as exc:  # what a unary Invoke would end with: UNKNOWN
                log.error("invoke failed", exc_info=True, reqnr=call.request.reqnr)
                unknown = StatusError(grpc.StatusCode.UNKNOWN, f"{type(exc).__name__}: {exc}")
                outcome.failure.CopyFrom(failure_of(unknown))
            try:
                async with writing:
                    await context.write(outcome)
            except Exception as exc:  # the stream ended: the caller sends it again
                log.info(
                    "invoke outcome not delivered: its stream ended",
                    reqnr=call.request.reqnr,
                    error=f"{type(exc).__name__}: {exc}",
                )

        try:
            async for call in calls:
                answering.spawn(answer(call, time.time()), name="invoke-call")
            await answering.drain()
        finally:
            answering.cancel()

    async def for_caller(
        self,
        context: grpc.aio.ServicerContext,
        request: drone_pb2.InvokeRequest,
        received_at: float,
    ) -> drone_pb2.InvokeReply:
        """Invoke for the caller of ``context``: the reply, or StatusError (counted and
        logged) if the caller may not send it or the drone refused or failed it."""
        service = self.service
        try:
            refusal = service.not_as(context, "Invoke", request.controller_id)
            if refusal is not None:
                raise refusal
            return await self.invoke(request, received_at)
        except StatusError as err:
            service.seq.rejected += 1
            service.log.warning(
                "invoke rejected",
                controller=request.controller_id,
                reqnr=request.reqnr,
                request_epoch=request.epoch,
                method=request.method,
                code=err.code.name,
                reason=err.message,
            )
            raise

    async def invoke(
        self, request: drone_pb2.InvokeRequest, received_at: float
    ) -> drone_pb2.InvokeReply:
        """Invoke without gRPC: the reply, or StatusError saying why not.

        Three kinds of failure: the sequencer's refusals (not the master, a
        stale epoch, a wrong reqnr, a duplicate that differs) leave the reqnr
        unused and carry ``baton-master`` / ``baton-epoch`` /
        ``baton-after-reqnr`` metadata; UNAVAILABLE (the vehicle not
        connected, no telemetry yet) means nothing was executed, so the reqnr
        stays unused too and the same request can be sent again; any other
        failure after the reqnr was accepted (bad method or payload,
        autopilot refusal, no acknowledgement in time) is served with that
        failure, which is cached and given again to a duplicate (dedupe.py).

        A request runs to its end once it is received, whatever its caller
        does: it is a task of its own that the caller's cancellation (a
        deadline, a client that gave up) does not reach, so what the vehicle
        did is always recorded and a re-sent reqnr is answered from the
        cache, never executed again. A duplicate that arrives meanwhile
        waits for it (the lock) and gets its outcome.
        """
        while True:
            await self.service.operator.wait_resumed(request)  # paused: waits, not admitted
            task = self._running.spawn(self._to_the_end(request, received_at))
            task.add_done_callback(_retrieve_exception)
            reply = await asyncio.shield(task)
            if reply is not None:
                return reply

    async def _to_the_end(
        self, request: drone_pb2.InvokeRequest, received_at: float
    ) -> drone_pb2.InvokeReply | None:
        """The request under the execution lock, to its end (``request_flow.RequestFlow``);
        None when a pause came before it got the lock (it waits again, not admitted)."""
        service = self.service
        async with service.execution_lock:
            steps = RequestFlow(service.core, request, received_at).run()
            parsed = _Parsed()
            result: object = None
            while True:
                try:
                    io = steps.send(result)
                except StopIteration as stop:
                    outcome = stop.value
                    break
                except InvariantBroken as broken:
                    # A defect of baton: stop as a kill -9 would, rather than fly on.
                    service.log.error(
                        "invariant broken; the drone service stops", problem=str(broken)
                    )
                    os._exit(INVARIANT_EXIT)
                result = await self._perform(request, io, parsed)
        if isinstance(outcome, Parked):
            return None
        if isinstance(outcome, Duplicate):
            return self._answer_duplicate(request, outcome.cached)
        if isinstance(outcome, Failed):
            raise outcome.error
        race = service.race
        reqnr = request.reqnr
        if race is not None and race.order == "notice-first" and self.handed_over_after == reqnr:
            await asyncio.sleep(race.delay_s)
        return signed_reply(
            service.signer, reqnr, outcome.epoch, request.method, outcome.digest, outcome.reply
        )

    async def _perform(self, request: drone_pb2.InvokeRequest, io: Io, parsed: _Parsed) -> object:
        """What one turn of a request's flow asks for, done."""
        service = self.service
        if isinstance(io, FirstOfMaster):
            first = io.record
            service.log.info(
                "first request of new master",
                master=request.controller_id,
                epoch=first.epoch,
                after_reqnr=first.after_reqnr,
                delay_s=round(first.delay_s, 6),
            )
        elif isinstance(io, Begin):
            if service.store is not None:
                service.store.begin(io.intent, io.kept)
        elif isinstance(io, Parse):
            try:
                route = service.dispatcher.route(request.method)
                parsed.message = route.parse(request.payload)
            except StatusError as err:
                return err
        elif isinstance(io, LookAtVehicle):
            vehicle = service.vehicle
            return VehicleSeen(vehicle.connected, f"at {vehicle.url} ({vehicle.link().problem})")
        elif isinstance(io, Send | Now):
            return time.time()
        elif isinstance(io, Execute):
            return await self._execute(request, parsed.message)
        elif isinstance(io, Acknowledged):
            self._acknowledged(request, parsed.message, io.leg_before)
        elif isinstance(io, Booking):
            self.served(request.reqnr, io.effects)
        return None

    async def _execute(self, request: drone_pb2.InvokeRequest, message: Any) -> Executed:
        """The handler of the request's method, on the vehicle: what it came to."""
        service = self.service
        route = service.dispatcher.route(request.method)
        handler = service.dispatcher.handler(route)
        try:
            reply = await handler(message)
        except StatusError as err:
            return Executed(time.time(), error=err)
        except Exception as exc:
            service.log.error("handler failed", method=request.method, exc_info=True)
            failure = StatusError(
                grpc.StatusCode.INTERNAL, f"{request.method} failed on the drone: {exc!r}"
            )
            return Executed(time.time(), error=failure)
        payload = reply.SerializeToString()
        log = service.log.debug if route.is_read else service.log.info
        log(
            "executed",
            controller=request.controller_id,
            reqnr=request.reqnr,
            method=request.method,
            reply_bytes=len(payload),
        )
        return Executed(time.time(), payload)

    def _acknowledged(
        self, request: drone_pb2.InvokeRequest, message: Any, leg_before: bytes | None
    ) -> None:
        """What the vehicle's acknowledgement changed, kept: the command it follows, the
        leg a resume flies on, the cruise speed; the policy told the leg it flies."""
        service = self.service
        route = service.dispatcher.route(request.method)
        service.keep_command()
        service.operator.keep_leg(leg_before)
        if route.service == "Mobility" and service.policy is not None:
            service.policy.executed(route.name, message)
        if service.store is not None and isinstance(message, api.SetSpeedRequest):
            # Commanded state the vehicle needs again after a restart (store.py).
            service.store.save_commanded(SPEED_KEY, message.speed_m_s)

    def _answer_duplicate(
        self, request: drone_pb2.InvokeRequest, cached: CachedReply
    ) -> drone_pb2.InvokeReply:
        self.service.log.info(
            "duplicate answered from cache",
            controller=request.controller_id,
            reqnr=request.reqnr,
            method=request.method,
            failed=cached.error is not None,
        )
        return answered_again(self.service.signer, request.reqnr, cached)

    def served(self, reqnr: int, effects: list[DroneEffect]) -> None:
        """Applies a served request's effects (``DroneCore.served``): booked and saved, and
        the script's handover or preparation after it."""
        race = self.service.race
        hold = race.delay_s if race is not None and race.order == "reply-first" else 0.0
        self.service.apply(effects, notice_delay_s=hold)
        if any(isinstance(effect, Switched) for effect in effects):
            self.handed_over_after = reqnr


def answered_again(signer: Signer | None, reqnr: int, cached: CachedReply) -> drone_pb2.InvokeReply:
    """A duplicate of request ``reqnr`` answered from the reply cache: its failure raised
    again (StatusError), or its reply as it was served, signed as a duplicate."""
    error = cached.duplicate_error()
    if error is not None:
        raise error
    return signed_reply(
        signer, reqnr, cached.epoch, cached.method, cached.digest, cached.reply, duplicate=True
    )

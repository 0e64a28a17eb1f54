"""The controller's gRPC face: the drone-API proxy and the ControllerRing service.

The proxy serves the same Mobility, Camera and Clock services as the drone,
from the drone API's one method table (``rpc/methods.py``, read from the
proto descriptors) with one generic handler, so a method added to the
contract is proxied without code here. Request and reply stay
serialized end to end: the controller logs and forwards bytes.
"""

from __future__ import annotations

import hmac
import math
from collections.abc import AsyncIterator, Awaitable, Callable

import grpc
from google.protobuf import message as protobuf_message

from baton.controller.core import CLOCK_SLEEP
from baton.controller.node import ControllerNode
from baton.controller.ring import RingReceiver
from baton.rpc.errors import StatusError, abort_with, status_of
from baton.rpc.methods import DRONE_API_SERVICES, drone_api, service_full_name
from baton.rpc.mission import MISSION_TOKEN_ENV, MISSION_TOKEN_METADATA, token_in
from baton.rpc.outcomes import failure_of
from baton.rpc.server import Servicer, generic, servicer
from baton.rpc.tls import caller, refused, refused_status
from baton.v1 import drone_api_pb2 as api
from baton.v1 import ring_pb2, ring_pb2_grpc


def caller_refused(
    node_id: int, token: str | None, context: grpc.aio.ServicerContext, what: str
) -> StatusError | None:
    """PERMISSION_DENIED unless the caller is the mission program (rpc/mission.py)."""
    if token is None:
        return None
    sent = token_in(context.invocation_metadata())
    if sent is not None and hmac.compare_digest(sent, token):
        return None
    return StatusError(
        grpc.StatusCode.PERMISSION_DENIED,
        f"controller {node_id}: {what} is for this controller's mission program only, which "
        f"sends the {MISSION_TOKEN_METADATA} metadata it was given in {MISSION_TOKEN_ENV}; "
        f"this call sent {'none' if sent is None else 'another token'}. Nothing was "
        "changed. GetStatus is open to anyone.",
    )


class DroneApiProxy(grpc.GenericRpcHandler):
    """Answers the local mission program's drone-API calls through the controller.

    With a mission token (``rpc/mission.py``), calls without it are refused
    before they reach the node: they take no request number and hold no call.
    """

    def __init__(self, node: ControllerNode, token: str | None = None) -> None:
        self._node = node
        self._token = token
        self._methods = drone_api()
        self._handlers: dict[str, grpc.RpcMethodHandler] = {}  # made once per method

    def service(
        self, handler_call_details: grpc.HandlerCallDetails
    ) -> grpc.RpcMethodHandler | None:
        """The raw-bytes handler of a drone-API method, None for other methods."""
        method = handler_call_details.method
        handler = self._handlers.get(method)
        if handler is None:
            found = self._methods.get(method)
            if found is None:
                return None
            handler = grpc.unary_unary_rpc_method_handler(self._handler(method, found.request_type))
            self._handlers[method] = handler
        return handler

    def _handler(
        self, method: str, request_class: type[protobuf_message.Message]
    ) -> Callable[[bytes, grpc.aio.ServicerContext], Awaitable[bytes]]:
        async def handle(request: bytes, context: grpc.aio.ServicerContext) -> bytes:
            refused = caller_refused(self._node.id, self._token, context, method)
            if refused is not None:
                await abort_with(context, refused)
            try:
                return await self.answer(method, request_class, request, context)
            except StatusError as exc:
                await abort_with(context, exc)

        return handle

    async def answer(
        self,
        method: str,
        request_class: type[protobuf_message.Message],
        request: bytes,
        context: grpc.aio.ServicerContext,
    ) -> bytes:
        """The reply to one call of the program, unary or on its stream; StatusError if it
        fails (the caller's token is checked already)."""
        try:
            parsed = request_class.FromString(request)
        except protobuf_message.DecodeError as exc:
            raise StatusError(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"{method}: payload is not a {request_class.__name__}: {exc}",
            ) from None
        check_request(method, parsed)
        entry = await self._node.program.call(method, request, lambda: _gave_up(context))
        if entry.status_code != 0:
            raise StatusError(status_of(entry.status_code), entry.status_message)
        return bytes(entry.reply)

    async def serve_calls(
        self, calls: AsyncIterator[ring_pb2.ProgramCall], context: grpc.aio.ServicerContext
    ) -> AsyncIterator[ring_pb2.ProgramOutcome]:
        """ControllerRing.ProgramCalls: the program's calls on its kept stream, answered in
        turn as the unary methods answer them. The stream ending (the program cancels it,
        or dies) while a call is at the node cancels that call: the node logs the give-up
        as for a unary call's (``ProgramCalls.call``)."""
        refused = caller_refused(self._node.id, self._token, context, "ProgramCalls")
        if refused is not None:
            await abort_with(context, refused)
        async for call in calls:
            found = self._methods.get(call.method)
            try:
                if found is None:
                    raise StatusError(
                        grpc.StatusCode.UNIMPLEMENTED,
                        f"ProgramCalls: call {call.call} names {call.method!r}, not a method "
                        'of the drone API ("/baton.v1.Mobility/GetPosition" ...); nothing '
                        "was logged",
                    )
                reply = await self.answer(call.method, found.request_type, call.request, context)
            except StatusError as exc:
                yield ring_pb2.ProgramOutcome(call=call.call, failure=failure_of(exc))
                continue
            yield ring_pb2.ProgramOutcome(call=call.call, reply=reply)


def _gave_up(context: grpc.aio.ServicerContext) -> grpc.StatusCode:
    """Why the program's call ended early: its deadline passed, or it cancelled."""
    remaining = context.time_remaining()
    if remaining is not None and remaining <= 0:
        return grpc.StatusCode.DEADLINE_EXCEEDED
    return grpc.StatusCode.CANCELLED


def check_request(method: str, request: protobuf_message.Message) -> None:
    """Refuses (StatusError) a request no controller takes a request number for:
    Clock.Sleep needs a finite, non-negative duration. ``baton replay`` refuses the same."""
    if method != CLOCK_SLEEP:
        return
    assert isinstance(request, api.SleepRequest)
    if not math.isfinite(request.seconds) or request.seconds < 0:
        raise StatusError(
            grpc.StatusCode.INVALID_ARGUMENT,
            f"Clock.Sleep: seconds must be finite and >= 0, got {request.seconds}",
        )


def ring_receiver(node: ControllerNode) -> RingReceiver:
    """The receiving end of ``node``'s ring streams."""
    return RingReceiver(
        node.id,
        lambda: node.protocol.holds_lognr,
        node.on_log,
        node.log,
        node.config.log_message_cap,
        node.on_sync,
        lambda lognr: node.protocol.epoch_of(lognr),
        node.relay_for,
        node.arriving,
        lambda head: node.protocol.holds(head),
    )


class ControllerRingService(ring_pb2_grpc.ControllerRingServicer):
    """LogRing, GetStatus, MissionDone and ProgramCalls of one controller, on one of its ports.

    The ring port (``receiver`` given) takes LogRing; with ``authenticated``
    (mutual TLS) only from a controller of the ring, as its certificate says,
    and GetStatus from any part with a certificate; never MissionDone or
    ProgramCalls. The mission program's loopback port has no receiver: LogRing
    is refused there, and MissionDone and ProgramCalls (through the ``proxy``)
    are its program's (the token).
    """

    def __init__(
        self,
        node: ControllerNode,
        token: str | None = None,
        receiver: RingReceiver | None = None,
        authenticated: bool = False,
        proxy: DroneApiProxy | None = None,
    ) -> None:
        self._node = node
        self._token = token
        self.receiver = receiver
        self._authenticated = authenticated
        self._proxy = proxy  # the mission port's: ProgramCalls

    async def LogRing(self, request_iterator: object, context: grpc.aio.ServicerContext) -> None:  # type: ignore[override]
        """Receives log messages from a predecessor or an old master, acknowledging each."""
        if self.receiver is None:
            await abort_with(
                context,
                StatusError(
                    grpc.StatusCode.PERMISSION_DENIED,
                    f"LogRing: controller {self._node.id} takes log frames on its ring port "
                    f"({self._node.config.controller(self._node.id).address}) only, from a "
                    "controller's certificate; this is its mission program's port",
                ),
            )
        ring = self._node.config.ring_order
        refusal = refused(
            context,
            self._authenticated,
            "LogRing",
            f"log frames come from the ring's controllers ({', '.join(map(str, ring))}) only",
            lambda who: who.role == "controller" and who.number in ring,
        )
        if refusal is not None:
            self._node.log.warning("ring stream refused", reason=refusal.message)
            await abort_with(context, refusal)
        sender = caller(context) if self._authenticated else None
        await self.receiver.serve(context, None if sender is None else sender.number)

    async def GetStatus(
        self, request: ring_pb2.GetControllerStatusRequest, context: grpc.aio.ServicerContext
    ) -> ring_pb2.ControllerStatus:
        """The controller's state, counters and peer streams."""
        refusal = refused_status(context, self._authenticated)
        if refusal is not None:
            await abort_with(context, refusal)
        return controller_status(self._node)

    async def MissionDone(
        self, request: ring_pb2.MissionDoneRequest, context: grpc.aio.ServicerContext
    ) -> ring_pb2.MissionDoneReply:
        """The local mission program ended; the master flushes its last log entries."""
        if self.receiver is not None:  # the ring port: peers may not end our mission
            await abort_with(
                context,
                StatusError(
                    grpc.StatusCode.PERMISSION_DENIED,
                    f"MissionDone: controller {self._node.id} takes it from its mission program "
                    f"on its mission port ({self._node.mission_address}) only, not on the ring "
                    "port; nothing was changed",
                ),
            )
        refused = caller_refused(self._node.id, self._token, context, "MissionDone")
        if refused is not None:
            await abort_with(context, refused)
        flushed = await self._node.program.mission_done(request.failed, request.error)
        return ring_pb2.MissionDoneReply(flushed=flushed, lognr=self._node.protocol.lognr)

    async def ProgramCalls(  # type: ignore[override]
        self,
        request_iterator: AsyncIterator[ring_pb2.ProgramCall],
        context: grpc.aio.ServicerContext,
    ) -> AsyncIterator[ring_pb2.ProgramOutcome]:
        """The mission program's drone-API calls on the stream it keeps (the mission port)."""
        if self._proxy is None:
            await abort_with(
                context,
                StatusError(
                    grpc.StatusCode.PERMISSION_DENIED,
                    f"ProgramCalls: controller {self._node.id} takes its mission program's calls "
                    f"on its mission port ({self._node.mission_address}) only, not on the ring "
                    "port; nothing was changed",
                ),
            )
        async for outcome in self._proxy.serve_calls(request_iterator, context):
            yield outcome


def mission_port(node: ControllerNode, token: str | None) -> list[Servicer]:
    """What a controller serves its mission program on: the drone API (unary, through
    ``DroneApiProxy``) and ControllerRing (MissionDone, ProgramCalls, GetStatus)."""
    proxy = DroneApiProxy(node, token)
    ring = ControllerRingService(node, token, proxy=proxy)
    return [
        generic(proxy, *map(service_full_name, DRONE_API_SERVICES)),
        servicer(
            service_full_name("ControllerRing"),
            ring_pb2_grpc.add_ControllerRingServicer_to_server,
            ring,
        ),
    ]


def controller_status(node: ControllerNode) -> ring_pb2.ControllerStatus:
    """A ControllerStatus snapshot of ``node``."""
    p = node.protocol
    return ring_pb2.ControllerStatus(
        id=node.id,
        state=p.state.value,
        master=p.master,
        reqnr=p.reqnr,
        lognr=p.lognr,
        log_bytes=p.log.size,
        log_entries=len(p.log),
        queue_length=len(p.log_queue),
        peers=[
            ring_pb2.PeerStatus(
                id=pid,
                address=link.address,
                stream_up=link.stream_up,
                unacked=link.unacked,
                connects=link.counters.connects,
                sent_messages=link.counters.sent_messages - link.counters.relayed_messages,
                relayed_messages=link.counters.relayed_messages,
                relays_aborted=link.counters.relays_aborted,
                relaying=link.relaying,
            )
            for pid, link in sorted(node.peers.items())
        ],
        predecessor=p.predecessor,
        successor=p.successor,
        mission=node.program.mission,
        mission_error=node.program.mission_error,
        replayed=p.replayed,
        invoked=p.invoked,
        reply_chain=node.program.reply_chain,
        drone_connected=node.drone_connected,
        drone_calls=node.program.drone_calls,
        waiting=node.waiting,
        waits=[w.to_proto() for w in node.waits],
        epoch=p.epoch,
        catching_up_to=0 if p.caught_up else (p.catch_up_to or 0),
        watermark_reqnr=p.watermark_reqnr,
        fenced_messages=node.books.fenced_messages,
        program_restarts=node.program.restarts,
        routed_around=node.routed_around,
        standby_up=node.standby_up,
        answered_from_retained=node.answered_from_retained,
        log_file=node.history.status(),
        refused_messages=node.core.refused_messages,
        last_refused=node.core.last_refused,
        refused_words=node.core.refused_words,
        last_refused_word=node.core.last_refused_word,
        handovers=[
            ring_pb2.ControllerHandover(
                role=h.role,
                peer=h.peer,
                lognr=h.lognr,
                reqnr=h.reqnr,
                log_bytes=h.log_bytes,
                at=h.at,
                epoch=h.epoch,
                drone_after_reqnr=h.drone_after_reqnr,
                holds_reqnr=h.holds_reqnr,
                first_new_reqnr=h.first_new_reqnr,
                first_new_at=h.first_new_at,
            )
            for h in node.handovers
        ],
        t_conn_s=node.all_t_conn_s,
        drone_connected_at=node.all_drone_connected_at,
        mission_address=node.mission_address,
        mission_id=node.config.mission_id or "",
    )

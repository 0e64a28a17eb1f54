"""The station port's one dispatcher: each ControllerRing call to the session of the
mission its ``baton-mission`` metadata names (rules.route).

Each session keeps the servicer a lone controller serves on its own port
(controller/service.py ``ControllerRingService``), unchanged: the router
collects the method handlers that servicer's generated ``add_..._to_server``
registers, and hands each call to the handlers of its mission. A call the
router refuses (no mission named, one not hosted) ends with the refusal
before its request is read.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import grpc

from baton.rpc.errors import StatusError, abort_with
from baton.rpc.mission import mission_in
from baton.station.rules import route
from baton.v1 import ring_pb2, ring_pb2_grpc

RING_SERVICE = "baton.v1.ControllerRing"
Handlers = Mapping[str, grpc.RpcMethodHandler]
_RING_METHODS = {
    f"/{RING_SERVICE}/{m.name}": m
    for m in ring_pb2.DESCRIPTOR.services_by_name["ControllerRing"].methods
}


class _Collector:
    """Takes the handlers a generated ``add_..._to_server`` gives a server."""

    def __init__(self) -> None:
        self.handlers: dict[str, grpc.RpcMethodHandler] = {}

    def add_generic_rpc_handlers(self, handlers: object) -> None:
        """The same handlers again, the older way: the registered ones are kept."""

    def add_registered_method_handlers(
        self, service: str, handlers: Mapping[str, grpc.RpcMethodHandler]
    ) -> None:
        self.handlers |= {f"/{service}/{name}": h for name, h in handlers.items()}


def ring_handlers(ring_servicer: ring_pb2_grpc.ControllerRingServicer) -> Handlers:
    """The method handlers of one session's ControllerRing servicer, by full method name."""
    collector = _Collector()
    ring_pb2_grpc.add_ControllerRingServicer_to_server(ring_servicer, collector)  # type: ignore[arg-type]
    return collector.handlers


def _refusing(method: str, error: StatusError) -> grpc.RpcMethodHandler:
    """A handler of ``method``'s kind that ends the call with ``error``."""

    async def refuse(request: Any, context: grpc.aio.ServicerContext) -> None:
        await abort_with(context, error)

    rpc = _RING_METHODS[method]
    make: Callable[..., grpc.RpcMethodHandler]
    if rpc.client_streaming and rpc.server_streaming:
        make = grpc.stream_stream_rpc_method_handler
    elif rpc.client_streaming:
        make = grpc.stream_unary_rpc_method_handler
    elif rpc.server_streaming:
        make = grpc.unary_stream_rpc_method_handler
    else:
        make = grpc.unary_unary_rpc_method_handler
    return make(refuse)


class MissionRouter(grpc.GenericRpcHandler):
    """ControllerRing for every session of a station, routed by mission id."""

    def __init__(self, station_id: int, sessions: Callable[[], Mapping[str, Handlers]]) -> None:
        self._station_id = station_id
        self._sessions = sessions  # the hosting sessions' handlers, by mission id, now

    def service(
        self, handler_call_details: grpc.HandlerCallDetails
    ) -> grpc.RpcMethodHandler | None:
        method = handler_call_details.method
        if method not in _RING_METHODS:
            return None
        mission = mission_in(handler_call_details.invocation_metadata)
        found = route(self._sessions(), mission, self._station_id, method)
        if isinstance(found, StatusError):
            return _refusing(method, found)
        return found.get(method)

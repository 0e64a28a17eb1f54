"""Which code answers which drone-API method, read from the proto descriptors.

``Drone.Invoke`` carries a full gRPC method name and a serialized request.
The routing table is built from ``drone_api.proto``'s service descriptors, so
a method added to the contract is routed (or reported UNIMPLEMENTED by the
backend) without a hand-written list to keep in sync.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from typing import Any

import grpc
from google.protobuf import message_factory
from google.protobuf.descriptor import ServiceDescriptor
from google.protobuf.message import DecodeError, Message

from baton.rpc.errors import StatusError
from baton.v1 import drone_api_pb2 as api

# Services the drone answers itself; Clock is answered by the controller so
# that every replica of a mission program reads the same (logged) time.
DRONE_SERVICES = ("Mobility", "Camera")
CONTROLLER_SERVICES = ("Clock",)

Handler = Callable[[Any], Awaitable[Message]]


@dataclass(frozen=True)
class Route:
    """One drone-API method: its types and the service that implements it."""

    method: str  # full gRPC name, "/baton.v1.Mobility/GetPosition"
    service: str  # "Mobility"
    name: str  # "GetPosition"
    request_type: type[Message]
    reply_type: type[Message]

    @property
    def answered_by_drone(self) -> bool:
        """False for Clock methods, which only a controller may answer."""
        return self.service in DRONE_SERVICES

    @property
    def is_read(self) -> bool:
        """Reads (Get*) change nothing: logged at debug level (commands at info), and
        executed again when a restart cut them off (store.py)."""
        return self.name.startswith("Get")

    def parse(self, payload: bytes) -> Message:
        """The request message; INVALID_ARGUMENT if the payload does not parse."""
        request = self.request_type()
        try:
            request.ParseFromString(payload)
        except DecodeError as exc:
            raise StatusError(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"payload of {self.method} is not a {self.request_type.DESCRIPTOR.full_name}: "
                f"{exc}",
            ) from None
        return request


def _routes_of(service: ServiceDescriptor) -> dict[str, Route]:
    routes = {}
    for method in service.methods:
        full = f"/{service.full_name}/{method.name}"
        routes[full] = Route(
            method=full,
            service=service.name,
            name=method.name,
            request_type=message_factory.GetMessageClass(method.input_type),
            reply_type=message_factory.GetMessageClass(method.output_type),
        )
    return routes


def drone_api_routes() -> dict[str, Route]:
    """Every method of the drone API (Mobility, Camera, Clock) by full gRPC name."""
    routes: dict[str, Route] = {}
    for name in (*DRONE_SERVICES, *CONTROLLER_SERVICES):
        routes.update(_routes_of(api.DESCRIPTOR.services_by_name[name]))
    return routes


class Dispatcher:
    """Finds the route of a method and the coroutine that executes it.

    ``implementations`` maps a service name to the object with one coroutine
    per RPC, named as in the proto (the Mobility backend, the camera).
    """

    def __init__(self, implementations: Mapping[str, object]) -> None:
        self.routes = drone_api_routes()
        self._implementations = dict(implementations)

    def route(self, method: str) -> Route:
        """The route of ``method``; UNIMPLEMENTED if the drone does not answer it."""
        route = self.routes.get(method)
        if route is None:
            raise StatusError(
                grpc.StatusCode.UNIMPLEMENTED,
                f"unknown drone-API method {method!r}; expected a full gRPC name like "
                "'/baton.v1.Mobility/GetPosition'",
            )
        if not route.answered_by_drone:
            raise StatusError(
                grpc.StatusCode.UNIMPLEMENTED,
                f"{method}: {route.service} is answered by the controller, not the drone",
            )
        return route

    def handler(self, route: Route) -> Handler:
        """The coroutine function for ``route``; UNIMPLEMENTED if its service lacks it."""
        implementation = self._implementations.get(route.service)
        handler = getattr(implementation, route.name, None)
        if handler is None:
            raise StatusError(
                grpc.StatusCode.UNIMPLEMENTED,
                f"{route.method} is in the contract but this drone has no {route.service} "
                "implementation for it",
            )
        return handler  # type: ignore[no-any-return]

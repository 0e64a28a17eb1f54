"""Which code answers which drone-API method.

``Drone.Invoke`` carries a full gRPC method name and a serialized request.
The routing table is the drone API's one method table (``rpc/methods.py``,
read from ``drone_api.proto``'s service descriptors), so a method added to
the contract is routed (or reported UNIMPLEMENTED by the backend) without a
hand-written list to keep in sync.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping
from typing import Any

import grpc
from google.protobuf.message import Message

from baton.rpc.errors import StatusError
from baton.rpc.methods import Method, drone_api, path

Handler = Callable[[Any], Awaitable[Message]]
# A drone-API method as the dispatcher routes it (the one table: rpc/methods.py).
Route = Method
# Services answered by another service's implementation: the gimbal is reached over
# the vehicle's own MAVLink link, so the vehicle backend (MAVSDK) answers it too.
ANSWERED_BY = {"Gimbal": "Mobility"}


class Dispatcher:
    """Finds the route of a method and the coroutine that executes it.

    ``implementations`` maps a service name to the object with one coroutine
    per RPC, named as in the proto (the Mobility backend, the camera); a service
    not in it is answered by the one ``ANSWERED_BY`` names, if any.
    """

    def __init__(self, implementations: Mapping[str, object]) -> None:
        self.routes = drone_api()
        self._implementations = dict(implementations)

    def route(self, method: str) -> Route:
        """The route of ``method``; UNIMPLEMENTED if the drone does not answer it."""
        route = self.routes.get(method)
        if route is None:
            raise StatusError(
                grpc.StatusCode.UNIMPLEMENTED,
                f"unknown drone-API method {method!r}; expected a full gRPC name like "
                f"{path('Mobility.GetPosition')!r}",
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
        if implementation is None and route.service in ANSWERED_BY:
            implementation = self._implementations.get(ANSWERED_BY[route.service])
        handler = getattr(implementation, route.name, None)
        if handler is None:
            raise StatusError(
                grpc.StatusCode.UNIMPLEMENTED,
                f"{route.path} is in the contract but this drone has no {route.service} "
                "implementation for it",
            )
        return handler  # type: ignore[no-any-return]

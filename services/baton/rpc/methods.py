"""The drone API's methods (and the ring's), read once from the contracts' descriptors.

A method has two names: ``"Mobility.GetPosition"`` (its ``rpc``, for people
and error messages) and its gRPC path ``"/baton.v1.Mobility/GetPosition"``
(what ``Drone.Invoke``, the log and the audit carry). Code that needs one
asks ``path("Mobility.GetPosition")`` or ``method(...)``, which look the
name up in the descriptors and raise at import time for a name the
contracts lack, instead of spelling the path by hand. ``drone_api()`` is the
one table of the drone API: the drone's dispatcher, the controller's proxy,
``baton replay`` and the simulation all read it, and a method added to
``drone_api.proto`` is in it without a line here.

Shared with the SDK (``clients/pyproject.toml`` ships this module with the
``baton-sdk`` wheel): it imports only the contracts and ``rpc/errors.py``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from types import MappingProxyType

import grpc
from google.protobuf import message_factory, text_format
from google.protobuf.message import DecodeError, Message

from baton.rpc.errors import StatusError
from baton.v1 import drone_api_pb2, ring_pb2

# Services the drone answers itself; Clock is answered by the controller so
# that every replica of a mission program reads the same (logged) time.
DRONE_SERVICES = ("Mobility", "Camera", "Gimbal")
CONTROLLER_SERVICES = ("Clock",)
# The drone API a mission program calls (the controller proxies all of it).
DRONE_API_SERVICES = (*DRONE_SERVICES, *CONTROLLER_SERVICES)
# Where each service is described: the drone API, then the controller ring.
_CONTRACTS = (drone_api_pb2, ring_pb2)


@dataclass(frozen=True)
class Method:
    """One method of a contract: its names and its message types."""

    path: str  # full gRPC name, "/baton.v1.Mobility/GetPosition"
    service: str  # "Mobility"
    name: str  # "GetPosition"
    request_type: type[Message]
    reply_type: type[Message]

    @property
    def rpc(self) -> str:
        """``Service.Method``, the name people read ("Mobility.GetPosition")."""
        return f"{self.service}.{self.name}"

    @property
    def answered_by_drone(self) -> bool:
        """False for Clock methods, which only a controller may answer."""
        return self.service in DRONE_SERVICES

    @property
    def is_read(self) -> bool:
        """Reads (Get*) change nothing: logged at debug level (commands at info), and
        executed again when a restart cut them off (drone/store.py)."""
        return self.name.startswith("Get")

    def parse(self, payload: bytes) -> Message:
        """The request message; INVALID_ARGUMENT if the payload does not parse."""
        request = self.request_type()
        try:
            request.ParseFromString(payload)
        except DecodeError as exc:
            raise StatusError(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"payload of {self.path} is not a {self.request_type.DESCRIPTOR.full_name}: {exc}",
            ) from None
        return request


def _method_of(service_name: str, method_name: str) -> Method | None:
    for contract in _CONTRACTS:
        service = contract.DESCRIPTOR.services_by_name.get(service_name)
        if service is None or method_name not in service.methods_by_name:
            continue
        described = service.methods_by_name[method_name]
        return Method(
            path=f"/{service.full_name}/{method_name}",
            service=service_name,
            name=method_name,
            request_type=message_factory.GetMessageClass(described.input_type),
            reply_type=message_factory.GetMessageClass(described.output_type),
        )
    return None


@cache
def method(rpc: str) -> Method:
    """The method named ``Service.Method`` ("Mobility.GetPosition"); ValueError if the
    drone API and the controller ring have no such method."""
    service_name, _, method_name = rpc.partition(".")
    found = _method_of(service_name, method_name)
    if found is None:
        raise ValueError(
            f"{rpc!r}: not a method of the drone API or the controller ring "
            "(protos/baton/v1/drone_api.proto, ring.proto); expected Service.Method, "
            "like 'Mobility.GetPosition'"
        )
    return found


def path(rpc: str) -> str:
    """The gRPC path of ``Service.Method``: ``path("Clock.Sleep")`` is "/baton.v1.Clock/Sleep"."""
    return method(rpc).path


def service_prefix(service_name: str) -> str:
    """The start every path of a service shares: "/baton.v1.Clock/"."""
    for contract in _CONTRACTS:
        service = contract.DESCRIPTOR.services_by_name.get(service_name)
        if service is not None:
            return f"/{service.full_name}/"
    raise ValueError(f"{service_name!r}: not a service of the drone API or the controller ring")


def service_full_name(service_name: str) -> str:
    """A service's full name ("baton.v1.Mobility"), for reflection and health."""
    return service_prefix(service_name).strip("/")


@cache
def drone_api() -> Mapping[str, Method]:
    """Every method of the drone API (Mobility, Camera, Gimbal, Clock), by gRPC path."""
    table: dict[str, Method] = {}
    for service_name in DRONE_API_SERVICES:
        service = drone_api_pb2.DESCRIPTOR.services_by_name[service_name]
        for described in service.methods:
            found = method(f"{service_name}.{described.name}")
            table[found.path] = found
    return MappingProxyType(table)


def rpc_of(grpc_path: str) -> str:
    """``Service.Method`` of a gRPC path ("/baton.v1.Mobility/Arm" -> "Mobility.Arm");
    a path outside the contracts' package keeps its package."""
    package = f"/{drone_api_pb2.DESCRIPTOR.package}."
    return grpc_path.removeprefix(package).replace("/", ".")


def describe_request(method: str, request: bytes) -> str:
    """``Service.Method {fields}``: a logged or asked request as readable protobuf text
    (its bytes in hex where it is not a drone-API method or does not decode)."""
    name = rpc_of(method)
    found = drone_api().get(method)
    if found is None:
        return f"{name} (not a drone-API method) request bytes {bytes(request).hex()}"
    try:
        decoded = found.request_type.FromString(request)
    except DecodeError:
        return f"{name} (does not decode) request bytes {bytes(request).hex()}"
    return f"{name} {{{text_format.MessageToString(decoded, as_one_line=True)}}}"


def differing_fields(method: str, logged: bytes, asked: bytes) -> list[str]:
    """The fields of two requests of ``method`` that differ (empty if not decodable)."""
    found = drone_api().get(method)
    if found is None:
        return []
    request_class = found.request_type
    try:
        a, b = request_class.FromString(logged), request_class.FromString(asked)
    except DecodeError:
        return []
    return [
        field.name
        for field in request_class.DESCRIPTOR.fields
        if getattr(a, field.name) != getattr(b, field.name)
    ]


def describe_nondeterminism(
    reqnr: int, logged_method: str, logged_request: bytes, method: str, request: bytes
) -> str:
    """The determinism guard's message: both requests decoded as ``baton replay`` shows
    them, and the fields that differ when the method is the same."""
    text = (
        f"non-deterministic mission program at request {reqnr}: the log holds "
        f"{describe_request(logged_method, logged_request)} but this program asks "
        f"{describe_request(method, request)}"
    )
    if logged_method == method:
        fields = differing_fields(method, logged_request, request)
        if fields:
            text += f" (fields that differ: {', '.join(fields)})"
    return text

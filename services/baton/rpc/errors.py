"""An exception that carries a gRPC status, raised anywhere and mapped once.

Handlers raise ``StatusError(code, message)``; ``abort_with`` turns it into
the RPC's status. Status codes mean what the gRPC docs say they mean:
INVALID_ARGUMENT for a request that can never succeed as sent,
FAILED_PRECONDITION for one that could succeed in another state (not the
master, vehicle not armed), UNAVAILABLE for a peer or vehicle that is not
reachable now, ABORTED for an autopilot that refused a command.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NoReturn

import grpc

_STATUS_BY_CODE = {code.value[0]: code for code in grpc.StatusCode}


def status_of(code: int) -> grpc.StatusCode:
    """The grpc.StatusCode with numeric value ``code`` (UNKNOWN for a number gRPC lacks)."""
    return _STATUS_BY_CODE.get(code, grpc.StatusCode.UNKNOWN)


class StatusError(Exception):
    """A failure with the gRPC status code a caller should see."""

    def __init__(
        self,
        code: grpc.StatusCode,
        message: str,
        metadata: Sequence[tuple[str, str]] = (),
    ) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.metadata = tuple(metadata)

    def __str__(self) -> str:
        return f"{self.code.name}: {self.message}"


async def abort_with(context: grpc.aio.ServicerContext, error: StatusError) -> NoReturn:
    """Ends the RPC with the error's status, message and trailing metadata."""
    if error.metadata:
        context.set_trailing_metadata(error.metadata)
    await context.abort(error.code, error.message)
    raise AssertionError("unreachable: context.abort raises")

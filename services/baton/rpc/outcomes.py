"""A call's failure as a message on a stream, and back (drone.proto ``InvokeStream``).

A call on a stream cannot end with its own status: its failure travels in its
outcome (``CallFailure``), and the caller raises from it the error its unary
call would have raised, so the code that handles both is one (docs/design.md,
"The proxy path"). Not in the SDK's distribution, as the drone's contract is not.
"""

from __future__ import annotations

import grpc

from baton.rpc.errors import StatusError, status_of
from baton.v1 import drone_api_pb2


def failure_of(error: StatusError) -> drone_api_pb2.CallFailure:
    """A call's failure on a stream (drone.proto InvokeStream) as its RPC would end."""
    return drone_api_pb2.CallFailure(
        code=error.code.value[0], message=error.message, metadata=dict(error.metadata)
    )


def error_of(failure: drone_api_pb2.CallFailure) -> grpc.aio.AioRpcError:
    """The error a caller's RPC would have raised for a call's ``failure`` on a stream,
    with its code, details and trailing metadata: callers handle both alike."""
    return grpc.aio.AioRpcError(
        status_of(failure.code),
        grpc.aio.Metadata(),
        grpc.aio.Metadata(*failure.metadata.items()),
        failure.message,
    )

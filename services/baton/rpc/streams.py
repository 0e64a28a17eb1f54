"""Reading and writing a ``grpc.aio`` stream's messages with their types.

A call's ``read()`` returns the next message or ``grpc.aio.EOF``, which grpc's
stubs type as ``object``: every reader would have to narrow it again. These
two read one message and say the end in a typed way. A call's ``write()`` on
a call that finished raises ``asyncio.InvalidStateError``, not the call's
status: ``write_message`` says that end as every other end of a stream is said.
"""

from __future__ import annotations

import asyncio
from typing import Any, TypeVar, cast

import grpc

_Request = TypeVar("_Request")
_Reply = TypeVar("_Reply")

_Stream = grpc.aio.UnaryStreamCall[Any, _Reply] | grpc.aio.StreamStreamCall[Any, _Reply]


async def read_message(call: _Stream[_Reply]) -> _Reply | None:
    """The stream's next message, or None once the peer has ended it."""
    message = await call.read()
    if message is grpc.aio.EOF:
        return None
    return cast(_Reply, message)


async def next_message(call: _Stream[_Reply]) -> _Reply:
    """The stream's next message, for a reader that expects one: EOFError at its end."""
    message = await read_message(call)
    if message is None:
        raise EOFError("the stream ended before its next message")
    return message


async def write_message(
    call: grpc.aio.StreamStreamCall[_Request, Any] | grpc.aio.StreamUnaryCall[_Request, Any],
    message: _Request,
) -> None:
    """Writes ``message`` on the stream. A call that finished before the write (its peer
    ended it, or it broke: grpc raises InvalidStateError, 'RPC already finished') raises
    the AioRpcError of its status, as a write the end cut short does: to the writer the
    stream is down. One its peer ended with OK is UNAVAILABLE here: the message was not
    taken, and a new stream may take it."""
    try:
        await call.write(message)
    except asyncio.InvalidStateError:
        if not call.done():
            raise  # a write after the writer's own done_writing: a fault of the writer
        code, details = await call.code(), await call.details()
        if code is grpc.StatusCode.OK:
            code, details = grpc.StatusCode.UNAVAILABLE, "the peer ended the stream"
        raise grpc.aio.AioRpcError(
            code, await call.initial_metadata(), await call.trailing_metadata(), details
        ) from None

"""Reading a ``grpc.aio`` stream's messages with their types.

A call's ``read()`` returns the next message or ``grpc.aio.EOF``, which grpc's
stubs type as ``object``: every reader would have to narrow it again. These
two read one message and say the end in a typed way.
"""

from __future__ import annotations

from typing import Any, TypeVar, cast

import grpc

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

"""Calls on the drone service as a controller makes them: paths, requests, errors."""

from __future__ import annotations

from collections.abc import Awaitable

import grpc
import pytest
from google.protobuf.message import Message

from baton.v1 import drone_pb2

POSITION = "/baton.v1.Mobility/GetPosition"


ARM = "/baton.v1.Mobility/Arm"


TAKEOFF = "/baton.v1.Mobility/Takeoff"


GOTO = "/baton.v1.Mobility/Goto"


def invoke(
    cid: int, reqnr: int, method: str, request: Message | None = None, epoch: int = 1
) -> drone_pb2.InvokeRequest:
    payload = request.SerializeToString() if request is not None else b""
    return drone_pb2.InvokeRequest(
        controller_id=cid, reqnr=reqnr, method=method, payload=payload, epoch=epoch
    )


async def expect_error(call: Awaitable[object], code: grpc.StatusCode) -> grpc.aio.AioRpcError:
    with pytest.raises(grpc.aio.AioRpcError) as info:
        await call
    assert info.value.code() == code, info.value.details()
    return info.value


async def refused_details(call: Awaitable[object], code: grpc.StatusCode) -> str:
    """What a call that ends with ``code`` said (``expect_error``'s details)."""
    return (await expect_error(call, code)).details() or ""

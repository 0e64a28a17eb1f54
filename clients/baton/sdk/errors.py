"""Exceptions a mission program sees, and how both APIs make them."""

from __future__ import annotations

import grpc
import grpc.aio


class DroneCallError(Exception):
    """A drone-API call failed; ``rpc`` names it, ``code`` is its gRPC status."""

    def __init__(self, rpc: str, code: grpc.StatusCode, details: str) -> None:
        super().__init__(f"{rpc} failed with {code.name}: {details}")
        self.rpc = rpc
        self.code = code
        self.details = details


class ConcurrentCallError(RuntimeError):
    """A second call while one is pending: the replay needs one call at a time."""


def call_error(rpc: str, exc: grpc.RpcError) -> DroneCallError:
    """The ``DroneCallError`` of a failed call, from the blocking or the asyncio channel."""
    if isinstance(exc, grpc.Call | grpc.aio.AioRpcError):
        return DroneCallError(rpc, exc.code(), exc.details() or "")
    return DroneCallError(rpc, grpc.StatusCode.UNKNOWN, str(exc))


def concurrent_call_error(rpc: str, pending: str) -> ConcurrentCallError:
    """The error of ``rpc`` called while ``pending`` has not returned."""
    return ConcurrentCallError(
        f"{rpc} called while {pending} is pending: a mission program makes one call "
        "at a time, so that every replica replays it"
    )

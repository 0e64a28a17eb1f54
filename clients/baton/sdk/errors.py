"""Exceptions a mission program sees."""

from __future__ import annotations

import grpc


class DroneCallError(Exception):
    """A drone-API call failed; ``rpc`` names it, ``code`` is its gRPC status."""

    def __init__(self, rpc: str, code: grpc.StatusCode, details: str) -> None:
        super().__init__(f"{rpc} failed with {code.name}: {details}")
        self.rpc = rpc
        self.code = code
        self.details = details


class ConcurrentCallError(RuntimeError):
    """A second call while one is pending: the replay needs one call at a time."""

"""Malformed input for the fuzz tests (issue 11): seeded mutants of valid requests,
and the status one raw request ends with."""

from __future__ import annotations

import random

import grpc

SEED = 11
INPUTS_PER_METHOD = 150
# The codes of an exception nobody handled: never a server's answer to bad input.
UNHANDLED = {grpc.StatusCode.UNKNOWN, grpc.StatusCode.INTERNAL}


def mutants(valid: list[bytes], rng: random.Random, count: int) -> list[bytes]:
    """``count`` inputs: valid ones flipped, cut, extended, and plain random bytes."""
    out = []
    for k in range(count):
        base = bytearray(rng.choice(valid))
        kind = k % 4
        if kind == 0 and base:
            for _ in range(rng.randint(1, 4)):
                base[rng.randrange(len(base))] = rng.randrange(256)
        elif kind == 1 and base:
            base = base[: rng.randrange(len(base))]
        elif kind == 2:
            base += rng.randbytes(rng.randint(1, 16))
        else:
            base = bytearray(rng.randbytes(rng.randint(0, 64)))
        out.append(bytes(base))
    return out


async def answer(
    channel: grpc.aio.Channel, method: str, raw: bytes, stream: bool
) -> grpc.StatusCode:
    """The status one raw request ends with; a stream's first message counts as OK."""
    try:
        if stream:
            raw_stream: grpc.aio.UnaryStreamMultiCallable[bytes, bytes]
            raw_stream = channel.unary_stream(method)
            call = raw_stream(raw, timeout=2)
            await call.read()
            call.cancel()
        else:
            raw_unary: grpc.aio.UnaryUnaryMultiCallable[bytes, bytes]
            raw_unary = channel.unary_unary(method)
            await raw_unary(raw, timeout=2)
    except grpc.aio.AioRpcError as err:
        return err.code()
    return grpc.StatusCode.OK

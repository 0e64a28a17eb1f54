"""The pure admission decisions (rpc/admission.py), the ports' rules (ports.py), and
the gate that applies them (gate.py) on a real server."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

import grpc
import pytest

from baton.certs.make import init
from baton.rpc.admission import Caller, PortPolicy, admit, port_full, to_cut
from baton.rpc.channels import aio_channel
from baton.rpc.mission import mission_metadata
from baton.rpc.ports import (
    DRONE_REQUEST_BYTES,
    PROGRAM_PORT_CALLS,
    drone_policy,
    mission_policy,
    ring_policy,
    station_policy,
)
from baton.rpc.server import BatonServer, generic
from baton.rpc.tls import DRONE, OPERATOR, Identity, Tls

DRONE_PORT = drone_policy([0, 1, 2])
INVOKE, HANDOVER, STATUS = (
    "/baton.v1.Drone/Invoke",
    "/baton.v1.Drone/Handover",
    "/baton.v1.Drone/GetStatus",
)
NOW = 1_800_000_000.0
STATION = Caller(Identity.controller(1), 0x51, NOW + 3600)
Queue = asyncio.Queue[None]


def test_the_drone_admits_its_controllers_and_an_operator_each_to_their_calls() -> None:
    assert admit(DRONE_PORT, INVOKE, STATION, frozenset(), 0, NOW) is None
    assert admit(DRONE_PORT, HANDOVER, Caller(OPERATOR, 7), frozenset(), 0, NOW) is None
    for who in (Caller(OPERATOR, 7), Caller(DRONE, 8), Caller(Identity.controller(9), 9)):
        refusal = admit(DRONE_PORT, INVOKE, who, frozenset(), 0, NOW)
        assert refusal is not None and refusal.code is grpc.StatusCode.PERMISSION_DENIED
        assert "Invoke: refused to" in refusal.message and "before reading" in refusal.message
    for operators in ("Handover", "Resume", "Pause", "Abort", "LandNow"):
        refusal = admit(DRONE_PORT, "/baton.v1.Drone/" + operators, STATION, frozenset(), 0, NOW)
        assert refusal is not None and "only an operator" in refusal.message
    assert admit(DRONE_PORT, STATUS, Caller(DRONE, 8), frozenset(), 0, NOW) is None
    assert DRONE_PORT.max_request_bytes == DRONE_REQUEST_BYTES


def test_a_revoked_certificate_or_none_is_unauthenticated_whatever_the_call() -> None:
    for method in (INVOKE, STATUS):
        refusal = admit(DRONE_PORT, method, STATION, frozenset({0x51}), 0, NOW)
        assert refusal is not None and refusal.code is grpc.StatusCode.UNAUTHENTICATED
        assert "serial 51" in refusal.message and "revoked" in refusal.message
    refusal = admit(DRONE_PORT, STATUS, Caller(None, None), frozenset(), 0, NOW)
    assert refusal is not None and refusal.code is grpc.StatusCode.UNAUTHENTICATED


def test_one_caller_holds_at_most_its_share_of_calls() -> None:
    cap = DRONE_PORT.calls_per_caller
    assert admit(DRONE_PORT, INVOKE, STATION, frozenset(), cap - 1, NOW) is None
    refusal = admit(DRONE_PORT, INVOKE, STATION, frozenset(), cap, NOW)
    assert refusal is not None and refusal.code is grpc.StatusCode.RESOURCE_EXHAUSTED


def test_a_stations_port_caps_a_callers_calls_per_mission_and_over_all() -> None:
    port = station_policy()
    log_ring, cap = "/baton.v1.ControllerRing/LogRing", port.calls_per_caller
    all_cap = port.calls_per_caller_all_missions
    assert all_cap is not None and all_cap > cap
    # A caller's streams for one mission do not take the room of its others.
    assert admit(port, log_ring, STATION, frozenset(), 0, NOW, cap) is None
    refusal = admit(port, log_ring, STATION, frozenset(), cap, NOW, cap)
    assert refusal is not None and refusal.code is grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "for this mission" in refusal.message
    refusal = admit(port, log_ring, STATION, frozenset(), 0, NOW, all_cap)
    assert refusal is not None and "for all its missions" in refusal.message
    # Stations stream frames; the operator alone starts and stops sessions.
    start = "/baton.v1.Station/StartMission"
    assert admit(port, start, Caller(OPERATOR, 7), frozenset(), 0, NOW) is None
    refusal = admit(port, start, STATION, frozenset(), 0, NOW)
    assert refusal is not None and refusal.code is grpc.StatusCode.PERMISSION_DENIED
    assert admit(port, log_ring, Caller(DRONE, 8), frozenset(), 0, NOW) is not None


def test_the_ring_port_takes_frames_from_the_ring_and_reads_a_slice_and_its_head() -> None:
    ring = ring_policy([0, 1, 2], 16 << 10)
    log_ring = "/baton.v1.ControllerRing/LogRing"
    assert admit(ring, log_ring, STATION, frozenset(), 0, NOW) is None
    assert admit(ring, log_ring, Caller(OPERATOR, 1), frozenset(), 0, NOW) is not None
    assert 16 << 10 < ring.max_request_bytes <= 1 << 20


def test_an_expired_certificate_on_a_connection_made_before_is_refused() -> None:
    refusal = admit(DRONE_PORT, STATUS, STATION, frozenset(), 0, NOW + 3601)
    assert refusal is not None and refusal.code is grpc.StatusCode.UNAUTHENTICATED
    assert "has expired" in refusal.message


def test_the_timer_cuts_exactly_the_streams_whose_certificates_no_longer_count() -> None:
    other = Caller(Identity.controller(2), 0x52, NOW + 60)
    live = {"a": STATION, "b": other, "c": Caller(None, None), "d": STATION}
    assert to_cut(live, frozenset({0x51}), NOW) == ["a", "d"]
    assert to_cut(live, frozenset(), NOW) == []
    assert to_cut(live, frozenset(), NOW + 61) == ["b"]


def test_a_mission_port_takes_at_most_its_calls_in_flight_whoever_makes_them() -> None:
    port, get_position = mission_policy(), "/baton.v1.Mobility/GetPosition"
    cap = port.calls_in_flight
    assert cap is not None and cap == PROGRAM_PORT_CALLS
    assert port_full(port, get_position, cap - 1) is None
    refusal = port_full(port, get_position, cap)
    assert refusal is not None and refusal.code is grpc.StatusCode.RESOURCE_EXHAUSTED
    assert refusal.message.startswith(f"GetPosition: the mission port has {cap} calls in flight")
    # A port of many callers bounds each caller's share instead.
    assert port_full(station_policy(), get_position, 10_000) is None


@contextlib.asynccontextmanager
async def holding_port(
    tmp_path: Path, policy: PortPolicy, insecure: bool = False
) -> AsyncIterator[tuple[grpc.aio.UnaryUnaryMultiCallable[bytes, bytes], asyncio.Event, Queue]]:
    """A real server with ``policy`` whose one method holds each call until released,
    and controller 1's way to call it (``insecure``: anyone's, on a port without TLS):
    (the call, the release, a queue of arrivals)."""
    certs = tmp_path / "certs"
    init(certs, [Identity.controller(1), DRONE])
    release, arrived = asyncio.Event(), Queue()

    async def hold(request: bytes, context: grpc.aio.ServicerContext) -> bytes:
        arrived.put_nowait(None)
        await release.wait()
        return request

    handler: grpc.RpcMethodHandler[bytes, bytes] = grpc.unary_unary_rpc_method_handler(hold)
    served = generic(grpc.method_handlers_generic_handler("test.Hold", {"Hold": handler}))
    own = None if insecure else Tls.load(certs, DRONE)
    server = BatonServer("127.0.0.1:0", [served], tls=own, policy=policy)
    await server.start()
    try:
        tls = None if insecure else Tls.load(certs, Identity.controller(1))
        async with aio_channel(server.address, tls, None if insecure else DRONE) as channel:
            yield channel.unary_unary("/test.Hold/Hold"), release, arrived
    finally:
        release.set()
        await server.stop(0)


async def test_a_port_holds_at_most_a_callers_share_and_frees_it_as_calls_end(
    tmp_path: Path,
) -> None:
    """Through a real server: the gate counts a caller's calls in flight, refuses the
    one above the cap before reading it, and counts a finished call out."""
    policy = PortPolicy("test port", 1 << 20, calls_per_caller=4)
    async with holding_port(tmp_path, policy) as (call, release, arrived):
        held = [asyncio.ensure_future(call(b"x", timeout=20)) for _ in range(4)]
        for _ in held:
            await asyncio.wait_for(arrived.get(), 20)
        with pytest.raises(grpc.aio.AioRpcError) as refused:
            await call(b"y" * (1 << 19), timeout=20)
        assert refused.value.code() is grpc.StatusCode.RESOURCE_EXHAUSTED
        assert "4 calls in flight on the test port" in (refused.value.details() or "")
        # A port of one mission counts the caller's calls whatever mission they name.
        with pytest.raises(grpc.aio.AioRpcError) as named:
            await call(b"y", timeout=20, metadata=mission_metadata("another"))
        assert named.value.code() is grpc.StatusCode.RESOURCE_EXHAUSTED
        release.set()
        assert await asyncio.gather(*held) == [b"x"] * 4
        assert await call(b"z", timeout=20) == b"z"


async def test_a_port_of_many_missions_counts_a_callers_calls_per_mission_it_names(
    tmp_path: Path,
) -> None:
    """A station's port: a caller's calls for one mission at the cap leave its calls for
    another admitted, up to the cap over all missions."""
    policy = PortPolicy("test port", 1 << 20, calls_per_caller=2, calls_per_caller_all_missions=3)
    async with holding_port(tmp_path, policy) as (call, release, arrived):
        held = [
            asyncio.ensure_future(call(b"x", timeout=20, metadata=mission_metadata(m)))
            for m in ("a", "a", "b")
        ]
        for _ in held:
            await asyncio.wait_for(arrived.get(), 20)
        for mission, why in (("a", "for this mission"), ("c", "for all its missions")):
            with pytest.raises(grpc.aio.AioRpcError) as refused:
                await call(b"y", timeout=20, metadata=mission_metadata(mission))
            assert refused.value.code() is grpc.StatusCode.RESOURCE_EXHAUSTED
            assert why in (refused.value.details() or "")
        release.set()
        assert await asyncio.gather(*held) == [b"x"] * 3


async def test_a_port_without_tls_holds_at_most_its_calls_in_flight_and_frees_them(
    tmp_path: Path,
) -> None:
    """Through a real server without TLS (a mission port's): the calls above the port's
    cap are refused before they are read, whoever makes them, until calls end."""
    policy = PortPolicy("test port", 1 << 20, calls_in_flight=3)
    async with holding_port(tmp_path, policy, insecure=True) as (call, release, arrived):
        held = [asyncio.ensure_future(call(b"x", timeout=20)) for _ in range(3)]
        for _ in held:
            await asyncio.wait_for(arrived.get(), 20)
        for _ in range(2):
            with pytest.raises(grpc.aio.AioRpcError) as refused:
                await call(b"y", timeout=20)
            assert refused.value.code() is grpc.StatusCode.RESOURCE_EXHAUSTED
            assert "the test port has 3 calls in flight" in (refused.value.details() or "")
        assert arrived.empty()  # the refused calls never reached the method
        release.set()
        assert await asyncio.gather(*held) == [b"x"] * 3
        assert await call(b"z", timeout=20) == b"z"

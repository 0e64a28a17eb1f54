"""LinkProxy inside the test's event loop: timing, integrity, closing, gRPC."""

from __future__ import annotations

import asyncio
import hashlib
import os
import statistics
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import pytest
import uvloop
from grpc_health.v1 import health_pb2, health_pb2_grpc
from link_endpoints import Echo, Sink, connect
from waiting import eventually

from baton.config import LinkSpec
from baton.link.cli import read_shape
from baton.link.proxy import READ_BYTES, LinkProxy, reset_connection
from baton.link.shaper import SEGMENT_BYTES, SerialLine
from baton.rpc.channels import aio_channel
from baton.rpc.server import BatonServer

OFF = LinkSpec()


@pytest.fixture
async def make_proxy() -> AsyncIterator[Callable[..., asyncio.Future[LinkProxy]]]:
    proxies: list[LinkProxy] = []

    async def make(target: str, up: LinkSpec = OFF, down: LinkSpec | None = None) -> LinkProxy:
        proxy = LinkProxy("127.0.0.1:0", target, up, up if down is None else down)
        await proxy.start()
        proxies.append(proxy)
        return proxy

    yield make  # type: ignore[misc]
    for proxy in proxies:
        await proxy.stop()


async def ping_pong(address: str, rounds: int) -> list[float]:
    """Round-trip times of one-byte messages over one connection."""
    loop = asyncio.get_running_loop()
    reader, writer = await connect(address)
    times = []
    for _ in range(rounds):
        started = loop.time()
        writer.write(b"x")
        assert await reader.readexactly(1) == b"x"
        times.append(loop.time() - started)
    writer.close()
    return times


async def test_round_trip_takes_twice_the_latency(echo: Echo, make_proxy) -> None:
    proxy = await make_proxy(echo.address, LinkSpec(latency=0.020))
    rtts = await ping_pong(proxy.address, 8)
    assert min(rtts) >= 0.040
    assert statistics.median(rtts) < 0.040 + 0.015


async def test_directions_are_shaped_separately(echo: Echo, make_proxy) -> None:
    proxy = await make_proxy(echo.address, LinkSpec(latency=0.030), LinkSpec(latency=0.005))
    rtts = await ping_pong(proxy.address, 5)
    assert min(rtts) >= 0.035
    assert statistics.median(rtts) < 0.035 + 0.015


async def test_a_reshaped_link_slows_its_open_connections(
    echo: Echo, make_proxy, tmp_path: Path
) -> None:
    """``baton link --shape-file`` on SIGHUP: the file read, every open line retuned."""
    proxy = await make_proxy(echo.address, LinkSpec(latency=0.005))
    loop = asyncio.get_running_loop()
    reader, writer = await connect(proxy.address)

    async def round_trip() -> float:
        started = loop.time()
        writer.write(b"x")
        assert await reader.readexactly(1) == b"x"
        return loop.time() - started

    assert await round_trip() < 0.005 * 2 + 0.015
    shape = tmp_path / "shape.json"
    shape.write_text('{"up": {"latency": "60ms"}}')
    up, down = read_shape(shape, proxy.up, proxy.down)
    assert (up.latency, down.latency) == (0.060, 0.005)  # down kept its own
    proxy.reshape(up, down)
    slow = await round_trip()
    assert 0.065 <= slow < 0.065 + 0.015, slow
    writer.close()
    for text, problem in (
        ("{", "not JSON"),
        ('{"sideways": {}}', "expected an object with 'up' and/or 'down'"),
        ('{"up": {"latency": "fast"}}', "latency"),
    ):
        shape.write_text(text)
        with pytest.raises(ValueError, match=problem) as bad:
            read_shape(shape, up, down)
        assert str(shape) in str(bad.value)


async def test_pass_through_is_fast_and_intact(echo: Echo, make_proxy) -> None:
    proxy = await make_proxy(echo.address)
    rtts = await ping_pong(proxy.address, 20)
    assert statistics.median(rtts) < 0.005
    payload = os.urandom(3 * 10**6)
    reader, writer = await connect(proxy.address)
    writer.write(payload)
    writer.write_eof()  # half-close: the echo still answers everything, then closes
    echoed = await asyncio.wait_for(reader.read(), 30)
    assert hashlib.sha256(echoed).digest() == hashlib.sha256(payload).digest()
    writer.close()
    assert proxy.counters.bytes_up == proxy.counters.bytes_down == len(payload) + len(rtts)


async def test_shaped_transfer_is_intact_and_paced(sink: Sink, make_proxy) -> None:
    proxy = await make_proxy(sink.address, LinkSpec(latency=0.010, bandwidth=80e6))
    payload = os.urandom(2 * 10**6)
    sink.expect = len(payload)
    _, writer = await connect(proxy.address)
    await asyncio.wait_for(sink.accepted.wait(), 10)
    loop = asyncio.get_running_loop()
    started = loop.time()
    writer.write(payload)
    await asyncio.wait_for(sink.done.wait(), 30)
    assert sink.done_at - started >= 0.010 + 16e6 / 80e6
    assert sink.digest.digest() == hashlib.sha256(payload).digest()
    writer.close()


async def test_buffering_stays_bounded_while_the_sender_is_faster(sink: Sink, make_proxy) -> None:
    spec = LinkSpec(latency=0.005, bandwidth=200e6)
    proxy = await make_proxy(sink.address, spec)
    size = 16 * 10**6
    sink.expect = size
    _, writer = await connect(proxy.address)
    writer.write(bytes(size))  # far more than the bound, all at once
    await asyncio.wait_for(sink.done.wait(), 60)
    assert proxy.counters.peak_in_flight <= SerialLine(spec).max_in_flight + READ_BYTES
    writer.close()


async def test_end_of_stream_propagates_both_ways(echo: Echo, make_proxy) -> None:
    proxy = await make_proxy(echo.address, LinkSpec(latency=0.005))
    reader, writer = await connect(proxy.address)
    writer.write(b"last words")
    writer.write_eof()
    # The echo answers, then closes once it sees our end: we see its end behind the data.
    assert await asyncio.wait_for(reader.read(), 10) == b"last words"
    writer.close()
    await _until(lambda: proxy.counters.active == 0)


async def test_target_close_reaches_the_client(sink: Sink, make_proxy) -> None:
    proxy = await make_proxy(sink.address, LinkSpec(latency=0.005))
    reader, writer = await connect(proxy.address)
    await asyncio.wait_for(sink.accepted.wait(), 10)
    sink.writers[0].close()
    assert await asyncio.wait_for(reader.read(), 10) == b""
    writer.close()


async def test_client_reset_resets_the_target(sink: Sink, make_proxy) -> None:
    proxy = await make_proxy(sink.address, LinkSpec(latency=0.005))
    _, writer = await connect(proxy.address)
    await asyncio.wait_for(sink.accepted.wait(), 10)
    reset_connection(writer)
    await asyncio.wait_for(sink.eof.wait(), 10)
    await _until(lambda: proxy.counters.active == 0)


async def test_unreachable_target_resets_the_client(sink: Sink, make_proxy) -> None:
    address = sink.address
    await sink.stop()
    await sink.start()  # a fresh port for the fixture's teardown; `address` is now closed
    proxy = await make_proxy(address)
    reader, writer = await connect(proxy.address)
    with pytest.raises((ConnectionError, asyncio.IncompleteReadError)):
        await asyncio.wait_for(reader.readexactly(1), 10)
    writer.close()
    assert proxy.counters.failed == 1


async def test_stop_closes_open_connections(echo: Echo) -> None:
    proxy = LinkProxy("127.0.0.1:0", echo.address, LinkSpec(latency=0.005), OFF)
    await proxy.start()
    reader, writer = await connect(proxy.address)
    writer.write(b"x")
    assert await asyncio.wait_for(reader.readexactly(1), 10) == b"x"
    await asyncio.wait_for(proxy.stop(), 10)
    with pytest.raises((ConnectionError, asyncio.IncompleteReadError)):
        await asyncio.wait_for(reader.readexactly(1), 10)
    writer.close()


async def test_grpc_calls_work_through_the_link_and_pay_its_round_trip(make_proxy) -> None:
    server = BatonServer("127.0.0.1:0", [])
    await server.start()
    try:
        link = LinkSpec(latency=0.010, bandwidth=25e6)
        proxy = await make_proxy(server.address, link)
        loop = asyncio.get_running_loop()
        async with aio_channel(proxy.address) as channel:
            # typeshed's HealthStub declares no methods (hence the two ignores below).
            stub = health_pb2_grpc.HealthStub(channel)
            times = []
            for _ in range(10):
                started = loop.time()
                check = health_pb2.HealthCheckRequest(service="")
                reply = await stub.Check(check, timeout=10)  # type: ignore[attr-defined]
                times.append(loop.time() - started)
                assert reply.status == health_pb2.HealthCheckResponse.SERVING
            # A watch stream: many small frames both ways over one long-lived connection.
            stream = stub.Watch(check, timeout=10)  # type: ignore[attr-defined]
            first = await stream.read()
            assert first.status == health_pb2.HealthCheckResponse.SERVING
            stream.cancel()
        # After the connection is up, a unary call is one round trip over the link.
        assert min(times[1:]) >= 0.020
        assert statistics.median(times[1:]) < 0.020 + 0.030
        assert proxy.counters.connections >= 1
    finally:
        await server.stop(0)


async def _until(condition: Callable[[], bool], deadline: float = 10.0) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + deadline
    while not condition():
        assert loop.time() < end, "condition not reached before the deadline"
        await asyncio.sleep(0.01)


def test_a_paced_transfer_waits_on_timers_not_by_spinning(monkeypatch) -> None:
    """Under uvloop, as the services run it: each 16 KiB segment is waited for about once.

    uvloop counts time in whole milliseconds, so a wait of under one returned at
    once with the clock unchanged, and the proxy spun until the segment was due
    (about 17 wake-ups a segment, and three times the CPU of the transfer: the
    links of a twelve-controller ring then took a core of the machine's two)."""
    waits = 0
    sleep = asyncio.sleep

    async def counted(delay: float) -> None:
        nonlocal waits
        waits += 1
        await sleep(delay)

    monkeypatch.setattr(asyncio, "sleep", counted)
    size = 2 << 20

    async def transfer() -> None:
        sink = Sink()
        await sink.start()
        sink.expect = size
        proxy = LinkProxy("127.0.0.1:0", sink.address, LinkSpec(latency=0.020, bandwidth=25e6), OFF)
        await proxy.start()
        _, writer = await connect(proxy.address)
        writer.write(os.urandom(size))
        await asyncio.wait_for(sink.done.wait(), 30)
        writer.close()
        await proxy.stop()
        await sink.stop()

    uvloop.run(transfer())
    segments = size // SEGMENT_BYTES
    assert waits <= 2 * segments, f"{waits} waits for {segments} segments"


async def test_a_connection_that_fails_in_the_emulator_is_reset_and_logged_not_left_to_asyncio(
    echo: Echo, make_proxy, monkeypatch: pytest.MonkeyPatch
) -> None:
    """CI (test_link_radio, under load): a connection cut as the vehicle left the range
    ended in an exception that escaped the handler, and asyncio printed "Unhandled
    exception in client_connected_cb" on stderr, not a JSON line. Whatever a connection
    fails with, the client is reset and the link logs it and goes on."""
    proxy = await make_proxy(echo.address)
    unhandled: list[dict] = []
    asyncio.get_running_loop().set_exception_handler(lambda _, context: unhandled.append(context))

    async def fails(*_: object) -> None:
        raise RuntimeError("unable to perform operation on a closed transport")

    monkeypatch.setattr(proxy, "_forward", fails)
    reader, writer = await connect(proxy.address)
    with pytest.raises((ConnectionError, asyncio.IncompleteReadError)):
        await asyncio.wait_for(reader.readexactly(1), 10)
    writer.close()
    await eventually(lambda: proxy.counters.active == 0, "the connection ended", 10)
    assert unhandled == [] and proxy.counters.failed == 1
    monkeypatch.undo()
    assert await asyncio.wait_for(ping_pong(proxy.address, 1), 10)  # it goes on

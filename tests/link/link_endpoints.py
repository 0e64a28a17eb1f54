"""Endpoints for link tests: a sink that timestamps what it receives, an echo server."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib


class Sink:
    """A TCP server that reads everything and notes when ``expect`` bytes have arrived."""

    def __init__(self) -> None:
        self.address = ""
        self.accepted = asyncio.Event()
        self.done = asyncio.Event()
        self.eof = asyncio.Event()
        self.expect = 0
        self.received = 0
        self.done_at = 0.0
        self.digest = hashlib.sha256()
        self.writers: list[asyncio.StreamWriter] = []
        self._server: asyncio.Server | None = None

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        self.address = f"127.0.0.1:{self._server.sockets[0].getsockname()[1]}"

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.writers.append(writer)
        self.accepted.set()
        loop = asyncio.get_running_loop()
        with contextlib.suppress(ConnectionError):
            while data := await reader.read(1 << 16):
                self.received += len(data)
                self.digest.update(data)
                if self.expect and self.received >= self.expect and not self.done.is_set():
                    self.done_at = loop.time()
                    self.done.set()
        self.eof.set()

    async def stop(self) -> None:
        assert self._server is not None
        self._server.close()
        for w in self.writers:
            w.close()
        await self._server.wait_closed()


class Echo:
    """A TCP server that sends back what it receives and closes after the client's end."""

    def __init__(self) -> None:
        self.address = ""
        self._server: asyncio.Server | None = None

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        self.address = f"127.0.0.1:{self._server.sockets[0].getsockname()[1]}"

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(ConnectionError):
            while data := await reader.read(1 << 16):
                writer.write(data)
                await writer.drain()
            writer.close()

    async def stop(self) -> None:
        assert self._server is not None
        self._server.close()
        await self._server.wait_closed()


def host_port(address: str) -> tuple[str, int]:
    host, _, port = address.rpartition(":")
    return host, int(port)


async def connect(address: str) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """Opens a TCP connection to ``host:port``."""
    return await asyncio.open_connection(*host_port(address))


async def send_and_time(address: str, sink: Sink, size: int) -> float:
    """Sends ``size`` bytes through ``address`` to ``sink``: seconds from first write to arrival."""
    loop = asyncio.get_running_loop()
    sink.expect, sink.received = size, 0
    sink.done.clear()
    sink.accepted.clear()
    _, writer = await connect(address)
    # The proxy connects onward before it reads; start the clock once the path is up.
    await asyncio.wait_for(sink.accepted.wait(), 10)
    payload = bytes(size)
    started = loop.time()
    writer.write(payload)
    await writer.drain()
    await asyncio.wait_for(sink.done.wait(), 120)
    elapsed = sink.done_at - started
    writer.close()
    return elapsed

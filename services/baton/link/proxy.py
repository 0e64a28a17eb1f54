"""The link emulator: a TCP proxy that delays and rate-limits each direction.

Every accepted connection is forwarded to one target. Each direction reads
chunks from its source while its in-flight amount is below a bound (so a
64 MB transfer holds a few MB at most, and the sender feels backpressure),
asks its ``SerialLine`` when each chunk arrives, and writes it to the sink
at that time. End of stream and resets travel the same way, behind the data
sent before them: a half-close stays a half-close, a reset becomes a reset.

With a radio range (``radio.py``) the link is up only while the vehicle is
within it: a connection accepted out of range is reset at once (refused), and
the vehicle leaving the range resets every open connection (cut). With a
fade (``radio.Fade``) every open connection's lines are retuned as the
vehicle's distance changes. ``reshape`` changes the link's own latency and
bandwidth while it runs (``baton link --shape-file``, on SIGHUP: a link that
gets slow, for the drone's round-trip measurement).
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import socket
import struct
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from baton.config import LinkSpec
from baton.link.radio import POSITION_PERIOD_S, Fade, RadioRange, read_position
from baton.link.shaper import SerialLine
from baton.logs import get_logger

# Bytes asked of the source per read.
READ_BYTES = 64 << 10
# uvloop's clock and timers count whole milliseconds: a sleep of less than one
# returns at once with the clock unchanged, and a segment due in 0.3 ms was
# waited for by spinning (17 wake-ups a segment, 3 times the CPU of the
# whole transfer). A segment is late by under a millisecond instead, never early.
CLOCK_RESOLUTION_S = 0.001


class _Signal(enum.Enum):
    EOF = "eof"  # the source half-closed: pass the half-close on
    RESET = "reset"  # the source failed: reset the sink and drop the connection


@dataclass
class LinkCounters:
    """What a link has carried since it started."""

    connections: int = 0  # accepted from clients
    active: int = 0  # open now
    failed: int = 0  # accepted, but the target refused or was unreachable
    bytes_up: int = 0  # client -> target, delivered
    bytes_down: int = 0  # target -> client, delivered
    peak_in_flight: int = 0  # most bytes one direction held at once (the buffering bound)
    refused: int = 0  # accepted while the vehicle was out of radio range, and reset
    cut: int = 0  # open when the vehicle left radio range, and reset

    def as_fields(self) -> dict[str, int]:
        """The counters as log fields."""
        return asdict(self)


def _split_address(address: str) -> tuple[str, int]:
    host, _, port = address.rpartition(":")
    return host.strip("[]"), int(port)


def reset_connection(writer: asyncio.StreamWriter) -> None:
    """Closes a connection with a TCP reset, so the peer sees a reset, not an end of stream."""
    sock = writer.get_extra_info("socket")
    if sock is not None and not writer.transport.is_closing():
        # OSError: the peer went first. ValueError: uvloop's socket of a transport
        # that closed meanwhile has no file descriptor left.
        with contextlib.suppress(OSError, ValueError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    writer.transport.abort()


class _Direction:
    """One direction of one connection: source -> serial line -> sink."""

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        spec: LinkSpec,
        on_delivered: Callable[[int], None],
        on_in_flight: Callable[[int], None],
    ) -> None:
        self.reader = reader
        self.writer = writer
        self.line = SerialLine(spec)
        self.upward = False  # client -> target (which spec a fade retunes it to)
        self.in_flight = 0
        self._on_delivered = on_delivered
        self._on_in_flight = on_in_flight
        self._pending: deque[tuple[float, bytes | _Signal]] = deque()
        self._arrived = asyncio.Event()
        self._room = asyncio.Event()
        self._room.set()

    def _enqueue(self, arrival: float, item: bytes | _Signal) -> None:
        self._pending.append((arrival, item))
        self._arrived.set()

    async def _receive(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            # Backpressure: stop reading while the line holds enough to stay busy.
            while self.in_flight >= self.line.max_in_flight:
                self._room.clear()
                await self._room.wait()
            try:
                data = await self.reader.read(READ_BYTES)
            except (ConnectionError, OSError):
                self._enqueue(self.line.close_time(loop.time()), _Signal.RESET)
                return
            now = loop.time()
            if not data:
                self._enqueue(self.line.close_time(now), _Signal.EOF)
                return
            self.in_flight += len(data)
            self._on_in_flight(self.in_flight)
            offset = 0
            for arrival, length in self.line.segments(now, len(data)):
                self._enqueue(arrival, data[offset : offset + length])
                offset += length

    async def _deliver(self) -> _Signal:
        """Writes each segment at its arrival time; returns how the stream ended."""
        loop = asyncio.get_running_loop()
        while True:
            while not self._pending:
                self._arrived.clear()
                await self._arrived.wait()
            arrival, item = self._pending[0]
            delay = arrival - loop.time()
            if delay > 0:
                await asyncio.sleep(max(delay, CLOCK_RESOLUTION_S))
                continue
            if isinstance(item, _Signal):
                self._pending.popleft()
                if item is _Signal.EOF and self.writer.can_write_eof():
                    self.writer.write_eof()
                return item
            # Everything due by now goes out in one write.
            now = loop.time()
            batch = []
            while self._pending and self._pending[0][0] <= now:
                head = self._pending[0][1]
                if isinstance(head, _Signal):
                    break
                batch.append(head)
                self._pending.popleft()
            size = sum(map(len, batch))
            self.writer.write(b"".join(batch))
            await self.writer.drain()
            self._on_delivered(size)
            self.in_flight -= size
            self._room.set()

    async def run(self) -> _Signal:
        """Forwards until the source ends; RESET also when the sink fails."""
        receiving = asyncio.create_task(self._receive())
        try:
            return await self._deliver()
        except (ConnectionError, OSError):
            return _Signal.RESET
        finally:
            receiving.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await receiving


class LinkProxy:
    """A TCP proxy from ``listen`` to ``target`` that emulates a link.

    ``up`` shapes client -> target, ``down`` target -> client. Use inside one
    event loop: ``await proxy.start()``, then connect to ``proxy.address``;
    ``await proxy.stop()`` closes the listener and every connection. With
    ``radio`` and ``position_file`` it carries connections only while the
    vehicle (its position file) is within the radio's range.
    """

    def __init__(
        self,
        listen: str,
        target: str,
        up: LinkSpec,
        down: LinkSpec,
        radio: RadioRange | None = None,
        position_file: Path | None = None,
        fade: Fade | None = None,
    ) -> None:
        if (radio is None) != (position_file is None):
            raise ValueError("a radio range needs the vehicle's position file, and vice versa")
        if fade is not None and radio is None:
            raise ValueError("a fade needs a radio range")
        self.listen = listen
        self.target = target
        self.up = up
        self.down = down
        self.radio = radio
        self.position_file = position_file
        # Whether the vehicle is within the radio's range (always, without one).
        self.in_range = True
        self.fade = fade
        # How deep into the fade the vehicle is (0: none, 1: on the circle), in
        # tenths as last logged, and the open connections' directions to retune.
        self.depth = 0.0
        self._logged_depth = 0
        self._directions: set[_Direction] = set()
        self._radio_watch: asyncio.Task[None] | None = None
        self.counters = LinkCounters()
        self.address = listen
        self.log = get_logger("link").bind(target=target)
        self._server: asyncio.Server | None = None
        self._connections: set[asyncio.Task[None]] = set()
        self._writers: set[asyncio.StreamWriter] = set()

    async def start(self) -> None:
        """Starts listening; ``address`` then holds the bound port."""
        if self.radio is not None:
            self._look_at_the_vehicle()
            self._radio_watch = asyncio.create_task(self._watch_the_vehicle())
        host, port = _split_address(self.listen)
        self._server = await asyncio.start_server(
            self._serve, host, port, limit=READ_BYTES, reuse_address=True
        )
        bound_port = self._server.sockets[0].getsockname()[1]
        self.address = f"{self.listen.rpartition(':')[0]}:{bound_port}"
        self.log = self.log.bind(listen=self.address)
        self.log.info(
            "link listening",
            up=self.up.model_dump(),
            down=self.down.model_dump(),
            radio_range_m=self.radio.range_m if self.radio is not None else None,
            fade=None if self.fade is None else vars(self.fade),
        )

    def _look_at_the_vehicle(self) -> bool:
        """Reads the vehicle's position; notes (and logs) it entering or leaving the
        range. Returns whether it just left."""
        assert self.radio is not None and self.position_file is not None
        where = read_position(self.position_file)
        covered = where is not None and self.radio.covers(*where)
        if self.fade is not None and where is not None:
            self._retune(self.fade.depth(self.radio.distance_m(*where), self.radio.range_m))
        if covered == self.in_range:
            return False
        self.in_range = covered
        distance = (
            f"{self.radio.distance_m(*where):.0f} m" if where is not None else "position unknown"
        )
        self.log.info(
            "vehicle in radio range" if covered else "vehicle out of radio range",
            distance=distance,
            range_m=self.radio.range_m,
            open_connections=self.counters.active,
        )
        return not covered

    def reshape(self, up: LinkSpec, down: LinkSpec) -> None:
        """The link's own latency and bandwidth from now on, per direction: every open
        line (faded as deep as the vehicle is, with a fade) and new ones follow."""
        self.up, self.down = up, down
        self._apply()
        self.log.info("link reshaped", up=up.model_dump(), down=down.model_dump())

    def _specs(self) -> tuple[LinkSpec, LinkSpec]:
        """The (up, down) specs now: the link's own, faded if there is a fade."""
        if self.fade is None:
            return self.up, self.down
        return self.fade.spec(self.up, self.depth), self.fade.spec(self.down, self.depth)

    def _apply(self) -> None:
        up, down = self._specs()
        for direction in self._directions:
            direction.line.retune(up if direction.upward else down)

    def _retune(self, depth: float) -> None:
        """The vehicle is ``depth`` into the fade: every open line and new ones follow."""
        assert self.fade is not None
        if depth == self.depth:
            return
        self.depth = depth
        up, down = self._specs()
        self._apply()
        tenths = int(depth * 10)
        if tenths != self._logged_depth:
            self._logged_depth = tenths
            self.log.info(
                "radio fade",
                depth=round(depth, 2),
                up=up.model_dump(),
                down=down.model_dump(),
            )

    async def _watch_the_vehicle(self) -> None:
        """Cuts every open connection when the vehicle leaves the range."""
        while True:
            await asyncio.sleep(POSITION_PERIOD_S)
            if self._look_at_the_vehicle():
                self.counters.cut += len(self._connections)
                for writer in list(self._writers):
                    reset_connection(writer)

    async def stop(self) -> None:
        """Closes the listener, resets open connections and logs the counters."""
        if self._radio_watch is not None:
            self._radio_watch.cancel()
            await asyncio.gather(self._radio_watch, return_exceptions=True)
        if self._server is not None:
            self._server.close()
        for writer in list(self._writers):
            reset_connection(writer)
        for task in list(self._connections):
            task.cancel()
        await asyncio.gather(*self._connections, return_exceptions=True)
        if self._server is not None:
            await self._server.wait_closed()
            self._server = None
        self.log.info("link stopped", **self.counters.as_fields())

    async def __aenter__(self) -> LinkProxy:
        await self.start()
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.stop()

    async def _serve(
        self, client_reader: asyncio.StreamReader, client: asyncio.StreamWriter
    ) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._connections.add(task)
        self._writers.add(client)
        self.counters.connections += 1
        self.counters.active += 1
        peer = client.get_extra_info("peername")
        try:
            if not self.in_range:
                self.counters.refused += 1
                self.log.debug("refused: the vehicle is out of radio range", peer=str(peer))
                reset_connection(client)
                return
            host, port = _split_address(self.target)
            try:
                target_reader, target = await asyncio.open_connection(host, port, limit=READ_BYTES)
            except OSError as exc:
                self.counters.failed += 1
                self.log.warning("target unreachable; resetting the client", error=str(exc))
                reset_connection(client)
                return
            self._writers.add(target)
            try:
                await self._forward(client_reader, client, target_reader, target)
            finally:
                self._writers.discard(target)
        except asyncio.CancelledError:
            # stop() ends connections this way; asyncio's server callback would
            # report a cancelled handler as an error, so it ends quietly here.
            reset_connection(client)
        except Exception as exc:  # one connection's end, never the link's
            # A write to a transport a radio cut aborted meanwhile, say (CI, under
            # load): asyncio would print it on stderr, outside the JSON log.
            self.counters.failed += 1
            self.log.warning("connection failed in the link; reset", error=repr(exc))
            reset_connection(client)
        finally:
            self._connections.discard(task)
            self._writers.discard(client)
            self.counters.active -= 1
            self.log.debug("connection closed", peer=str(peer))

    def _count_up(self, size: int) -> None:
        self.counters.bytes_up += size

    def _count_down(self, size: int) -> None:
        self.counters.bytes_down += size

    def _note_in_flight(self, size: int) -> None:
        self.counters.peak_in_flight = max(self.counters.peak_in_flight, size)

    async def _forward(
        self,
        client_reader: asyncio.StreamReader,
        client: asyncio.StreamWriter,
        target_reader: asyncio.StreamReader,
        target: asyncio.StreamWriter,
    ) -> None:
        up_spec, down_spec = self._specs()
        up = _Direction(client_reader, target, up_spec, self._count_up, self._note_in_flight)
        down = _Direction(target_reader, client, down_spec, self._count_down, self._note_in_flight)
        up.upward = True
        self._directions |= {up, down}
        tasks = {asyncio.create_task(up.run()), asyncio.create_task(down.run())}
        try:
            pending = tasks
            while pending:
                done, pending = await asyncio.wait(pending, return_when=asyncio.FIRST_COMPLETED)
                if any(t.result() is _Signal.RESET for t in done):
                    # A reset on either side (or a sink that went away) ends both directions.
                    reset_connection(client)
                    reset_connection(target)
                    break
            else:
                # Both sides half-closed and all data arrived: close normally.
                client.close()
                target.close()
        finally:
            self._directions -= {up, down}
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            for writer in (client, target):
                if not writer.transport.is_closing():
                    reset_connection(writer)

"""The live fleet view's web server: the page, its document, and server-sent events.

Plain HTTP/1.1 on asyncio's streams (no web framework: three read-only
routes), one process with the poller:

- ``GET /``: the page (``page.PAGE``), which loads nothing else but ``/events``;
- ``GET /state``: the newest document (``state.fleet_view``) as JSON;
- ``GET /events``: ``text/event-stream``, the newest document at once, then
  each new one as the poller reads it (only when something shown changed),
  and a comment every ``KEEPALIVE_S`` so that a proxy keeps the stream open.

The poller reads the network (``read``: blocking gRPC calls, so in a thread)
every ``poll_s`` seconds, one read at a time however many pages watch: a
hundred open pages cost the stations no more than one. Anything but GET of
those paths is answered 404 or 405 naming what there is.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import sys
from collections.abc import Callable
from functools import partial
from typing import Any

from baton.view.page import PAGE
from baton.view.state import changed

# A comment line on an idle event stream this often, seconds.
KEEPALIVE_S = 15.0
# A request's line and headers: more than this is refused.
MAX_HEAD_BYTES = 16_384
ROUTES = ("/", "/state", "/events")
# The page may run its own inline script and style, and talk to this server only.
CSP = (
    "default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; connect-src 'self'"
)


class FleetViewServer:
    """Serves the view of what ``read()`` returns, read every ``poll_s`` seconds."""

    def __init__(self, read: Callable[[], dict[str, Any]], poll_s: float) -> None:
        self.read = read
        self.poll_s = poll_s
        self.document: dict[str, Any] | None = None
        self._fresh = asyncio.Condition()
        self._server: asyncio.Server | None = None
        self._poller: asyncio.Task[None] | None = None
        self._handlers: set[asyncio.Task[Any]] = set()

    async def start(self, host: str, port: int) -> str:
        """Listens and starts polling; the bound HOST:PORT."""
        self._server = await asyncio.start_server(self._serve, host, port)
        self._poller = asyncio.create_task(self._poll())
        bound = self._server.sockets[0].getsockname()
        return f"{bound[0]}:{bound[1]}"

    async def stop(self) -> None:
        if self._poller is not None:
            self._poller.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._poller
        if self._server is not None:
            self._server.close()
            # Event streams never end by themselves: their handlers are cancelled.
            for handler in list(self._handlers):
                handler.cancel()
            await asyncio.gather(*self._handlers, return_exceptions=True)
            await self._server.wait_closed()

    async def _poll(self) -> None:
        while True:
            try:
                document = await asyncio.to_thread(self.read)
            except Exception as exc:
                # The view outlives a failed read (the registry being written, say): the
                # pages keep the last document, whose time says how old it is, and the
                # next read tries again.
                print(f"baton fleet view: reading the network: {exc!r}", file=sys.stderr)
                await asyncio.sleep(self.poll_s)
                continue
            if changed(self.document, document):
                async with self._fresh:
                    self.document = document
                    self._fresh.notify_all()
            await asyncio.sleep(self.poll_s)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        handler = asyncio.current_task()
        assert handler is not None
        self._handlers.add(handler)
        handler.add_done_callback(self._handlers.discard)
        try:
            method, path = await _request(reader)
            if path not in ROUTES:
                await _answer(writer, 404, f"no {path} here; there is {', '.join(ROUTES)}")
            elif method != "GET":
                await _answer(writer, 405, f"{method} {path}: only GET")
            elif path == "/":
                await _answer(writer, 200, PAGE, "text/html; charset=utf-8")
            elif path == "/state":
                body = json.dumps(await self._first())
                await _answer(writer, 200, body, "application/json")
            else:
                await self._events(writer)
        except (ConnectionError, asyncio.IncompleteReadError):
            pass  # the browser went away
        except ValueError as exc:
            with contextlib.suppress(ConnectionError):
                await _answer(writer, 400, str(exc))
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()

    async def _first(self) -> dict[str, Any]:
        async with self._fresh:
            await self._fresh.wait_for(lambda: self.document is not None)
            assert self.document is not None
            return self.document

    def _newer_than(self, sent: dict[str, Any]) -> bool:
        return self.document is not sent

    async def _events(self, writer: asyncio.StreamWriter) -> None:
        writer.write(_head(200, "text/event-stream", None) + b"Cache-Control: no-store\r\n\r\n")
        sent = await self._first()
        writer.write(_event(sent))
        await writer.drain()
        while True:
            async with self._fresh:
                try:
                    await asyncio.wait_for(
                        self._fresh.wait_for(partial(self._newer_than, sent)), KEEPALIVE_S
                    )
                except TimeoutError:
                    writer.write(b": still here\n\n")
                    await writer.drain()
                    continue
                assert self.document is not None
                sent = self.document
            writer.write(_event(sent))
            await writer.drain()


async def _request(reader: asyncio.StreamReader) -> tuple[str, str]:
    """The request's method and path (its query dropped); ValueError for a malformed one."""
    try:
        head = await reader.readuntil(b"\r\n\r\n")
    except asyncio.LimitOverrunError:
        raise ValueError(f"request head over {MAX_HEAD_BYTES} bytes") from None
    if len(head) > MAX_HEAD_BYTES:
        raise ValueError(f"request head over {MAX_HEAD_BYTES} bytes")
    parts = head.split(b"\r\n", 1)[0].decode("latin-1").split()
    if len(parts) != 3 or not parts[2].startswith("HTTP/"):
        raise ValueError(f"request line {' '.join(parts)!r}: expected METHOD PATH HTTP/1.1")
    return parts[0], parts[1].split("?", 1)[0]


def _head(status: int, content_type: str, length: int | None) -> bytes:
    reason = {200: "OK", 400: "Bad Request", 404: "Not Found", 405: "Method Not Allowed"}
    lines = [
        f"HTTP/1.1 {status} {reason[status]}",
        f"Content-Type: {content_type}",
        f"Content-Security-Policy: {CSP}",
        "Connection: close",
    ]
    if length is not None:
        lines.append(f"Content-Length: {length}")
    return ("\r\n".join(lines) + "\r\n").encode("ascii")


async def _answer(
    writer: asyncio.StreamWriter,
    status: int,
    body: str,
    content_type: str = "text/plain; charset=utf-8",
) -> None:
    data = body.encode("utf-8")
    writer.write(_head(status, content_type, len(data)) + b"\r\n" + data)
    await writer.drain()


def _event(document: dict[str, Any]) -> bytes:
    return f"data: {json.dumps(document, separators=(',', ':'))}\n\n".encode()


async def serve_view(
    read: Callable[[], dict[str, Any]],
    listen: str,
    poll_s: float,
    address_file: str | None = None,
) -> int:
    """Serves the view on ``listen`` (HOST:PORT, port 0 picks one) until SIGTERM or
    SIGINT; announces ``http://HOST:PORT/`` as the other parts announce their ports."""
    from baton.lifecycle import announce, run_until_signalled

    host, _, port = listen.rpartition(":")
    server = FleetViewServer(read, poll_s)

    async def main(stop: asyncio.Event) -> int:
        bound = await server.start(host, int(port))
        url = f"http://{bound}/"
        announce(address_file, [bound], {"view": url, "address": bound})
        await stop.wait()
        await server.stop()
        return 0

    return await run_until_signalled(main)

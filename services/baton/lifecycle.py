"""A part's life: its event loop, announcing that it listens, running until a signal,
not outliving its parent. Every baton program that serves (controller, drone, link,
sim vehicle) goes through ``run``, ``announce`` and ``run_until_signalled``; the
testbed starts them with ``testbed/supervisor.py``."""

from __future__ import annotations

import asyncio
import ctypes
import json
import os
import signal
import sys
import tempfile
import threading
from collections.abc import Awaitable, Callable, Coroutine, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")

# How long a service may take to stop cleanly after SIGTERM or SIGINT.
STOP_DEADLINE_S = 5.0

_PR_SET_PDEATHSIG = 1

# The event loop of every serving part: "uvloop" (the default) or "asyncio".
EVENT_LOOP_ENV = "BATON_EVENT_LOOP"
EVENT_LOOPS = ("uvloop", "asyncio")


def run(main: Coroutine[Any, Any, T]) -> T:
    """Runs a part's ``main`` to its end on its own event loop, as ``asyncio.run`` does.

    The loop is uvloop's: a drone call through a controller crosses two
    processes' loops twice, and uvloop's takes less of that round trip than
    asyncio's (docs/design.md, "The proxy path"). ``BATON_EVENT_LOOP=asyncio``
    selects the standard loop instead, to measure the difference.
    """
    name = os.environ.get(EVENT_LOOP_ENV, "uvloop")
    factory: Callable[[], asyncio.AbstractEventLoop]
    if name == "uvloop":
        # Imported here: this module ships in the SDK (die_with_parent), which
        # depends on grpcio and protobuf only; uvloop is the services'.
        import uvloop

        factory = uvloop.new_event_loop
    elif name == "asyncio":
        factory = asyncio.new_event_loop
    else:
        main.close()
        raise SystemExit(
            f"{EVENT_LOOP_ENV}={name!r} in the environment: say one of {', '.join(EVENT_LOOPS)}"
        )
    with asyncio.Runner(loop_factory=factory) as runner:
        return runner.run(main)


def die_with_parent(parent: int) -> None:
    """Asks Linux to send this process SIGTERM when its parent, ``parent``, dies.

    Called at start by every process baton starts itself (the testbed's
    parts, a controller's mission program: ``--die-with-parent PID``), so
    that a parent killed outright leaves nothing running. Not a
    ``preexec_fn``: forking a process that runs gRPC threads is unsafe. If
    the parent died before this process got here, it ends at once. A no-op
    where there is no prctl.
    """
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != parent:
        os.kill(os.getpid(), signal.SIGTERM)


def write_atomically(path: str | Path, text: str) -> None:
    """Writes ``text`` to ``path`` so that a reader sees all of it or nothing.

    The one way a part announces itself (its address or URL file, which the
    testbed and the tests wait for) and writes any file another process polls.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.")
    try:
        with os.fdopen(fd, "w") as out:
            out.write(text)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def announce(
    ready_file: str | Path | None, ready: Sequence[str], *events: Mapping[str, Any]
) -> None:
    """Says that a part listens: ``ready``, one a line, written atomically to
    ``ready_file`` if given (its ``--address-file`` or ``--url-file``: what the testbed's
    supervisor waits for), then one JSON line ``{"event": "listening", ...event}`` per
    event on stdout, flushed (what a person and the tests read: the file is there by
    the time the line is)."""
    if ready_file is not None:
        write_atomically(ready_file, "".join(f"{line}\n" for line in ready))
    for event in events:
        print(json.dumps({"event": "listening", **event}), flush=True)


async def until_stopped(
    stop: asyncio.Event, period: float | None = None, tick: Callable[[], None] | None = None
) -> None:
    """Waits for ``stop``, calling ``tick`` every ``period`` seconds meanwhile (a link's
    counters, a sim vehicle's position file)."""
    while not stop.is_set():
        try:
            await asyncio.wait_for(stop.wait(), period)
        except TimeoutError:
            if tick is not None:
                tick()


async def run_until_signalled(
    main: Callable[[asyncio.Event], Awaitable[int]],
) -> int:
    """Runs ``main(stop_event)``; SIGTERM and SIGINT set the event for a clean exit.

    The clean exit has ``STOP_DEADLINE_S``: a part that is still stopping then
    (a call that waits on a peer dying with it, on a loaded machine) says so
    on stderr and exits with code 1, so that a testbed killed outright leaves
    nothing running (``lifecycle.die_with_parent``). A thread's timer, not the
    loop's: a loop stuck is what it guards against.
    """
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    deadline = threading.Timer(STOP_DEADLINE_S, _stop_overran)
    deadline.daemon = True

    def stopping() -> None:
        stop.set()
        if not deadline.is_alive():
            deadline.start()

    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stopping)
    try:
        return await main(stop)
    finally:
        deadline.cancel()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.remove_signal_handler(sig)


def _stop_overran() -> None:
    print(
        f"{sys.argv[0]}: still stopping {STOP_DEADLINE_S:g} s after SIGTERM; exiting now",
        file=sys.stderr,
        flush=True,
    )
    os._exit(1)

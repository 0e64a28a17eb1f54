"""The handover script, and the Connect streams that tell masters of a switch.

Handover triggers: a handover script (the paper's experiments: ``reqnr mid``
lines, "hand over to controller mid right after serving request reqnr";
``reqnr mid prepared`` prepares the handover then, docs/design.md "Prepared
handover") and the ``Handover`` RPC. Both end in ``Sequencer.switch`` (``sequencer.py``),
which the drone service calls with its execution lock held, so a switch
always falls between two requests.

The old master learns of a switch from a ``HandoverNotice`` on its Connect
stream. If it does not hold the stream at that moment the notice waits, and
is delivered as the only event of its next Connect (a former master is
otherwise refused Connect); it also learns from the FAILED_PRECONDITION
metadata of its next Invoke.
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from baton.drone.sequencer import ScriptedHandover, Sequencer
from baton.v1 import drone_pb2


class HandoverScriptError(ValueError):
    """A handover script that cannot be used; the message names file and line."""


def parse_handover_script(
    text: str, source: str, controllers: Iterable[int]
) -> dict[int, ScriptedHandover]:
    """The script's handovers by reqnr. Blank lines and ``#`` comments are allowed."""
    known = sorted(controllers)
    script: dict[int, ScriptedHandover] = {}
    for number, raw in enumerate(text.splitlines(), start=1):
        content = raw.split("#", 1)[0].strip()
        if not content:
            continue
        where = f"{source}:{number}"
        parts = content.split()
        kind = parts[2] if len(parts) == 3 else "forced"
        if (
            len(parts) not in (2, 3)
            or not all(p.isdigit() for p in parts[:2])
            or kind not in ("forced", "prepared")
        ):
            raise HandoverScriptError(
                f"{where}: expected 'REQNR CONTROLLER_ID' (two non-negative integers) and "
                f"optionally 'prepared' or 'forced' (the default), got {raw.strip()!r}"
            )
        reqnr, mid = int(parts[0]), int(parts[1])
        if reqnr < 1:
            raise HandoverScriptError(f"{where}: request numbers start at 1, got {reqnr}")
        if mid not in known:
            raise HandoverScriptError(f"{where}: unknown controller id {mid}; known ids: {known}")
        if reqnr in script:
            raise HandoverScriptError(
                f"{where}: reqnr {reqnr} already has a handover (line {script[reqnr].line})"
            )
        script[reqnr] = ScriptedHandover(reqnr, mid, number, prepared=kind == "prepared")
    return script


def load_handover_script(
    path: str | Path, controllers: Iterable[int]
) -> dict[int, ScriptedHandover]:
    """Reads and validates a handover script file."""
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise HandoverScriptError(
            f"{path}: cannot read the handover script: {exc.strerror}"
        ) from None
    return parse_handover_script(text, str(path), controllers)


@dataclass
class MasterStream:
    """One open Connect stream; ``wake`` is set when there is something to send or it must end."""

    controller_id: int
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    superseded: bool = False


class MasterStreams:
    """The open Connect streams, by controller; the sequencer decides who may hold one."""

    def __init__(self, sequencer: Sequencer) -> None:
        self._sequencer = sequencer
        self._streams: dict[int, MasterStream] = {}

    @property
    def master_connected(self) -> bool:
        """Whether the current master holds its Connect stream."""
        return self._sequencer.master in self._streams

    @property
    def holders(self) -> set[int]:
        """Controllers holding a Connect stream now."""
        return set(self._streams)

    def connected(self, controller_id: int) -> bool:
        """Whether ``controller_id`` holds a Connect stream now."""
        return controller_id in self._streams

    def attach(self, controller_id: int, mastership_epoch: int = 0) -> MasterStream:
        """Opens a Connect stream for the master, or for an old master owed a notice
        (``Sequencer.admit_connect``: refused to one holding a log taken over)."""
        self._sequencer.admit_connect(controller_id, mastership_epoch)
        previous = self._streams.get(controller_id)
        if previous is not None:
            # The controller reconnected (its old stream is likely dead): the
            # newest stream is the one that gets the notice.
            previous.superseded = True
            previous.wake.set()
        stream = MasterStream(controller_id)
        self._streams[controller_id] = stream
        return stream

    def detach(self, stream: MasterStream) -> None:
        """Forgets a stream that ended."""
        if self._streams.get(stream.controller_id) is stream:
            del self._streams[stream.controller_id]

    def wake(self, controller_id: int, delay_s: float = 0.0) -> None:
        """Wakes ``controller_id``'s stream (a notice is owed), after ``delay_s`` if given."""
        stream = self._streams.get(controller_id)
        if stream is None:
            return
        if delay_s > 0:  # fault injection: the reply overtakes the notice
            asyncio.get_running_loop().call_later(delay_s, stream.wake.set)
        else:
            stream.wake.set()


@dataclass
class StandbyStream:
    """One open Standby stream: events to send, in order."""

    controller_id: int
    events: asyncio.Queue[drone_pb2.StandbyEvent] = field(default_factory=asyncio.Queue)


class StandbyStreams:
    """The open Standby streams: which controllers the drone can reach now.

    A controller counts as reachable while one of its streams is open; the
    newest stream of a controller is the one told of a takeover.
    """

    def __init__(self) -> None:
        self._streams: dict[int, list[StandbyStream]] = {}

    def attach(self, controller_id: int) -> StandbyStream:
        """Opens a stream for ``controller_id``."""
        stream = StandbyStream(controller_id)
        self._streams.setdefault(controller_id, []).append(stream)
        return stream

    def detach(self, stream: StandbyStream) -> None:
        """Forgets a stream that ended."""
        streams = self._streams.get(stream.controller_id, [])
        if stream in streams:
            streams.remove(stream)
        if not streams:
            self._streams.pop(stream.controller_id, None)

    @property
    def reachable(self) -> set[int]:
        """Controllers holding a stream now."""
        return set(self._streams)

    def tell(self, controller_id: int, event: drone_pb2.StandbyEvent) -> bool:
        """Queues ``event`` on the controller's newest stream; False if it holds none."""
        streams = self._streams.get(controller_id)
        if not streams:
            return False
        streams[-1].events.put_nowait(event)
        return True

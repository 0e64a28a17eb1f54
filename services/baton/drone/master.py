"""Which controller is the master, when it changes, and telling the old master.

Handover triggers: a handover script (the paper's experiments: ``reqnr mid``
lines, "hand over to controller mid right after serving request reqnr") and
the ``Handover`` RPC. Both end in ``MasterSelection.switch``, which the drone
service calls with its execution lock held, so a switch always falls between
two requests.

The old master learns of a switch from a ``HandoverNotice`` on its Connect
stream. If it does not hold the stream at that moment the notice waits, and
is delivered as the only event of its next Connect (a former master is
otherwise refused Connect); it also learns from the FAILED_PRECONDITION
metadata of its next Invoke.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import grpc

from baton.logs import get_logger
from baton.rpc.errors import StatusError
from baton.v1 import drone_pb2

log = get_logger("drone")


class HandoverScriptError(ValueError):
    """A handover script that cannot be used; the message names file and line."""


@dataclass(frozen=True)
class ScriptedHandover:
    """One line of the handover script: hand over to ``new_master`` after ``after_reqnr``."""

    after_reqnr: int
    new_master: int
    line: int


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
        if len(parts) != 2 or not all(p.isdigit() for p in parts):
            raise HandoverScriptError(
                f"{where}: expected 'REQNR CONTROLLER_ID' (two non-negative integers), "
                f"got {raw.strip()!r}"
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
        script[reqnr] = ScriptedHandover(reqnr, mid, number)
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


class MasterSelection:
    """The master, the handover records, and the notices owed to old masters."""

    def __init__(self, controllers: Iterable[int], initial_master: int) -> None:
        self.controllers = sorted(set(controllers))
        if not self.controllers:
            raise ValueError("the drone needs at least one controller id")
        if initial_master not in self.controllers:
            raise ValueError(
                f"initial master {initial_master} is not a controller id; use one of "
                f"{self.controllers}"
            )
        self.master = initial_master
        self.handovers: list[drone_pb2.HandoverRecord] = []
        self._pending: dict[int, drone_pb2.HandoverNotice] = {}
        self._streams: dict[int, MasterStream] = {}

    @property
    def master_connected(self) -> bool:
        """Whether the current master holds its Connect stream."""
        return self.master in self._streams

    def check_known(self, controller_id: int) -> None:
        """INVALID_ARGUMENT unless ``controller_id`` is a known controller."""
        if controller_id not in self.controllers:
            raise StatusError(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"unknown controller id {controller_id}; known ids: {self.controllers}",
            )

    def not_master_error(self, controller_id: int, last_reqnr: int, what: str) -> StatusError:
        """The FAILED_PRECONDITION a non-master gets, with the master in message and metadata."""
        return StatusError(
            grpc.StatusCode.FAILED_PRECONDITION,
            f"{what} refused: controller {controller_id} is not the master; the master is "
            f"controller {self.master} (last reqnr served {last_reqnr})",
            metadata=(("baton-master", str(self.master)), ("baton-after-reqnr", str(last_reqnr))),
        )

    def switch(
        self, new_master: int, after_reqnr: int, trigger: str, notice_delay_s: float = 0.0
    ) -> drone_pb2.HandoverRecord:
        """Makes ``new_master`` the master and owes the old master a notice.

        The caller holds the drone's execution lock, so no request is being
        served. Raises FAILED_PRECONDITION if ``new_master`` already is the
        master (a handover to oneself would create a record with no delay
        to measure and a notice that tells the master nothing).
        """
        self.check_known(new_master)
        old = self.master
        if new_master == old:
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"controller {new_master} already is the master (after reqnr {after_reqnr})",
            )
        record = drone_pb2.HandoverRecord(
            old_master=old,
            new_master=new_master,
            after_reqnr=after_reqnr,
            decided_at=time.time(),
            trigger=trigger,
        )
        self.handovers.append(record)
        self.master = new_master
        # A master that got the role back no longer needs the notice of losing it.
        self._pending.pop(new_master, None)
        self._pending[old] = drone_pb2.HandoverNotice(
            old_master=old, new_master=new_master, after_reqnr=after_reqnr
        )
        stream = self._streams.get(old)
        log.info(
            "handover",
            old_master=old,
            new_master=new_master,
            after_reqnr=after_reqnr,
            trigger=trigger,
            old_master_connected=stream is not None,
        )
        if stream is not None:
            if notice_delay_s > 0:  # fault injection: the reply overtakes the notice
                asyncio.get_running_loop().call_later(notice_delay_s, stream.wake.set)
            else:
                stream.wake.set()
        return record

    def note_request(self, controller_id: int, received_at: float) -> None:
        """Completes the last handover's record with the new master's first request."""
        if not self.handovers:
            return
        record = self.handovers[-1]
        if record.new_master == controller_id and record.first_request_at == 0:
            record.first_request_at = received_at
            record.delay_s = received_at - record.decided_at
            log.info(
                "first request of new master",
                master=controller_id,
                after_reqnr=record.after_reqnr,
                delay_s=round(record.delay_s, 6),
            )

    def attach(self, controller_id: int, last_reqnr: int) -> MasterStream:
        """Opens a Connect stream for the master, or for an old master owed a notice."""
        self.check_known(controller_id)
        if controller_id != self.master and controller_id not in self._pending:
            raise self.not_master_error(controller_id, last_reqnr, "Connect")
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

    def pending_notice(self, controller_id: int) -> drone_pb2.HandoverNotice | None:
        """The notice owed to ``controller_id``, if any."""
        return self._pending.get(controller_id)

    def delivered(self, controller_id: int, notice: drone_pb2.HandoverNotice) -> None:
        """The notice was written to the stream; it is no longer owed."""
        if self._pending.get(controller_id) is notice:
            del self._pending[controller_id]

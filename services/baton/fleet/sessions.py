"""An admitted mission's sessions on its ring's stations: started together, stopped
together (``baton fleet start`` and ``cancel``).

The operator's side of ``Station.StartMission`` and ``StopMission``
(baton/station/): every station of the ring is given the mission's
configuration (its ring's stations at their ports, its drone) and program. A
start that one station refuses is undone on the stations it started, so a
mission either starts on its whole ring or leaves nothing new on any. A
station that hosts the mission already keeps it (mission ids are the
registry's, never reused): starting again is how a restarted station takes
its sessions back, from their history files. A stop tolerates a station
that hosts nothing of it.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import cast

import grpc

from baton.config import BatonConfig
from baton.rpc.channels import sync_channel
from baton.rpc.tls import Identity, Tls
from baton.v1 import station_pb2, station_pb2_grpc

# A start loads the configuration and launches the program; a stop stops both.
CALL_TIMEOUT_S = 30.0


class SessionError(RuntimeError):
    """A station that did not start or stop a session: which, and what it said;
    ``code``: the status it answered (UNAVAILABLE: not reached); ``leftover``: the
    stations a start that failed could not undo, what each said."""

    def __init__(
        self,
        message: str,
        code: grpc.StatusCode = grpc.StatusCode.UNAVAILABLE,
        leftover: Sequence[str] = (),
    ) -> None:
        super().__init__(message)
        self.code = code
        self.leftover = tuple(leftover)


@contextmanager
def station_stub(
    config: BatonConfig, sid: int, tls: Tls | None
) -> Iterator[station_pb2_grpc.StationStub]:
    """The operator's Station stub to station ``sid`` at its address in ``config``."""
    with sync_channel(config.controller(sid).reach, tls, Identity.controller(sid)) as channel:
        yield station_pb2_grpc.StationStub(channel)


def status_code(exc: grpc.RpcError) -> grpc.StatusCode:
    return cast(grpc.Call, exc).code()  # a failed call's error is the call


def said(config: BatonConfig, sid: int, exc: grpc.RpcError) -> str:
    details = cast(grpc.Call, exc).details()
    return f"station {sid} ({config.controller(sid).reach}): {status_code(exc).name}: {details}"


def start_sessions(
    config: BatonConfig,
    mission_id: str,
    program: str,
    args: Sequence[str],
    tls: Tls | None,
    stations: Sequence[int] | None = None,
) -> None:
    """Starts the mission's session on every station of ``stations`` (default: the
    whole ring, in ring order) that does not host it yet; SessionError naming the
    station that refused, after those this call started stopped it."""
    request = station_pb2.StartMissionRequest(
        mission_id=mission_id,
        config=json.dumps(config.model_dump(mode="json", exclude_unset=True)),
        program=program,
        args=list(args),
    )
    started: list[int] = []
    for sid in config.ring_order if stations is None else stations:
        try:
            with station_stub(config, sid, tls) as stub:
                stub.StartMission(request, timeout=CALL_TIMEOUT_S)
        except grpc.RpcError as exc:
            if status_code(exc) == grpc.StatusCode.ALREADY_EXISTS:
                continue
            problems = stop_sessions(config, mission_id, tls, started)
            undone = (f"; stopped on {', '.join(map(str, started))}" if started else "") + "".join(
                f"; {p}" for p in problems
            )
            raise SessionError(
                f"not started: {said(config, sid, exc)}{undone}", status_code(exc), problems
            ) from None
        started.append(sid)


def stop_sessions(
    config: BatonConfig, mission_id: str, tls: Tls | None, stations: Sequence[int] | None = None
) -> list[str]:
    """Stops the mission's session on ``stations`` (default: the whole ring); what a
    station that could not be reached or refused said, one line each (a station that
    hosts nothing of the mission counts as stopped)."""
    problems = []
    request = station_pb2.StopMissionRequest(mission_id=mission_id)
    for sid in config.ring_order if stations is None else stations:
        try:
            with station_stub(config, sid, tls) as stub:
                stub.StopMission(request, timeout=CALL_TIMEOUT_S)
        except grpc.RpcError as exc:
            if status_code(exc) != grpc.StatusCode.NOT_FOUND:
                problems.append(said(config, sid, exc))
    return problems

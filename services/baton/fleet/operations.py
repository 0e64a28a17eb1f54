"""The operator's view of missions in flight and the drain of a station (``baton
fleet missions --config``, ``status``, ``drain``): the I/O around the rule in
``draining.py``.

Every question goes to a station (``Station.GetStation``, ``ControllerRing.
GetStatus`` naming the mission) or to a drone (``Drone.GetStatus``) with a
deadline of ``ASK_TIMEOUT_S``, all of a mission's at once: a station or a
drone that does not answer is shown as such, never waited on longer.

A drain, in order (as ``kubectl drain``: cordon, then move what can move):

1. The registry marks the station drained: admission puts it in no new ring.
2. For each mission in flight whose ring holds it, the stations of the ring
   and the drone are asked where the drone is and who is master, and
   ``draining.drain_mission`` decides whether the ring can do without it.
3. Where it can: a master on the station is handed over (the drone's
   Handover, prepared: the drone forces it when the master cannot prepare),
   and the drain waits until the new master's session is ACTIVE in the
   handover's epoch, so that the station's log reached it; then its session
   is stopped (the other stations route around it as around a dead
   controller) and the registry records that the station left that ring.
4. Where it cannot, or a step failed, nothing more is done to that mission and
   the report says why; running the drain again later picks up from there.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TypeVar

import grpc

from baton.config import BatonConfig
from baton.drone.policy import Station
from baton.fleet.draining import MissionView, Stay, drain_mission
from baton.fleet.registry import IN_FLIGHT, MissionRow, Registry, RegistryError
from baton.fleet.sessions import said, station_stub, status_code
from baton.rpc.channels import sync_channel
from baton.rpc.mission import mission_metadata
from baton.rpc.tls import DRONE, Identity, Tls
from baton.sdk.types import Position
from baton.v1 import drone_pb2, drone_pb2_grpc, ring_pb2, ring_pb2_grpc, station_pb2

# A status question's deadline: a station or drone slower than this shows as silent.
ASK_TIMEOUT_S = 3.0
# How long a drain waits for the handed-over master's session to be ACTIVE, beyond
# the drone's prepare timeout.
HANDOVER_SETTLE_S = 30.0
POLL_S = 0.2
# How many times a drain reads a mission's master and moves it away before it gives up.
MASTER_LOOKS = 3

T = TypeVar("T")


def _details(exc: grpc.RpcError) -> str:
    return (exc.details() or "") if isinstance(exc, grpc.Call) else str(exc)


def _asked(call: Callable[[], T], where: str) -> T | str:
    """``call()``'s answer, or what went wrong, one line naming ``where``."""
    try:
        return call()
    except grpc.RpcError as exc:
        return f"{where}: no answer: {status_code(exc).name}: {_details(exc)}"


K = TypeVar("K")


def at_once(ask: Callable[[K], T], keys: Sequence[K]) -> dict[K, T]:
    """``ask`` of every key, all at once (each call has its own deadline)."""
    if not keys:
        return {}
    with ThreadPoolExecutor(max_workers=len(keys)) as pool:
        return dict(zip(keys, pool.map(ask, keys), strict=True))


def ask_stations(
    config: BatonConfig, sids: Sequence[int], tls: Tls | None
) -> dict[int, station_pb2.StationStatus | str]:
    """Each station's GetStation, at once; a line saying why for one that did not answer."""

    def ask(sid: int) -> station_pb2.StationStatus | str:
        try:
            reach = config.controller(sid).reach
        except KeyError:
            return f"station {sid}: not in the network file; add it with its address"

        def call() -> station_pb2.StationStatus:
            with station_stub(config, sid, tls) as stub:
                reply: station_pb2.StationStatus = stub.GetStation(
                    station_pb2.GetStationRequest(), timeout=ASK_TIMEOUT_S
                )
                return reply

        return _asked(call, f"station {sid} ({reach})")

    return at_once(ask, sids)


def drone_of(mission: MissionRow, tls: Tls | None) -> Identity:
    """The identity a mission's drone presents: its own, ``spiffe://baton/drone/NAME``
    for the registry's drone NAME, where the operator's certificate folder holds
    ``drone-NAME.crt`` (the fleet testbed gives each drone its own), else the one
    drone's of a mission, ``spiffe://baton/drone``."""
    if tls is None or tls.folder is None:
        return DRONE
    try:
        own = Identity.drone(mission.drone)
    except ValueError:
        return DRONE
    return own if (tls.folder / f"{own.name}.crt").exists() else DRONE


def ask_drone(mission: MissionRow, tls: Tls | None) -> drone_pb2.DroneStatus | str:
    """The mission's drone's GetStatus, or why there is none."""
    address = mission.drone_address
    if not address:
        return "drone: its address is not known (baton fleet start records it)"
    drone = drone_of(mission, tls)

    def call() -> drone_pb2.DroneStatus:
        with sync_channel(address, tls, drone) as channel:
            reply: drone_pb2.DroneStatus = drone_pb2_grpc.DroneStub(channel).GetStatus(
                drone_pb2.GetDroneStatusRequest(), timeout=ASK_TIMEOUT_S
            )
            return reply

    return _asked(call, f"drone ({address})")


def session_statuses(
    mission: MissionRow, replies: dict[int, station_pb2.StationStatus | str]
) -> dict[int, ring_pb2.ControllerStatus | str]:
    """Each station of the mission's live ring: its session's ControllerStatus, or why
    there is none (no answer, no session, failed)."""
    found: dict[int, ring_pb2.ControllerStatus | str] = {}
    for sid in mission.live_ring:
        reply = replies.get(sid, f"station {sid}: not asked")
        if isinstance(reply, str):
            found[sid] = reply
            continue
        hosted = {m.mission_id: m for m in reply.missions}.get(str(mission.id))
        if hosted is None:
            found[sid] = f"station {sid}: hosts no session of mission {mission.id}"
        elif hosted.state != station_pb2.SESSION_STATE_HOSTING:
            found[sid] = f"station {sid}: session failed: {hosted.error}"
        else:
            found[sid] = hosted.status
    return found


@dataclass(frozen=True)
class Overview:
    """One mission in flight as its stations say: master, state, progress."""

    master: int | None
    state: str
    reqnr: int
    silent: tuple[str, ...] = field(default_factory=tuple)


def overview(sessions: dict[int, ring_pb2.ControllerStatus | str]) -> Overview:
    """Who is master (the session that says so in the newest epoch), the program's
    state (the master's, else the furthest session's), and the furthest request."""
    answered = [s for s in sessions.values() if not isinstance(s, str)]
    silent = tuple(s for s in sessions.values() if isinstance(s, str))
    masters = sorted((s for s in answered if s.master), key=lambda s: s.epoch)
    furthest = max(answered, key=lambda s: s.reqnr, default=None)
    lead = masters[-1] if masters else furthest
    state = (
        ring_pb2.MissionState.Name(lead.mission).removeprefix("MISSION_STATE_").lower()
        if lead is not None
        else "unknown"
    )
    return Overview(
        masters[-1].id if masters else None,
        state,
        furthest.reqnr if furthest is not None else 0,
        silent,
    )


def controller_status(
    config: BatonConfig, sid: int, mission_id: int, tls: Tls | None
) -> ring_pb2.ControllerStatus | str:
    """A mission's session status on station ``sid`` (ControllerRing.GetStatus with the
    mission's metadata, as grpcurl asks it), or why there is none."""

    def call() -> ring_pb2.ControllerStatus:
        address = config.controller(sid).reach
        with sync_channel(address, tls, Identity.controller(sid)) as channel:
            reply: ring_pb2.ControllerStatus = ring_pb2_grpc.ControllerRingStub(channel).GetStatus(
                ring_pb2.GetControllerStatusRequest(),
                metadata=mission_metadata(str(mission_id)),
                timeout=ASK_TIMEOUT_S,
            )
            return reply

    return _asked(call, f"station {sid}")


@dataclass
class DrainReport:
    """What a drain did: the missions the station left (and where masters went), the
    ones it stays in and why, and the steps that failed."""

    station: int
    left: list[tuple[int, int | None]] = field(default_factory=list)
    stayed: list[Stay] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)

    @property
    def done(self) -> bool:
        return not self.stayed and not self.failed


def drain(registry: Registry, station: str, config: BatonConfig, tls: Tls | None) -> DrainReport:
    """Drains ``station`` (a name or an id) out of every ring that can do without it
    (the module docstring's steps); RegistryError for an unknown station."""
    named = registry.set_drained(station, True)
    sid = named.station.id
    if sid not in {c.id for c in config.controllers}:
        raise RegistryError(
            f"station {named.name} (id {sid}): not in the network file's controllers; add "
            "it with its address"
        )
    places = {s.station.id: s.station for s in registry.stations()}
    drained = frozenset(s.station.id for s in registry.stations() if s.drained) - {sid}
    report = DrainReport(sid)
    for mission in registry.missions():
        if mission.state != IN_FLIGHT or sid not in mission.live_ring:
            continue
        try:
            _drain_mission(registry, config, tls, sid, mission, places, drained, report)
        except grpc.RpcError as exc:
            report.failed.append(f"mission {mission.id}: {said(config, sid, exc)}")
    return report


def mission_view(
    mission: MissionRow,
    places: dict[int, Station],
    sessions: dict[int, ring_pb2.ControllerStatus | str],
    drone: drone_pb2.DroneStatus | str,
    drained: frozenset[int] = frozenset(),
) -> MissionView:
    """The drain rule's view of a mission: its ring without the stations that did not
    answer (they count as not there), the drone's word on where it is and who is
    master (else the sessions')."""
    answering = tuple(sid for sid in mission.live_ring if not isinstance(sessions[sid], str))
    if isinstance(drone, str):
        master, at = overview(sessions).master, None
    else:
        master = drone.master
        p = drone.position
        known = p.latitude_deg != 0 or p.longitude_deg != 0
        at = Position(p.latitude_deg, p.longitude_deg) if known else None
    return MissionView(mission.id, answering, mission.route, places, master, at, drained)


def _drain_mission(
    registry: Registry,
    config: BatonConfig,
    tls: Tls | None,
    sid: int,
    mission: MissionRow,
    places: dict[int, Station],
    drained: frozenset[int],
    report: DrainReport,
) -> None:
    moved_to = None
    # The drone's policy may move the master onto the station while the drain looks:
    # the master is read again after a handover, and moved again if it is back.
    for _ in range(MASTER_LOOKS):
        sessions = session_statuses(mission, ask_stations(config, mission.live_ring, tls))
        drone = ask_drone(mission, tls)
        if isinstance(sessions[sid], str):
            report.failed.append(f"mission {mission.id}: {sessions[sid]}")
            return
        view = mission_view(mission, places, sessions, drone, drained)
        decision = drain_mission(sid, view)
        if isinstance(decision, Stay):
            report.stayed.append(decision)
            return
        target = decision.hand_over_to
        if target is None:
            break
        if isinstance(drone, str):
            report.failed.append(
                f"mission {mission.id}: its master is on station {sid} and {drone}; the "
                "master cannot be moved"
            )
            return
        problem = _hand_over(config, tls, mission, sid, target)
        if problem:
            report.failed.append(f"mission {mission.id}: {problem}")
            return
        moved_to = target
    else:
        report.failed.append(
            f"mission {mission.id}: its master came back to station {sid} after "
            f"{MASTER_LOOKS} handovers away; its drone's policy keeps choosing it"
        )
        return
    with station_stub(config, sid, tls) as stub:
        stub.StopMission(
            station_pb2.StopMissionRequest(mission_id=str(mission.id)),
            timeout=ASK_TIMEOUT_S * 10,
        )
    registry.depart(mission.id, sid)
    report.left.append((mission.id, moved_to))


def _hand_over(
    config: BatonConfig, tls: Tls | None, mission: MissionRow, sid: int, target: int
) -> str:
    """Moves the mission's master from ``sid`` to ``target`` and waits until the target's
    session is ACTIVE in the new epoch; what went wrong, or empty."""
    assert mission.drone_address is not None
    bound = config.prepare_timeout + HANDOVER_SETTLE_S
    with sync_channel(mission.drone_address, tls, drone_of(mission, tls)) as channel:
        stub = drone_pb2_grpc.DroneStub(channel)
        try:
            reply = stub.Handover(
                drone_pb2.HandoverRequest(new_master=target, prepared=True), timeout=bound
            )
            epoch = reply.epoch
        except grpc.RpcError as exc:
            now = stub.GetStatus(drone_pb2.GetDroneStatusRequest(), timeout=ASK_TIMEOUT_S)
            if now.master == sid:
                return f"the drone refused the handover to station {target}: {_details(exc)}"
            # The master moved away already (the drone's policy or a takeover).
            target, epoch = now.master, now.epoch
    deadline = time.monotonic() + bound
    while time.monotonic() < deadline:
        status = controller_status(config, target, mission.id, tls)
        if (
            not isinstance(status, str)
            and status.state == ring_pb2.CONTROLLER_STATE_ACTIVE
            and status.epoch >= epoch
        ):
            return ""
        time.sleep(POLL_S)
    return (
        f"the master moved to station {target} (epoch {epoch}), whose session was not "
        f"ACTIVE within {bound:.0f} s; station {sid} keeps its session"
    )

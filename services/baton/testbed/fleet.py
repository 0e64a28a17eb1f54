"""``baton testbed --fleet FILE``: several drones, each with its sim vehicle, drone
service and survey, over stations (``baton station``), on one machine.

Every part is a real process under one ``Supervisor``. The missions are admitted
first, all of them, over the file's stations by the registry (``fleet/``, a
SQLite file in the workdir): a route no station covers refuses the fleet before
anything starts. Then the stations, each drone's vehicle and drone service, and
each mission's sessions on its ring's stations (``fleet/sessions.py``, the
operator's ``baton fleet start``). The drones pick their masters from where
they are (the file's ``handover_policy``, ``nearest`` by default). A mission's
result is what the vehicle and the camera counted (exactly once) and whether
its ring's replicas saw the same replies.

The steps that work over addresses (``admit_fleet``, ``fleet_network``,
``mission_config``, ``fly_fleet``: every vehicle ready, the sessions started,
every mission's end, the judging) are apart from those that start processes
(``start_stations``, ``start_mission_drone``): ``run_fleet`` does both, and
``fleet_external.run_external_fleet`` flies the same steps on parts that run
elsewhere (the compose fleet).
"""

from __future__ import annotations

import asyncio
import datetime
import json
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Literal

import grpc
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from baton.certs.make import issue
from baton.config import (
    BatonConfig,
    ConfigError,
    Duration,
    Location,
    PolicySetting,
    format_validation_error,
    read_yaml,
)
from baton.effects import read_effects
from baton.rpc.channels import aio_channel
from baton.rpc.mission import mission_metadata
from baton.rpc.tls import DRONE_NAME_PATTERN, OPERATOR, Identity, Tls
from baton.testbed.fleet_report import FLEET_REPORT_FORMAT, Flight
from baton.testbed.flight_map import Track
from baton.testbed.local import MissionPlan, Snapshot, free_port
from baton.testbed.report import build_report, check_side_effects
from baton.testbed.supervisor import Supervisor, baton_argv
from baton.v1 import drone_pb2, drone_pb2_grpc, ring_pb2, ring_pb2_grpc, station_pb2_grpc

# In each drone's folder of the workdir: what its vehicle and camera counted, and the
# configuration its drone service flies with.
VEHICLE_EFFECTS, CAMERA_EFFECTS = "vehicle-effects.jsonl", "camera-effects.jsonl"
DRONE_CONFIG = "drone.json"
# In the workdir: the registry and the network's file (the stations' addresses), as an
# operator's; ``baton fleet view`` watches the running fleet with them.
REGISTRY_FILE, NETWORK_FILE = "fleet.sqlite", "network.yaml"
# How often each drone's position is noted for the fleet's map, seconds.
TRACK_PERIOD_S = 0.5
# How long every vehicle has to be ready to arm once the fleet flies, seconds.
READY_S = 120.0


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class FleetStation(_Model):
    """A station: its id (its controller id in every ring), antenna and range."""

    id: int = Field(ge=0, le=2**31 - 1, strict=True)
    location: Location
    range_m: float = Field(gt=0)


class FleetSurvey(_Model):
    """The survey a drone flies from its home (``MissionPlan``'s fields)."""

    kind: Literal["grid", "corridor"] = "corridor"
    grid: int = Field(default=2, ge=1)
    length_m: float = Field(default=1000.0, gt=0)
    # A corridor's direction from home, degrees clockwise from north (90: east).
    bearing_deg: float = Field(default=90.0, ge=0, lt=360)
    spacing_m: float = Field(default=100.0, gt=0)
    altitude_m: float = Field(default=10.0, gt=0)
    speed_m_s: float = Field(default=5.0, gt=0)
    poll_s: float = Field(default=1.0, gt=0)

    def plan(self) -> MissionPlan:
        return MissionPlan(**self.model_dump())


class FleetDrone(_Model):
    """One drone of the fleet: its name, where it takes off and what it flies."""

    # Also its name in its certificate (spiffe://baton/drone/NAME): one DNS label.
    name: str = Field(pattern=f"^{DRONE_NAME_PATTERN}$")
    home: Location
    mission: FleetSurvey = FleetSurvey()


class FleetFile(_Model):
    """``--fleet FILE``: the stations, the drones, and what all the missions share."""

    stations: list[FleetStation] = Field(min_length=1)
    drones: list[FleetDrone] = Field(min_length=1)
    speedup: float = Field(default=10.0, gt=0)
    handover_policy: PolicySetting = "nearest"  # type: ignore[assignment]
    takeover_after: float = Field(default=3.0, ge=0)
    # Each station's certificate lives this long and is renewed halfway through from
    # the testbed's certificate issuer (docs/security.md, "Short-lived certificates").
    station_cert_lifetime: Duration = Field(default=3600.0, ge=10.0)

    @model_validator(mode="after")
    def _unique(self) -> FleetFile:
        ids = [str(s.id) for s in self.stations]
        names = [d.name for d in self.drones]
        for what, values in (("stations[].id", ids), ("drones[].name", names)):
            twice = sorted({v for v in values if values.count(v) > 1})
            if twice:
                raise ValueError(f"{what}: {', '.join(twice)} twice; give each its own")
        return self


def load_fleet(path: Path) -> FleetFile:
    """Reads and validates a fleet file; ConfigError names the file, field and fix."""
    data = read_yaml(path, "fleet file")
    try:
        return FleetFile.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(str(path), exc)) from None


@dataclass
class StationPart:
    """A running station: its id, its port, its state folder, and an operator's stub."""

    id: int
    address: str
    state_dir: Path
    channel: grpc.aio.Channel
    stub: station_pb2_grpc.StationAsyncStub

    async def status(self, mission_id: str) -> ring_pb2.ControllerStatus:
        """A hosted mission's ControllerStatus, asked on the station's port as any part
        asks it: ControllerRing.GetStatus naming the mission."""
        ring: ring_pb2_grpc.ControllerRingAsyncStub = ring_pb2_grpc.ControllerRingStub(self.channel)
        return await ring.GetStatus(
            ring_pb2.GetControllerStatusRequest(), metadata=mission_metadata(mission_id), timeout=5
        )


async def start_stations(
    supervisor: Supervisor,
    ids: Sequence[int],
    certs: Path | None,
    *,
    cert_lifetime_s: float | None = None,
) -> dict[int, StationPart]:
    """``baton station`` processes with ids ``ids``, each on a free port (the same
    again if the supervisor restarts it), and an operator's channel to each (``certs``
    None: insecure). With ``cert_lifetime_s``, a certificate issuer (``baton certs
    issuer``) starts beside them and each station holds a certificate of that lifetime,
    renewed from it halfway through (``--renew-from``)."""
    workdir = supervisor.workdir
    tls_flags = [f"--certs={certs}"] if certs is not None else ["--insecure"]
    parts = []
    if certs is not None and cert_lifetime_s is not None:
        issuer = f"127.0.0.1:{free_port()}"
        lifetime = datetime.timedelta(seconds=cert_lifetime_s)
        for sid in ids:
            issue(certs, Identity.controller(sid), valid_for=lifetime)
        tls_flags.append(f"--renew-from={issuer}")
        argv = baton_argv(
            "certs",
            "issuer",
            str(certs),
            f"--listen={issuer}",
            f"--lifetime={cert_lifetime_s}s",
            f"--address-file={workdir / 'issuer.address'}",
        )
        parts.append(("issuer", argv, workdir / "issuer.address"))
    parts += [
        (
            f"station-{sid}",
            baton_argv(
                "station",
                f"--id={sid}",
                f"--address=127.0.0.1:{free_port()}",
                f"--address-file={workdir / f'station-{sid}.address'}",
                f"--state-dir={workdir / f'station-{sid}'}",
                *tls_flags,
            ),
            workdir / f"station-{sid}.address",
        )
        for sid in ids
    ]
    addresses = (await supervisor.start_ready_together(parts))[len(parts) - len(ids) :]
    operator = Tls.load(certs, OPERATOR) if certs is not None else None
    return {
        sid: connect_station(sid, text.splitlines()[0], workdir / f"station-{sid}", operator)
        for sid, text in zip(ids, addresses, strict=True)
    }


def connect_station(sid: int, address: str, state_dir: Path, operator: Tls | None) -> StationPart:
    """An operator's channel to station ``sid`` at ``address`` (``operator`` None:
    insecure), whoever started it."""
    channel = aio_channel(address, operator, Identity.controller(sid))
    return StationPart(sid, address, state_dir, channel, station_pb2_grpc.StationStub(channel))


@dataclass
class MissionDrone:
    """A mission's sim vehicle and drone service, and where they count side effects."""

    name: str
    address: str
    workdir: Path
    channel: grpc.aio.Channel
    stub: drone_pb2_grpc.DroneAsyncStub

    async def status(self, audit: bool = False) -> drone_pb2.DroneStatus:
        return await self.stub.GetStatus(
            drone_pb2.GetDroneStatusRequest(include_audit=audit), timeout=5
        )

    async def ready(self) -> bool:
        """Whether its vehicle is connected and ready to arm; False too while the drone
        service does not answer yet (one started elsewhere may still be starting)."""
        try:
            status = await self.status()
        except grpc.aio.AioRpcError as exc:
            if exc.code() == grpc.StatusCode.UNAVAILABLE:
                return False
            raise
        return status.vehicle_connected and status.flight_state.ready

    async def served(self, reqnr: int) -> bool:
        """Whether it has served request ``reqnr``."""
        return (await self.status()).last_reqnr >= reqnr

    async def snapshot(self, controllers: dict[int, ring_pb2.ControllerStatus]) -> Snapshot:
        """The drone's status with its audit, its ring's statuses and the effects counted."""
        return Snapshot(
            await self.status(audit=True),
            controllers,
            read_effects(self.workdir / VEHICLE_EFFECTS),
            read_effects(self.workdir / CAMERA_EFFECTS),
        )


async def start_mission_drone(
    supervisor: Supervisor,
    name: str,
    config: BatonConfig,
    handovers: Sequence[tuple[int, int]] = (),
    ready_s: float = 30.0,
) -> MissionDrone:
    """A sim vehicle at ``config``'s drone home and a drone service for the mission
    ``config`` describes (its ring, its policy), with the scripted ``handovers``; each
    given ``ready_s`` to announce itself."""
    workdir = supervisor.workdir / name
    workdir.mkdir()
    home = config.drone.home
    url = await supervisor.start_ready(
        f"{name}-vehicle",
        baton_argv(
            "sim-vehicle",
            f"--speedup={config.speedup}",
            f"--url-file={workdir / 'vehicle.url'}",
            f"--home={home.latitude_deg},{home.longitude_deg},{home.altitude_m}",
            f"--effects-file={workdir / VEHICLE_EFFECTS}",
        ),
        workdir / "vehicle.url",
        ready_s,
    )
    config_file = write_drone_config(workdir, config)
    script = workdir / "handovers.txt"
    script.write_text("".join(f"{after} {to}\n" for after, to in handovers))
    address = await supervisor.start_ready(
        f"{name}-drone",
        baton_argv(
            "drone",
            f"--config={config_file}",
            "--address=127.0.0.1:0",
            f"--address-file={workdir / 'drone.address'}",
            f"--vehicle-url={url.splitlines()[0]}",
            f"--handover-file={script}",
            f"--state={workdir / 'drone-state.sqlite'}",
            f"--camera-effects-file={workdir / CAMERA_EFFECTS}",
        ),
        workdir / "drone.address",
        ready_s,
    )
    return connect_drone(name, address.splitlines()[0], workdir, config)


def write_drone_config(workdir: Path, config: BatonConfig) -> Path:
    """The mission's configuration as its drone service reads it (``--config``), in
    the drone's folder ``workdir``."""
    from baton.lifecycle import write_atomically

    path = workdir / DRONE_CONFIG
    write_atomically(path, json.dumps(config.model_dump(mode="json", exclude_unset=True)))
    return path


def connect_drone(name: str, address: str, workdir: Path, config: BatonConfig) -> MissionDrone:
    """An operator's channel to the drone service of ``config`` at ``address``, whose
    vehicle and camera count their effects in ``workdir``, whoever started them."""
    tls = None if config.tls.insecure else Tls.load(config.tls.certs, OPERATOR)
    channel = aio_channel(address, tls, config.drone_identity)
    return MissionDrone(name, address, workdir, channel, drone_pb2_grpc.DroneStub(channel))


@dataclass
class MissionResult:
    """One mission of the fleet at its end."""

    drone: str
    mission_id: str
    ring: tuple[int, ...]
    effects: dict[str, Any]
    replicas_consistent: bool
    masters: list[int] = field(default_factory=list)
    failed: str = ""

    @property
    def ok(self) -> bool:
        return (
            not self.failed
            and self.effects.get("exactly_once") is True
            and (self.replicas_consistent)
        )


def mission_result(
    drone: str, mission_id: str, ring: Sequence[int], plan: MissionPlan, snapshot: Snapshot
) -> MissionResult:
    """What a mission's vehicle, camera and replicas say at its end."""
    effects = check_side_effects(snapshot, plan.grid, plan.spacing_m, plan.targets())
    statuses = snapshot.controllers.values()
    consistent = len({(s.reply_chain, s.reqnr) for s in statuses}) == 1
    failed = "; ".join(
        f"station {s.id}: {s.mission_error}"
        for s in statuses
        if s.mission == ring_pb2.MISSION_STATE_FAILED
    )
    masters = [h.new_master for h in snapshot.drone.handovers]
    return MissionResult(drone, mission_id, tuple(ring), effects, consistent, masters, failed)


async def mission_ended(
    stations: Mapping[int, StationPart], drone: MissionDrone, mission_id: str, ring: Sequence[int]
) -> dict[int, ring_pb2.ControllerStatus] | None:
    """Its ring's statuses once every station's program ended and no prepared handover
    is under way at the drone; None before."""
    statuses = {sid: await stations[sid].status(mission_id) for sid in ring}
    ended = all(
        s.mission in (ring_pb2.MISSION_STATE_DONE, ring_pb2.MISSION_STATE_FAILED)
        for s in statuses.values()
    )
    return statuses if ended and (await drone.status()).preparing_for < 0 else None


def describe(results: Sequence[MissionResult], elapsed_s: float) -> str:
    """The per-mission lines and the fleet's summary, for a person."""
    lines = ["drone        mission  ring      masters        exactly once  replicas"]
    for r in results:
        ring = ",".join(map(str, r.ring))
        masters = "->".join(map(str, r.masters)) or "-"
        lines.append(
            f"{r.drone:<12} {r.mission_id:>7}  {ring:<9} {masters:<14} "
            f"{r.effects.get('exactly_once')!s:<13} "
            f"{'consistent' if r.replicas_consistent else 'DIVERGED'}"
            + (f"  FAILED: {r.failed}" if r.failed else "")
        )
    ok = sum(r.ok for r in results)
    lines.append(
        f"fleet: {ok}/{len(results)} missions completed exactly once with consistent "
        f"replicas in {elapsed_s:.1f} s"
    )
    return "\n".join(lines)


@dataclass
class FleetRun:
    """A fleet's run at its end: each mission's result and its flight (its report, its
    track, its pictures), and the network the stations formed."""

    results: list[MissionResult]
    flights: list[Flight]
    network: BatonConfig


def fleet_report(fleet: FleetFile, run: FleetRun, duration_s: float) -> dict[str, Any]:
    """The fleet's JSON report: the stations, each mission's result with its own
    single-mission report, and the summary."""
    reports = {f.drone: f.report for f in run.flights}
    missions = [
        {
            "drone": r.drone,
            "mission_id": r.mission_id,
            "ring": list(r.ring),
            "masters": reports[r.drone]["masters"],
            "handovers": reports[r.drone]["handovers"],
            "exactly_once": r.effects.get("exactly_once") is True,
            "replicas_consistent": r.replicas_consistent,
            "failed": r.failed,
            "ok": r.ok,
            "report": reports[r.drone],
        }
        for r in run.results
    ]
    return {
        "format": FLEET_REPORT_FORMAT,
        "duration_s": round(duration_s, 3),
        "speedup": fleet.speedup,
        "stations": [s.model_dump(mode="json") for s in fleet.stations],
        "missions": missions,
        "summary": {"missions": len(missions), "ok": sum(r.ok for r in run.results)},
    }


async def _follow(drones: Mapping[str, MissionDrone], tracks: dict[str, Track]) -> None:
    """Notes where each drone is, twice a second (as the single-mission testbed does);
    a drone that does not answer is skipped that time."""
    while True:
        for name, drone in drones.items():
            try:
                tracks[name].note(await drone.status(), time.time())
            except grpc.aio.AioRpcError:
                pass
        await asyncio.sleep(TRACK_PERIOD_S)


@dataclass(frozen=True)
class Admission:
    """A drone's admitted mission: its number in the registry, its ring (station ids in
    route order) and its first master."""

    number: int
    ring: tuple[int, ...]
    first_master: int


def admit_fleet(fleet: FleetFile, registry_file: Path) -> dict[str, Admission]:
    """A new registry in ``registry_file`` holding the file's stations, and every
    drone's mission admitted over them; ValueError names a refused mission."""
    from baton.drone.policy import Station
    from baton.fleet.admission import Refused
    from baton.fleet.registry import Registry
    from baton.fleet.routes import survey_route
    from baton.sdk.types import Position

    registry_file.unlink(missing_ok=True)
    admitted = {}
    with Registry(registry_file) as registry:
        for s in fleet.stations:
            where = Position(s.location.latitude_deg, s.location.longitude_deg)
            registry.add_station(f"station-{s.id}", Station(s.id, where, s.range_m))
        for d in fleet.drones:
            take_off = Position(d.home.latitude_deg, d.home.longitude_deg)
            route = survey_route(take_off, d.mission.plan().targets())
            decision = registry.admit(d.name, route)
            if isinstance(decision, Refused):
                raise ValueError(f"drone {d.name}'s mission is refused: {decision.message()}")
            number, how = decision
            admitted[d.name] = Admission(number, how.ring, how.first_master)
    return admitted


def fleet_identities(fleet: FleetFile) -> list[Identity]:
    """Who gets a certificate: each station (its controller id), each drone its own
    identity (spiffe://baton/drone/NAME: its missions' stations take no other drone's
    certificate for it, and check its replies with its own key), and the operator."""
    return [
        *(Identity.controller(s.id) for s in fleet.stations),
        *(Identity.drone(d.name) for d in fleet.drones),
        OPERATOR,
    ]


def fleet_network(fleet: FleetFile, addresses: Mapping[int, str], certs: Path) -> BatonConfig:
    """The network the stations form: each at its address, placed with its range, and
    what every mission over them shares (speed-up, handover policy, takeover)."""
    return BatonConfig.model_validate(
        {
            "controllers": [
                {
                    "id": s.id,
                    "address": addresses[s.id],
                    "location": s.location.model_dump(),
                    "range_m": s.range_m,
                }
                for s in fleet.stations
            ],
            "speedup": fleet.speedup,
            "handover_policy": fleet.handover_policy.model_dump(),
            "takeover_after": fleet.takeover_after,
            "flush_limit": 0,
            "tls": {"certs": str(certs)},
        }
    )


def write_network(workdir: Path, network: BatonConfig) -> Path:
    """The network's file in ``workdir``, as an operator's: with the registry, what
    ``baton fleet missions|status|view`` read."""
    from baton.lifecycle import write_atomically

    document = network.model_dump(mode="json", exclude_unset=True)
    path = workdir / NETWORK_FILE
    write_atomically(path, yaml.safe_dump(document, sort_keys=False))
    return path


def mission_config(
    network: BatonConfig, drone: FleetDrone, admission: Admission, address: str
) -> BatonConfig:
    """The configuration drone ``drone``'s mission flies with, on its stations and
    its drone service alike: admission's ring from its first master, the drone named,
    at home, at ``address``."""
    from baton.fleet.stations import ring_config

    mission = ring_config(network, admission.ring, admission.first_master)
    at = mission.drone.model_copy(
        update={"address": address, "home": drone.home, "name": drone.name}
    )
    return mission.model_copy(update={"drone": at})


def note_drone_addresses(
    registry_file: Path, admitted: Mapping[str, Admission], drones: Mapping[str, MissionDrone]
) -> None:
    """Each mission's drone address in the registry, as ``baton fleet start`` notes it."""
    from baton.fleet.registry import Registry

    with Registry(registry_file) as registry:
        for name, drone in drones.items():
            registry.set_drone_address(admitted[name].number, drone.address)


async def run_fleet(fleet: FleetFile, workdir: Path, timeout_s: float) -> FleetRun:
    """Admits every mission, starts the stations, vehicles and drones as processes, and
    flies the fleet (``fly_fleet``); ValueError names a refused mission before anything
    starts."""
    from baton.certs.make import init

    workdir.mkdir(parents=True, exist_ok=True)
    admitted = admit_fleet(fleet, workdir / REGISTRY_FILE)
    certs = workdir / "certs"
    init(certs, fleet_identities(fleet))
    async with Supervisor(workdir / "parts") as supervisor:
        stations = await start_stations(
            supervisor,
            [s.id for s in fleet.stations],
            certs,
            cert_lifetime_s=fleet.station_cert_lifetime,
        )
        network = fleet_network(fleet, {sid: s.address for sid, s in stations.items()}, certs)
        write_network(workdir, network)
        drones: dict[str, MissionDrone] = {}
        configs: dict[str, BatonConfig] = {}
        for d in fleet.drones:
            # The drone's port is picked as it starts; its sessions are told where it is.
            at_home = mission_config(network, d, admitted[d.name], "127.0.0.1:0")
            drone = await start_mission_drone(supervisor, d.name, at_home)
            drones[d.name] = drone
            configs[d.name] = mission_config(network, d, admitted[d.name], drone.address)
        note_drone_addresses(workdir / REGISTRY_FILE, admitted, drones)
        try:
            return await fly_fleet(fleet, admitted, configs, network, stations, drones, timeout_s)
        finally:
            await close_parts(stations, drones)


async def close_parts(
    stations: Mapping[int, StationPart], drones: Mapping[str, MissionDrone]
) -> None:
    """Closes the operator's channels to the stations and the drones."""
    for channel in [s.channel for s in stations.values()] + [d.channel for d in drones.values()]:
        await channel.close()


async def fly_fleet(
    fleet: FleetFile,
    admitted: Mapping[str, Admission],
    configs: Mapping[str, BatonConfig],
    network: BatonConfig,
    stations: Mapping[int, StationPart],
    drones: Mapping[str, MissionDrone],
    timeout_s: float,
) -> FleetRun:
    """Flies the admitted fleet on stations and drones that run already, wherever they
    run: waits for every vehicle to be ready, starts each mission's sessions on its
    ring's stations, waits for every mission's end following each drone's track, and
    judges each mission from its vehicle's and camera's effects and its replicas."""
    from baton.fleet.sessions import start_sessions

    operator = network.tls_for(OPERATOR)
    await _every([d.ready for d in drones.values()], "every vehicle ready", READY_S)
    # Followed from before the first mission starts: the others start while it flies.
    tracks = {name: Track() for name in drones}
    following = asyncio.create_task(_follow(drones, tracks))
    results, flights = [], []
    try:
        for d in fleet.drones:
            plan = d.mission.plan()
            await asyncio.to_thread(
                start_sessions,
                configs[d.name],
                str(admitted[d.name].number),
                str(plan.file),
                plan.args(),
                operator,
            )
        started = time.monotonic()
        for d in fleet.drones:
            admission, drone = admitted[d.name], drones[d.name]
            left = max(1.0, timeout_s - (time.monotonic() - started))
            statuses = await poll_until(
                partial(mission_ended, stations, drone, str(admission.number), admission.ring),
                f"drone {d.name}'s mission {admission.number} ended",
                left,
            )
            snapshot = await drone.snapshot(statuses)
            plan = d.mission.plan()
            results.append(
                mission_result(d.name, str(admission.number), admission.ring, plan, snapshot)
            )
            report = build_report(
                configs[d.name],
                snapshot,
                plan.grid,
                time.monotonic() - started,
                [],
                plan.spacing_m,
                targets=plan.targets() if plan.kind != "grid" else None,
            )
            taken = snapshot.camera_effects or []
            flights.append(Flight(d.name, report, tracks[d.name].points, taken))
    finally:
        following.cancel()
    return FleetRun(results, flights, network)


async def poll_until(check: Any, what: str, timeout_s: float) -> Any:
    """``check()``'s first truthy answer, polled; TimeoutError naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        answer = await check()
        if answer:
            return answer
        await asyncio.sleep(0.2)
    raise TimeoutError(f"{what}: not within {timeout_s:.0f} s")


async def _every(checks: Sequence[Any], what: str, timeout_s: float) -> None:
    for check in checks:
        await poll_until(check, what, timeout_s)

"""A mission's configuration over stations started by ``baton.testbed.fleet``, its
sessions started on them, and its mission programs there."""

from __future__ import annotations

import asyncio
from collections.abc import Mapping, Sequence
from pathlib import Path

import pytest
import yaml
from waiting import eventually

from baton.bench.cpu import child_pids
from baton.cli import main
from baton.config import BatonConfig
from baton.rpc.mission import MISSION_TOKEN_ENV
from baton.testbed.fleet import MissionDrone, StationPart, start_mission_drone, start_stations
from baton.testbed.supervisor import Supervisor, baton_argv
from baton.v1 import station_pb2


def mission_config(
    drone_address: str,
    stations: dict[int, StationPart],
    ring: Sequence[int],
    certs: Path,
    speedup: float = 20.0,
) -> BatonConfig:
    """A mission's configuration: its drone, and its ring's stations at their ports."""
    return BatonConfig.model_validate(
        {
            "drone": {"address": drone_address},
            "controllers": [{"id": sid, "address": stations[sid].address} for sid in ring],
            "ring": list(ring),
            "speedup": speedup,
            "flush_limit": 0,
            "tls": {"certs": str(certs)},
        }
    )


async def stations_and_drones(
    supervisor: Supervisor,
    certs: Path,
    rings: Mapping[str, Sequence[int]],
    handovers: Mapping[str, Sequence[tuple[int, int]]],
) -> tuple[dict[int, StationPart], dict[str, MissionDrone]]:
    """Stations 1, 2 and 3, and for each mission of ``rings`` its sim vehicle and drone
    service (its scripted ``handovers``), every vehicle ready to arm."""
    stations = await start_stations(supervisor, (1, 2, 3), certs)
    drones = {
        m: await start_mission_drone(
            supervisor, m, mission_config("127.0.0.1:0", stations, ring, certs), handovers[m]
        )
        for m, ring in rings.items()
    }
    for drone in drones.values():
        await eventually(drone.ready, f"{drone.name}'s vehicle ready to arm", 120)
    return stations, drones


async def start_on_rings(
    stations: dict[int, StationPart],
    drones: Mapping[str, MissionDrone],
    rings: Mapping[str, Sequence[int]],
    certs: Path,
    program: Path,
    args: Mapping[str, Sequence[str]],
) -> None:
    """Each mission of ``rings`` started on its ring's stations, in ring order, flying
    ``program`` with its ``args``."""
    for mission, ring in rings.items():
        config = as_text(mission_config(drones[mission].address, stations, ring, certs))
        for sid in ring:
            await stations[sid].stub.StartMission(
                station_pb2.StartMissionRequest(
                    mission_id=mission, config=config, program=str(program), args=args[mission]
                )
            )


async def program_pid(supervisor: Supervisor, station: StationPart, mission: str) -> int:
    """The process of the mission program that ``station`` runs for ``mission``: the
    station's child started on that session's program port."""
    address = (await station.status(mission)).mission_address.encode()
    process = supervisor.parts[f"station-{station.id}"].process
    assert process is not None
    for pid in child_pids(process.pid):
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        if address in argv:
            return pid
    raise AssertionError(f"station {station.id} runs no program for {mission} on {address!r}")


def program_token(pid: int) -> str:
    """The mission token a program process was started with (in its environment): what
    its calls on its program's port carry (rpc/mission.py)."""
    environ = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    prefix = f"{MISSION_TOKEN_ENV}=".encode()
    return next(v[len(prefix) :].decode() for v in environ if v.startswith(prefix))


def as_text(config: BatonConfig) -> str:
    """The configuration as StartMission carries it (JSON, which YAML reads)."""
    return config.model_dump_json(exclude_unset=True)


def network_file(
    path: Path,
    stations: dict[int, StationPart],
    places: dict[int, tuple[float, float]],
    range_m: float,
    certs: Path,
    **extra: object,
) -> Path:
    """The network's testbed file for ``baton fleet``: each station at its port, its
    antenna at ``places`` and its range; ``extra`` top-level fields (drone, speedup)."""
    document = {
        "drone": {"address": "127.0.0.1:1"},
        "controllers": [
            {
                "id": sid,
                "address": stations[sid].address,
                "location": {"latitude_deg": lat, "longitude_deg": lon},
                "range_m": range_m,
            }
            for sid, (lat, lon) in places.items()
        ],
        "tls": {"certs": str(certs)},
        **extra,
    }
    path.write_text(yaml.safe_dump(document))
    return path


async def fleet_cli(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    """``baton fleet ARGS`` run as an operator types it (off the event loop): its exit
    status and what it printed, out and err."""
    status = await asyncio.to_thread(main, ["fleet", *args])
    out, err = capsys.readouterr()
    return status, out + err


async def start_fleet_service(
    supervisor: Supervisor, registry: Path, network: Path | None, certs: Path
) -> str:
    """``baton fleet serve`` over ``registry`` (and the ``network`` file) as the operator
    of ``certs``, on a free port: its address."""
    ready = supervisor.workdir / "fleet.address"
    argv = baton_argv(
        "fleet",
        "serve",
        f"--registry={registry}",
        "--listen=127.0.0.1:0",
        f"--address-file={ready}",
        f"--certs={certs}",
        *([f"--config={network}"] if network is not None else []),
    )
    return await supervisor.start_ready("fleet", argv, ready)


async def hosted(station: StationPart) -> dict[str, station_pb2.SessionState.ValueType]:
    """The missions a station hosts, each with its session's state."""
    status = await station.stub.GetStation(station_pb2.GetStationRequest(), timeout=5)
    return {m.mission_id: m.state for m in status.missions}

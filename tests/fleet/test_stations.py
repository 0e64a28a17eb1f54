"""``baton station`` across real processes: three stations host two missions with
different rings, sharing a station, each flown by its own sim vehicle and drone
service, while a third mission's program crashes on two of the same stations and a
fourth stalls there (its drone never answers)."""

from __future__ import annotations

from functools import partial
from pathlib import Path

import grpc
import pytest
from helpers.missions import SMALL_GRID, assert_mission_promises
from helpers.stations import as_text, mission_config, stations_and_drones
from waiting import eventually

from baton.certs.make import init
from baton.config import BatonConfig
from baton.rpc.channels import aio_channel
from baton.rpc.mission import mission_metadata
from baton.rpc.tls import DRONE, OPERATOR, Identity, Tls
from baton.testbed.local import TestbedPlan
from baton.testbed.supervisor import Supervisor
from baton.v1 import ring_pb2, ring_pb2_grpc, station_pb2

RINGS = {"alpha": (1, 2), "bravo": (2, 3)}  # station 2 hosts both
HANDOVERS = {"alpha": ((7, 2),), "bravo": ((7, 3),)}
CRASHING = "def mission(drone):\n    raise RuntimeError('charlie crashes on purpose')\n"


def start_request(
    mission: str, config: BatonConfig, program: Path, args: list[str]
) -> station_pb2.StartMissionRequest:
    return station_pb2.StartMissionRequest(
        mission_id=mission, config=as_text(config), program=str(program), args=args
    )


async def test_two_missions_share_stations_exactly_once_and_a_crash_touches_neither(
    tmp_path: Path,
) -> None:
    certs = tmp_path / "certs"
    init(certs, [*(Identity.controller(s) for s in (1, 2, 3)), DRONE, OPERATOR])
    crash = tmp_path / "crash.py"
    crash.write_text(CRASHING)
    async with Supervisor(tmp_path / "parts") as supervisor:
        stations, drones = await stations_and_drones(supervisor, certs, RINGS, HANDOVERS)

        # A station outside a mission's ring is refused it, and keeps nothing of it.
        config = {
            m: mission_config(d.address, stations, RINGS[m], certs) for m, d in drones.items()
        }
        with pytest.raises(grpc.aio.AioRpcError) as refused:
            await stations[3].stub.StartMission(
                start_request("alpha", config["alpha"], SMALL_GRID.file, SMALL_GRID.args())
            )
        assert refused.value.code() == grpc.StatusCode.FAILED_PRECONDITION
        assert "does not hold station 3" in (refused.value.details() or "")
        assert not (stations[3].state_dir / "missions" / "alpha").exists()

        for mission, ring in RINGS.items():
            for sid in ring:
                started = await stations[sid].stub.StartMission(
                    start_request(mission, config[mission], SMALL_GRID.file, SMALL_GRID.args())
                )
                assert started.state == station_pb2.SESSION_STATE_HOSTING

        # Both fly; then a third mission on stations 1 and 3 crashes at once.
        for drone in drones.values():
            await eventually(partial(drone.served, 3), f"{drone.name} served request 3", 60)
        charlie = mission_config("127.0.0.1:1", stations, (1, 3), certs)
        for sid in (1, 3):
            await stations[sid].stub.StartMission(start_request("charlie", charlie, crash, []))

        async def charlie_failed() -> bool:
            for sid in (1, 3):
                status = await stations[sid].stub.GetStation(station_pb2.GetStationRequest())
                states = {m.mission_id: m for m in status.missions}
                if states["charlie"].state != station_pb2.SESSION_STATE_FAILED:
                    return False
                assert states["charlie"].error
            return True

        await eventually(charlie_failed, "charlie's sessions failed and ended", 60)
        # A fourth mission on the same stations stalls: its drone never answers. Its
        # status says why it waits; the others fly on (below), and its stop ends it.
        delta = mission_config("127.0.0.1:1", stations, (1, 3), certs)
        for sid in (1, 3):
            await stations[sid].stub.StartMission(
                start_request("delta", delta, SMALL_GRID.file, SMALL_GRID.args())
            )

        async def delta_waits() -> ring_pb2.ControllerStatus | None:
            status = await stations[1].status("delta")
            return (
                status
                if "no Connect stream to the drone at 127.0.0.1:1" in status.waiting
                else None
            )

        stalled = await eventually(delta_waits, "delta's master saying what it waits for", 60)
        assert stalled.mission == ring_pb2.MISSION_STATE_RUNNING, stalled
        for sid in (1, 3):
            stopped = await stations[sid].stub.StopMission(
                station_pb2.StopMissionRequest(mission_id="charlie")
            )
            assert not stopped.was_running
            assert not (stations[sid].state_dir / "missions" / "charlie").exists()
        with pytest.raises(grpc.aio.AioRpcError) as unknown:
            await stations[1].status("charlie")
        assert unknown.value.code() == grpc.StatusCode.NOT_FOUND
        assert "'charlie'" in (unknown.value.details() or "")

        # A station acts only on the missions whose ring holds it: station 3's
        # certificate streams no log frames into alpha's session on station 1.
        as_three = Tls.load(certs, Identity.controller(3))
        async with aio_channel(stations[1].address, as_three, Identity.controller(1)) as channel:
            call = ring_pb2_grpc.ControllerRingStub(channel).LogRing(
                metadata=mission_metadata("alpha")
            )
            with pytest.raises(grpc.aio.AioRpcError) as denied:
                await call.read()
            assert denied.value.code() == grpc.StatusCode.PERMISSION_DENIED
        # A malformed frame from a station of alpha's ring ends that stream only: both
        # missions fly on (checked below, exactly once).
        as_one = Tls.load(certs, Identity.controller(1))
        async with aio_channel(stations[2].address, as_one, Identity.controller(2)) as channel:
            raw: grpc.aio.StreamStreamMultiCallable[bytes, bytes]
            raw = channel.stream_stream("/baton.v1.ControllerRing/LogRing")
            garbage = raw(iter([b"\xff\xff not a LogFrame"]), metadata=mission_metadata("alpha"))
            with pytest.raises(grpc.aio.AioRpcError) as malformed:
                async for _ in garbage:
                    pass
            assert malformed.value.code() == grpc.StatusCode.INVALID_ARGUMENT

        async def ended(mission: str) -> dict[int, ring_pb2.ControllerStatus] | None:
            statuses = {sid: await stations[sid].status(mission) for sid in RINGS[mission]}
            done = all(s.mission == ring_pb2.MISSION_STATE_DONE for s in statuses.values())
            drone = await drones[mission].status()
            return statuses if done and drone.preparing_for < 0 else None

        for mission in RINGS:
            statuses = await eventually(lambda m=mission: ended(m), f"{mission} done", 120)
            snapshot = await drones[mission].snapshot(statuses)
            plan = TestbedPlan(mission=SMALL_GRID, handovers=HANDOVERS[mission])
            assert_mission_promises(snapshot, plan)
            assert {a.controller_id for a in snapshot.drone.audit} == set(RINGS[mission])

        for mission, ring in [*RINGS.items(), ("delta", (1, 3))]:
            for sid in ring:
                await stations[sid].stub.StopMission(
                    station_pb2.StopMissionRequest(mission_id=mission)
                )
                assert not (stations[sid].state_dir / "missions" / mission).exists()
        for channel in [
            *(s.channel for s in stations.values()),
            *(d.channel for d in drones.values()),
        ]:
            await channel.close()

"""The handover policy inside the drone service: its telemetry in, handovers and holds out."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import grpc
import pytest
from drone_harness import DroneUnderTest, start_drone
from helpers.drone_calls import GOTO, POSITION, invoke
from waiting import eventually

from baton.digest import request_digest
from baton.drone.policy import FLY_ON, HANDOVER, HOLD, STAY, PolicyParams, Station
from baton.drone.policy_runner import PolicyRunner
from baton.drone.safety import Failsafe
from baton.drone.store import Intent
from baton.rpc.errors import StatusError
from baton.rpc.server import BatonServer
from baton.rpc.streams import next_message
from baton.sdk import Position, offset
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

HOME = Position(47.397742, 8.545594)
RPC, POLICY = drone_pb2.HANDOVER_TRIGGER_RPC, drone_pb2.HANDOVER_TRIGGER_POLICY
# Three stations along a line east of home, 500 m apart, 400 m of range each.
STATIONS = {cid: Station(cid, offset(HOME, 0.0, 500.0 * cid), 400.0) for cid in (0, 1, 2)}
PARAMS = PolicyParams("nearest", margin_m=50.0, dwell_s=0.0, link_lost_after_s=0.0)


def put(drone: DroneUnderTest, east_m: float, altitude_m: float = 10.0) -> None:
    """Moves the fake vehicle ``east_m`` east of home."""
    where = offset(HOME, 0.0, east_m)
    drone.vehicle.position.latitude_deg = where.latitude_deg
    drone.vehicle.position.longitude_deg = where.longitude_deg
    drone.vehicle.position.relative_altitude_m = altitude_m


class Links:
    """Standby streams held for controllers, as their links to the drone."""

    def __init__(self, drone: DroneUnderTest) -> None:
        self.drone = drone
        self.calls: dict[int, grpc.aio.UnaryStreamCall] = {}  # type: ignore[type-arg]

    async def up(self, *cids: int) -> None:
        for cid in cids:
            call = self.drone.stub.Standby(drone_pb2.StandbyRequest(controller_id=cid))
            assert (await next_message(call)).HasField("held")
            self.calls[cid] = call
        await eventually(
            lambda: set(cids) <= self.drone.service.standby.reachable, f"{cids} reachable"
        )

    async def down(self, *cids: int) -> None:
        for cid in cids:
            self.calls.pop(cid).cancel()
        await eventually(
            lambda: not set(cids) & self.drone.service.standby.reachable, f"{cids} unreachable"
        )

    def close(self) -> None:
        for call in self.calls.values():
            call.cancel()


@pytest.fixture
async def ranged() -> AsyncIterator[tuple[DroneUnderTest, Links]]:
    drone, server = await start_drone(policy=PARAMS, stations=STATIONS)
    links = Links(drone)
    yield drone, links
    links.close()
    await server.stop(0)


async def test_the_drone_hands_over_to_the_nearest_station_and_says_why(
    ranged: tuple[DroneUnderTest, Links],
) -> None:
    drone, links = ranged
    await links.up(0, 1, 2)
    assert drone.service.policy is not None
    await drone.stub.Invoke(invoke(0, 1, POSITION))  # the mission has begun
    put(drone, 200.0)
    decision = await drone.service.policy.tick()
    assert decision is not None and decision.action == STAY
    put(drone, 300.0)  # 1 nearer by 100 m
    decision = await drone.service.policy.tick()
    assert decision is not None and decision.action == HANDOVER and decision.target == 1
    status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
    assert status.master == 1 and status.handover_policy == drone_pb2.HANDOVER_POLICY_NEAREST
    (record,) = status.handovers
    assert (record.old_master, record.new_master, record.trigger) == (0, 1, POLICY)
    assert (
        record.kind == drone_pb2.HANDOVER_KIND_COOPERATIVE
    )  # 0's link is up: it is told, and sends its log
    assert "1 nearer (200 m) than master 0 (300 m of 400 m)" in record.reason
    assert record.position.longitude_deg == pytest.approx(offset(HOME, 0, 300.0).longitude_deg)
    assert [d.action for d in status.policy_decisions] == [STAY, HANDOVER]
    assert status.policy_decision.reason == record.reason and not status.holding


async def test_the_operator_overrides_the_policy_while_its_choice_is_usable(
    ranged: tuple[DroneUnderTest, Links],
) -> None:
    drone, links = ranged
    await links.up(0, 1, 2)
    assert drone.service.policy is not None
    put(drone, 650.0)  # 1 at 150 m, 2 at 350 m
    await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=2))
    decision = await drone.service.policy.tick()
    assert decision is not None and decision.action == STAY
    assert "chosen by the script or operator" in decision.reason
    put(drone, 550.0)  # 2 out of range (450 m of 400 m): the policy moves it to 1
    decision = await drone.service.policy.tick()
    assert decision is not None and (decision.action, decision.target) == (HANDOVER, 1)
    status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
    assert [(h.trigger, h.new_master) for h in status.handovers] == [(RPC, 2), (POLICY, 1)]


async def test_no_usable_controller_holds_the_vehicle_and_resumes_its_leg(
    ranged: tuple[DroneUnderTest, Links],
) -> None:
    drone, links = ranged
    await links.up(0, 1)
    assert drone.service.policy is not None
    put(drone, 0.0)
    # A leg that ends short of 2's range (it begins 600 m east).
    target = offset(HOME, 0.0, 580.0)
    goto = api.GotoRequest(
        latitude_deg=target.latitude_deg, longitude_deg=target.longitude_deg, relative_altitude_m=10
    )
    await drone.stub.Invoke(invoke(0, 1, GOTO, goto))
    # The fake vehicle jumps to the target; say it is still flying, 130 m out, and
    # every link is down (out of 0's range, and 1's link lost).
    put(drone, 450.0)
    await links.down(0, 1)
    decision = await drone.service.policy.tick()
    assert decision is not None and decision.action == HOLD
    assert decision.reason.endswith("the leg leads into no station's range")
    assert drone.vehicle.calls[-2:] == ["GetFlightState", "Hold"]
    status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
    assert status.holding and status.policy_decision.action == HOLD
    assert "0 out of range (450 m of 400 m); 1 link down" in status.policy_decision.reason
    calls = len(drone.vehicle.calls)
    decision = await drone.service.policy.tick()  # still none: no second Hold
    assert decision is not None and decision.action == HOLD
    assert "Hold" not in drone.vehicle.calls[calls:]
    # 1 comes back: it takes over (0 cannot be told) and the vehicle flies on.
    await links.up(1)
    decision = await drone.service.policy.tick()
    assert decision is not None and (decision.action, decision.target) == (HANDOVER, 1)
    assert decision.takeover
    assert drone.vehicle.calls[-1] == "Goto"
    assert drone.vehicle.position.longitude_deg == pytest.approx(target.longitude_deg)
    status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
    assert not status.holding and status.master == 1
    assert status.handovers[-1].kind == drone_pb2.HANDOVER_KIND_TAKEOVER
    assert [d.action for d in status.policy_decisions][-3:] == [
        HOLD,
        HANDOVER,
        drone_pb2.POLICY_ACTION_RESUME,
    ]


async def test_a_leg_into_another_range_is_flown_on_and_its_station_takes_over(
    ranged: tuple[DroneUnderTest, Links],
) -> None:
    """Master 1 lost with the vehicle in its range only, flying towards 2's: no hold;
    2 takes over once the vehicle is in its range and 2's link is up."""
    drone, links = ranged
    await links.up(0, 1)
    assert drone.service.policy is not None
    put(drone, 0.0)
    target = offset(HOME, 0.0, 900.0)
    goto = api.GotoRequest(
        latitude_deg=target.latitude_deg, longitude_deg=target.longitude_deg, relative_altitude_m=10
    )
    await drone.stub.Invoke(invoke(0, 1, GOTO, goto))
    put(drone, 450.0)
    await links.down(0, 1)
    decision = await drone.service.policy.tick()
    assert decision is not None and (decision.action, decision.target) == (FLY_ON, 2)
    assert decision.reason.endswith("flying on: the leg enters 2's range in 150 m")
    assert "Hold" not in drone.vehicle.calls
    status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
    assert not status.holding and status.policy_decision.action == FLY_ON
    # In 2's range, its link not up yet: still flying on (it has link_up_s to come up).
    put(drone, 650.0)
    decision = await drone.service.policy.tick()
    assert decision is not None and decision.action == FLY_ON
    assert "in 2's range (350 m of 400 m), its link has" in decision.reason
    await links.up(2)
    decision = await drone.service.policy.tick()
    assert decision is not None and (decision.action, decision.target) == (HANDOVER, 2)
    assert decision.takeover  # 1 cannot be told
    assert "Hold" not in drone.vehicle.calls and drone.vehicle.calls.count("Goto") == 1
    status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
    assert status.master == 2 and status.handovers[-1].kind == drone_pb2.HANDOVER_KIND_TAKEOVER
    assert [d.action for d in status.policy_decisions][-2:] == [FLY_ON, HANDOVER]


async def test_a_command_of_the_master_ends_a_hold(
    ranged: tuple[DroneUnderTest, Links],
) -> None:
    drone, _ = ranged
    assert drone.service.policy is not None
    put(drone, 1300.0)  # out of every range, no link: hold
    decision = await drone.service.policy.tick()
    assert decision is not None and decision.action == HOLD and drone.service.policy.holding
    # The master's Goto reaches the drone anyway (no radio here): it commands again.
    await drone.stub.Invoke(
        invoke(
            0,
            1,
            GOTO,
            api.GotoRequest(latitude_deg=47.4, longitude_deg=8.5, relative_altitude_m=10),
        )
    )
    assert not drone.service.policy.holding


async def test_a_master_still_starting_is_not_taken_over_by_the_first_controller_up() -> None:
    policy = PolicyParams("nearest", margin_m=50.0, dwell_s=0.0, link_lost_after_s=3.0)
    drone, server = await start_drone(policy=policy, stations=STATIONS)
    links = Links(drone)
    try:
        assert drone.service.policy is not None
        put(drone, 150.0, altitude_m=0.0)  # in 0's and 1's range; 0 has not come up yet
        await links.up(1)
        decision = await drone.service.policy.tick()
        assert decision is not None and decision.action == STAY, decision
        assert "master 0 link down (0.0 s" in decision.reason and "waiting 3 s" in decision.reason
        assert drone.service.seq.master == 0
    finally:
        links.close()
        await server.stop(0)


# -- a drone restarted around a hold (its state file; the vehicle outlives it) -----------


class Restartable:
    """A drone with a state file over one fake vehicle, restarted as a kill would: the
    service and its streams go, the vehicle keeps doing what it was last told."""

    def __init__(self, state: Path, params: PolicyParams = PARAMS) -> None:
        self.state, self.params = state, params
        self.drone: DroneUnderTest
        self.server: BatonServer
        self.links: Links

    async def start(self) -> DroneUnderTest:
        previous = getattr(self, "drone", None)
        vehicle = previous.vehicle if previous is not None else None
        self.drone, self.server = await start_drone(
            vehicle=vehicle, policy=self.params, stations=STATIONS, state_file=str(self.state)
        )
        self.links = Links(self.drone)
        return self.drone

    async def restart(self) -> DroneUnderTest:
        """The service again; the vehicle's calls are counted from the restart on."""
        await self.stop()
        self.drone.vehicle.calls.clear()
        return await self.start()

    async def stop(self) -> None:
        self.links.close()
        await self.server.stop(0)
        assert self.drone.service.store is not None
        self.drone.service.store.close()

    @property
    def policy(self) -> PolicyRunner:
        assert self.drone.service.policy is not None
        return self.drone.service.policy

    async def status(self) -> drone_pb2.DroneStatus:
        return await self.drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())


@pytest.fixture
async def restartable(tmp_path: Path) -> AsyncIterator[Restartable]:
    bed = Restartable(tmp_path / "drone.sqlite")
    await bed.start()
    yield bed
    await bed.stop()


def goto(east_m: float) -> api.GotoRequest:
    target = offset(HOME, 0.0, east_m)
    return api.GotoRequest(
        latitude_deg=target.latitude_deg, longitude_deg=target.longitude_deg, relative_altitude_m=10
    )


async def fly_and_lose_every_link(
    bed: Restartable, leg_to_east_m: float
) -> drone_pb2.PolicyAction.ValueType:
    """Master 0 sends the vehicle on a leg to ``leg_to_east_m``; at 450 m east (out of
    0's range, in 1's) every link goes down: the policy's decision."""
    drone = bed.drone
    await bed.links.up(0, 1)
    put(drone, 0.0)
    await drone.stub.Invoke(invoke(0, 1, GOTO, goto(leg_to_east_m)))
    put(drone, 450.0)  # the fake vehicle jumped to the target: say it is still flying
    await bed.links.down(0, 1)
    decision = await bed.policy.tick()
    assert decision is not None
    return decision.action


def flight_commands(drone: DroneUnderTest, since: int = 0) -> list[str]:
    return [c for c in drone.vehicle.calls[since:] if c in ("Hold", "Goto")]


@pytest.mark.parametrize("usable_at_once", [False, True], ids=["still-none", "usable-at-once"])
async def test_a_drone_restarted_while_the_vehicle_holds_keeps_the_hold_and_resumes_the_leg(
    restartable: Restartable, usable_at_once: bool
) -> None:
    """The vehicle held by the policy outlives the drone service: the restarted drone
    knows it holds (GetStatus says so at once), and on which leg, and flies it on as
    soon as a controller is usable, whether that is at its first decision or later."""
    bed = restartable
    assert await fly_and_lose_every_link(bed, 580.0) == HOLD  # the leg ends short of 2's range
    assert flight_commands(bed.drone) == ["Goto", "Hold"]
    drone = await bed.restart()
    assert (await bed.status()).holding, "the restarted drone forgot the vehicle holds"
    if not usable_at_once:
        decision = await bed.policy.tick()
        assert decision is not None and decision.action == HOLD
        assert decision.reason.endswith("the leg leads into no station's range")
        # The hold is sent again (the vehicle may not have heard it before the restart).
        assert flight_commands(drone) == ["Hold"]
        assert (await bed.status()).holding
    await bed.links.up(1)
    decision = await bed.policy.tick()
    assert decision is not None and (decision.action, decision.target) == (HANDOVER, 1)
    assert flight_commands(drone)[-1:] == ["Goto"], "the vehicle was left holding"
    target = goto(580.0)
    assert drone.vehicle.position.longitude_deg == pytest.approx(target.longitude_deg)
    status = await bed.status()
    assert not status.holding and status.master == 1
    resume = status.policy_decisions[-1]
    assert resume.action == drone_pb2.POLICY_ACTION_RESUME, status.policy_decisions
    assert "held before the drone's restart" in resume.reason
    # Counted where the report finds it after another restart, with no decision left.
    assert status.policy_resumes == 1
    await bed.restart()
    status = await bed.status()
    assert (status.policy_resumes, len(status.policy_decisions)) == (1, 0)


async def test_a_drone_restarted_while_flying_on_still_flies_the_leg_on(
    restartable: Restartable,
) -> None:
    """No controller usable, the leg leading into 2's range: flying on. The restarted
    drone knows the leg too, so it flies on rather than holding the vehicle."""
    bed = restartable
    assert await fly_and_lose_every_link(bed, 900.0) == FLY_ON
    drone = await bed.restart()
    assert not (await bed.status()).holding
    decision = await bed.policy.tick()
    assert decision is not None and (decision.action, decision.target) == (FLY_ON, 2), decision
    assert flight_commands(drone) == []


async def test_a_goto_cut_off_by_a_restart_forgets_the_old_leg_and_hold(
    restartable: Restartable,
) -> None:
    """The master's Goto while the vehicle held, cut off by a restart: the vehicle may be
    flying to the new target (the master is told UNKNOWN), so the old leg is never resumed."""
    bed = restartable
    assert await fly_and_lose_every_link(bed, 580.0) == HOLD
    request = invoke(0, 2, GOTO, goto(300.0))
    store = bed.drone.service.store
    assert store is not None
    store.begin(Intent(2, GOTO, request_digest(GOTO, request.payload), 0, 1.0))
    drone = await bed.restart()
    assert not (await bed.status()).holding
    await bed.links.up(1)
    decision = await bed.policy.tick()
    assert decision is not None and (decision.action, decision.target) == (HANDOVER, 1)
    assert flight_commands(drone) == []


async def test_a_resume_the_vehicle_refused_is_tried_again(restartable: Restartable) -> None:
    """The resume's Goto fails (the autopilot did not answer): the drone still holds the
    vehicle as far as it knows, and sends the Goto again at its next decision."""
    bed = restartable
    assert await fly_and_lose_every_link(bed, 580.0) == HOLD
    drone = bed.drone
    goto_once = drone.vehicle.Goto

    async def refused(request: api.GotoRequest) -> api.GotoReply:
        drone.vehicle.Goto = goto_once  # type: ignore[method-assign]
        drone.vehicle.calls.append("Goto")
        raise StatusError(grpc.StatusCode.UNAVAILABLE, "Goto: no answer from the autopilot")

    drone.vehicle.Goto = refused  # type: ignore[method-assign]
    await bed.links.up(1)
    with pytest.raises(StatusError):
        await bed.policy.tick()
    assert (await bed.status()).holding
    decision = await bed.policy.tick()
    assert decision is not None and decision.action == STAY
    assert flight_commands(drone) == ["Goto", "Hold", "Goto", "Goto"]
    assert drone.vehicle.position.longitude_deg == pytest.approx(goto(580.0).longitude_deg)
    assert not (await bed.status()).holding


async def test_a_drone_restarted_while_holding_waits_for_its_master_before_resuming(
    tmp_path: Path,
) -> None:
    """Held in master 0's range, 0's link lost: a restarted drone counts 0 as seen for
    its start-up grace, and the policy waits for 0 (stay). Nobody can command the
    vehicle meanwhile, so it is not resumed until 0's link is up again."""
    params = PolicyParams("nearest", margin_m=50.0, dwell_s=0.0, link_lost_after_s=0.5)
    bed = Restartable(tmp_path / "drone.sqlite", params)
    drone = await bed.start()
    try:
        await bed.links.up(0)
        put(drone, 0.0)
        await drone.stub.Invoke(invoke(0, 1, GOTO, goto(80.0)))  # in 0's range only
        put(drone, 50.0)
        await bed.links.down(0)

        async def held() -> bool:
            decision = await bed.policy.tick()
            return decision is not None and decision.action == HOLD

        await eventually(held, "the hold once 0's loss is waited out")
        drone = await bed.restart()
        decision = await bed.policy.tick()
        assert decision is not None and decision.action == STAY and decision.waiting, decision
        assert flight_commands(drone) == [], "resumed with no controller usable"
        assert (await bed.status()).holding
        await bed.links.up(0)
        decision = await bed.policy.tick()
        assert decision is not None and decision.action == STAY and not decision.waiting
        assert flight_commands(drone) == ["Goto"]
        assert not (await bed.status()).holding
    finally:
        await bed.stop()


async def test_in_failsafe_the_policy_neither_holds_nor_flies_the_leg_on(
    ranged: tuple[DroneUnderTest, Links],
) -> None:
    """The failsafe's action (a return) has the vehicle: the policy's hold would stop
    it, its resume would fly the mission's leg again (issue 32)."""
    drone, links = ranged
    await links.up(0, 1)
    assert drone.service.policy is not None
    put(drone, 0.0)
    target = offset(HOME, 0.0, 580.0)
    goto = api.GotoRequest(
        latitude_deg=target.latitude_deg, longitude_deg=target.longitude_deg, relative_altitude_m=10
    )
    await drone.stub.Invoke(invoke(0, 1, GOTO, goto))
    put(drone, 450.0)
    drone.service.core.enter_failsafe(Failsafe("lost_link", "rtl", 0.0, "no usable controller"))
    await links.down(0, 1)
    calls = len(drone.vehicle.calls)
    await drone.service.policy.tick()
    await links.up(1)
    await drone.service.policy.tick()
    assert "Hold" not in drone.vehicle.calls[calls:]
    assert "Goto" not in drone.vehicle.calls[calls:]

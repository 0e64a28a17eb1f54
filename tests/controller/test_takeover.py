"""A master killed with kill -9 does not end the mission (issue 10), across real processes.

Before takeovers the drone waited for ever for the dead master (its
``Handover`` RPC answered OK, and no controller could take over). Now every
controller holds a standby stream to the drone; the drone, having seen
neither a stream nor a request of the master for the takeover time, makes
the first reachable controller after it in ring order master in a new
epoch. That controller replays what it holds and re-sends the rest, which
the drone answers from the replies it retained above the master's
watermark, so nothing is executed twice: counted at the sim vehicle and the
camera. A killed master that comes back is told it was taken over (fenced),
drops what it had, and rejoins as a replica with a restarted program.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from helpers.missions import FAST_LINK, LONG_LEGS, assert_mission_promises, log_events, until_served
from waiting import eventually

from baton.config import LinkSpec
from baton.testbed.local import WIFI_DRONE_LINK, LocalTestbed, Snapshot, TestbedPlan, local_config
from baton.v1 import drone_pb2, ring_pb2

LOST = drone_pb2.HANDOVER_TRIGGER_LOST


def three_controllers(
    flush_limit: int,
    handovers: tuple[tuple[int, int], ...] = (),
    drone_link: LinkSpec = FAST_LINK,
    **fields: Any,
) -> TestbedPlan:
    """Ring 0 -> 1 -> 2 -> 0, master 0, the long-legged mission at 20x, fast links;
    ``fields``: more of the configuration (``local_config``)."""
    config = local_config(
        3,
        flush_limit=flush_limit,
        speedup=20.0,
        controller_link=FAST_LINK,
        drone_link=drone_link,
        **fields,
    )
    return TestbedPlan(config=config, handovers=handovers, mission=LONG_LEGS)


def takeovers(
    snapshot: Snapshot,
) -> list[tuple[int, int, drone_pb2.HandoverTrigger.ValueType]]:
    """(old master, new master, trigger) of every takeover the drone made."""
    return [
        (h.old_master, h.new_master, h.trigger)
        for h in snapshot.drone.handovers
        if h.kind == drone_pb2.HANDOVER_KIND_TAKEOVER
    ]


async def kill_when(
    testbed: LocalTestbed, victim: int, after_reqnr: int, unflushed: bool
) -> Snapshot:
    """Waits until the drone served ``after_reqnr`` (and, if ``unflushed``, ``victim`` holds
    log entries it has not flushed), then kill -9 of ``victim``; the snapshot of then."""

    async def ready() -> bool:
        snapshot = await testbed.snapshot(audit=False)
        master = snapshot.controllers[victim]
        return snapshot.drone.last_reqnr >= after_reqnr and (
            not unflushed or master.log_entries > 0
        )

    await eventually(ready, f"request {after_reqnr} served", 120)
    before = await testbed.snapshot(audit=False)
    await testbed.kill_controller(victim)
    return before


async def test_a_killed_master_is_taken_over_and_the_mission_completes(tmp_path: Path) -> None:
    plan = three_controllers(0)
    async with LocalTestbed(plan, tmp_path) as testbed:
        await kill_when(testbed, 0, 12, unflushed=False)
        snapshot = await testbed.run_mission(240)
    assert_mission_promises(snapshot, plan)
    assert takeovers(snapshot) == [(0, 1, LOST)]
    record = snapshot.drone.handovers[0]
    # Seen last at the kill; taken over after the takeover time (3 s of mission time,
    # at least 1 s of wall time); the new master's first request came after.
    assert record.decided_at - record.lost_at >= snapshot.drone.takeover_after_s
    assert record.first_request_at > record.decided_at
    assert snapshot.drone.master == 1 and snapshot.drone.epoch == 2
    roles = [h.role for h in snapshot.controllers[1].handovers]
    assert roles == [ring_pb2.HANDOVER_ROLE_TAKER]
    assert "master lost: taken over" in [e.get("msg") for e in log_events(tmp_path, "drone")]


async def test_the_unflushed_tail_of_a_killed_master_comes_from_the_drone(
    tmp_path: Path,
) -> None:
    """A 2 MB flush limit: the master holds pictures it has not flushed when it is killed.
    Only the drone has those replies; it retained them (above the watermark) and gives
    them to the new master with the TakeOver, which answers its program from them: none
    is executed twice, none is even sent again."""
    plan = three_controllers(2 * 2**20)
    async with LocalTestbed(plan, tmp_path) as testbed:
        before = await kill_when(testbed, 0, 14, unflushed=True)
        snapshot = await testbed.run_mission(240)
    assert_mission_promises(snapshot, plan)
    assert takeovers(snapshot) == [(0, 1, LOST)]
    lost = before.controllers[0]
    assert lost.log_entries > 0
    # The requests the dead master had logged and not flushed were answered from the
    # replies the drone retained, not executed again.
    assert before.drone.retained_replies >= 1
    assert snapshot.controllers[1].answered_from_retained >= 1


async def test_a_killed_master_restarted_after_the_takeover_rejoins_as_a_replica(
    tmp_path: Path,
) -> None:
    """It restarts with its log file (which may hold messages that never left it) and
    asks the drone, which tells it it was taken over; it drops all it had, restarts its
    program, and catches up from the ring like a controller with nothing."""
    plan = three_controllers(2 * 2**20)
    async with LocalTestbed(plan, tmp_path) as testbed:
        await kill_when(testbed, 0, 14, unflushed=True)

        async def taken_over() -> bool:
            snapshot = await testbed.snapshot(audit=False)
            return snapshot.drone.master == 1 and snapshot.drone.last_reqnr > 20

        await eventually(taken_over, "controller 1 master and flying", 120)
        await testbed.restart_controller(0)
        snapshot = await testbed.run_mission(240)
    assert_mission_promises(snapshot, plan)
    assert takeovers(snapshot) == [(0, 1, LOST)]
    rejoined = snapshot.controllers[0]
    assert [h.role for h in rejoined.handovers] == [ring_pb2.HANDOVER_ROLE_FENCED]
    assert not rejoined.master and rejoined.mission == ring_pb2.MISSION_STATE_DONE
    messages = [e.get("msg") for e in log_events(tmp_path, "controller-0")]
    assert "rejoined as a replica with nothing; catching up from the ring" in messages


async def test_a_master_killed_after_the_drone_decided_a_handover_before_its_log_left(
    tmp_path: Path,
) -> None:
    """The drone hands over from 0 to 1 after request 12; 0's log (16 MB flush limit:
    never flushed before) cannot leave it: the ring links into 1 and into 2 are cut
    before the mission starts. Cut once the mission runs, the cut may come after the
    log left (a loaded machine); cut into 1 only, 0 routes around it to 2 after the
    detection time, and 2 gives 1 the log once 0 is dead. 0 is killed once the drone
    decided. 1, master by the drone's word, waits for a log that will never come, until
    the drone, not seeing 0, grants 1 again by takeover in a newer epoch; 1 gets every
    reply from the drone."""
    cut = ("link-ring-1", "link-ring-2")
    plan = replace(three_controllers(16 * 2**20, handovers=((12, 1),)), links_cut=cut)
    async with LocalTestbed(plan, tmp_path) as testbed:

        async def decided() -> bool:
            return (await testbed.snapshot(audit=False)).drone.master == 1

        await eventually(decided, "the drone decided the handover", 120)
        await testbed.kill_controller(0)
        for link in cut:
            await testbed.restore_link(link)
        snapshot = await testbed.run_mission(240)
    assert_mission_promises(snapshot, plan)
    assert takeovers(snapshot) == [(0, 1, LOST)]
    cooperative, taken = snapshot.drone.handovers
    assert (cooperative.kind, cooperative.epoch, taken.epoch) == (
        drone_pb2.HANDOVER_KIND_COOPERATIVE,
        2,
        3,
    )
    assert cooperative.first_request_at == 0  # 1 never sent a request in epoch 2
    assert snapshot.controllers[1].epoch == 3


async def test_a_dead_replica_is_routed_around_and_the_watermark_moves_on(
    tmp_path: Path,
) -> None:
    """Controller 1 of 0 -> 1 -> 2 -> 0 is killed for good: 0 sends to 2 after the
    detection time, the mission completes on 0 and 2, and the drone retains only the
    replies above a watermark that keeps moving (2 tells 0 what it holds)."""
    plan = three_controllers(0)
    async with LocalTestbed(plan, tmp_path) as testbed:
        await kill_when(testbed, 1, 12, unflushed=False)
        snapshot = await testbed.run_mission(240)
    assert_mission_promises(snapshot, plan)
    assert takeovers(snapshot) == []
    master = snapshot.controllers[0]
    assert list(master.routed_around) == [1] and master.successor == 2
    # Everything but the last few requests is known held by every live controller.
    assert snapshot.drone.last_reqnr - master.watermark_reqnr <= 3
    assert snapshot.drone.retained_replies <= 3


async def test_a_master_cut_off_from_the_drone_is_fenced_and_rejoins_when_the_link_returns(
    tmp_path: Path,
) -> None:
    """Controller 0's link to the drone is cut while its process lives: the drone, not
    seeing it, makes 1 master. 0 goes on re-sending its request into the cut; nothing it
    sends once the link is back is executed: the drone refuses it as taken over (or the
    ring told it first), and 0 stops acting as master, drops what it had and rejoins as
    a replica."""
    plan = three_controllers(2 * 2**20)
    async with LocalTestbed(plan, tmp_path) as testbed:
        await until_served(testbed, 12)
        await testbed.cut_link("link-drone-0")

        async def taken_over() -> bool:
            snapshot = await testbed.snapshot(audit=False)
            return snapshot.drone.master == 1 and snapshot.drone.last_reqnr > 24

        await eventually(taken_over, "controller 1 master and flying", 120)
        # 0 learns it from the ring (1's log messages of epoch 2, the test below) or,
        # if 1 flushed nothing yet, from the drone once the link is back: fenced once.
        await testbed.restore_link("link-drone-0")
        snapshot = await testbed.run_mission(240)
    assert_mission_promises(snapshot, plan)
    assert takeovers(snapshot) == [(0, 1, LOST)]
    rejoined = snapshot.controllers[0]
    assert [h.role for h in rejoined.handovers] == [ring_pb2.HANDOVER_ROLE_FENCED]
    assert not rejoined.master and rejoined.mission == ring_pb2.MISSION_STATE_DONE
    taken = snapshot.drone.handovers[0]
    assert all(
        a.controller_id != 0 for a in snapshot.drone.audit if a.received_at > taken.decided_at
    )


async def test_a_master_cut_off_from_the_drone_for_good_follows_the_ring_as_a_replica(
    tmp_path: Path,
) -> None:
    """As above, but the link never comes back (a station the vehicle flew away from):
    the drone cannot tell 0 it was taken over. The ring can: 1's log messages are of a
    newer mastership. 0 fences itself on them, rejoins with nothing and follows the
    ring; its program ends with the mission. Before, it stayed ACTIVE for ever, its
    program waiting on the drone (found by the simulation's --policy corridors)."""
    plan = three_controllers(2 * 2**20)
    async with LocalTestbed(plan, tmp_path) as testbed:
        await until_served(testbed, 12)
        await testbed.cut_link("link-drone-0")

        async def others_done() -> bool:
            snapshot = await testbed.snapshot(audit=False)
            return all(
                snapshot.controllers[cid].mission == ring_pb2.MISSION_STATE_DONE for cid in (1, 2)
            )

        await eventually(others_done, "the mission ended on controllers 1 and 2", 240)

        async def followed() -> bool:
            c = (await testbed.snapshot(audit=False)).controllers[0]
            return not c.master and c.mission == ring_pb2.MISSION_STATE_DONE

        await eventually(followed, "controller 0 a replica, its program done", 60)
        snapshot = await testbed.run_mission(60)
    assert_mission_promises(snapshot, plan)
    assert takeovers(snapshot) == [(0, 1, LOST)]
    rejoined = snapshot.controllers[0]
    assert [h.role for h in rejoined.handovers] == [ring_pb2.HANDOVER_ROLE_FENCED]
    assert rejoined.state == ring_pb2.CONTROLLER_STATE_PASSIVE


async def test_a_master_given_the_role_back_before_it_heard_of_a_takeover_rejoins_first(
    tmp_path: Path,
) -> None:
    """Controller 0, cut off from the drone, never hears of the handover to 2 (forced:
    0 is out of reach); 2, waiting for 0's log, is taken over by 1; then the role comes
    back to 0 by 1's handover message, and 0's link returns. 0 is still ACTIVE in epoch
    1 on a log the taker framed anew from the drone's replies: the drone's Connected says
    the takeover's epoch, and 0 rejoins with nothing before it takes the role from the
    handover message. Before, it went on as master on its epoch-1 log, the handover
    message queued for ever (the simulation's --policy seeds 71 and 177). The operator
    makes every switch here (``takeover_after: 0``: the drone takes nothing over)."""
    config = local_config(
        3,
        flush_limit=64 * 2**20,  # no flush: nothing on the ring tells 0 before its link returns
        speedup=20.0,
        controller_link=FAST_LINK,
        drone_link=FAST_LINK,
        takeover_after=0,
    )
    plan = TestbedPlan(config=config, mission=LONG_LEGS)
    async with LocalTestbed(plan, tmp_path) as testbed:
        assert testbed.drone_stub is not None
        drone = testbed.drone_stub
        await until_served(testbed, 12)
        await testbed.cut_link("link-drone-0")
        await drone.Handover(drone_pb2.HandoverRequest(new_master=2))  # 0 never hears
        taken = await drone.Handover(drone_pb2.HandoverRequest(new_master=1, takeover=True))
        await until_served(testbed, taken.after_reqnr + 4)  # 1 flies as master
        back = await drone.Handover(drone_pb2.HandoverRequest(new_master=0))
        assert back.epoch > taken.epoch
        await testbed.restore_link("link-drone-0")
        snapshot = await testbed.run_mission(240)
    assert snapshot.drone.takeover_after_s == 0  # the file's value reached the drone
    assert_mission_promises(snapshot, plan)
    assert takeovers(snapshot) == [(2, 1, drone_pb2.HANDOVER_TRIGGER_RPC)]
    rejoined = snapshot.controllers[0]
    assert ring_pb2.HANDOVER_ROLE_FENCED in [h.role for h in rejoined.handovers]
    assert rejoined.mission == ring_pb2.MISSION_STATE_DONE


async def test_a_master_behind_a_silent_link_is_taken_over_within_seconds(
    tmp_path: Path,
) -> None:
    """Controller 0's link to the drone goes silent: the link emulator is frozen
    (SIGSTOP), so its connections stay open and carry nothing, with no reset to notice,
    like a radio link that fades. The drone's keepalive finds it within 3 s, not the
    project's default 15 s, and 1 takes over; when the link comes back, 0 is fenced."""
    plan = three_controllers(2 * 2**20)
    async with LocalTestbed(plan, tmp_path) as testbed:
        await until_served(testbed, 12)
        silent_since = time.time()
        testbed.blackhole_link("link-drone-0")

        async def taken_over() -> bool:
            return (await testbed.snapshot(audit=False)).drone.master == 1

        await eventually(taken_over, "controller 1 master", 60)
        record = (await testbed.snapshot(audit=False)).drone.handovers[-1]
        found_after = record.decided_at - silent_since
        # Keepalive (ping 1 s, answer within 2 s), then the takeover time (1 s at 20x).
        assert found_after < 6.0, (
            f"the takeover came {found_after:.1f} s after the link went silent"
        )
        testbed.thaw_link("link-drone-0")
        snapshot = await testbed.run_mission(240)
    assert_mission_promises(snapshot, plan)
    assert takeovers(snapshot) == [(0, 1, LOST)]
    rejoined = snapshot.controllers[0]
    assert [h.role for h in rejoined.handovers] == [ring_pb2.HANDOVER_ROLE_FENCED]
    assert not rejoined.master and rejoined.mission == ring_pb2.MISSION_STATE_DONE


async def test_a_master_killed_with_a_picture_in_flight_gets_no_second_picture(
    tmp_path: Path,
) -> None:
    """The drone link is the WiFi one (20 Mbit/s): a picture's reply (about 1 MB) takes
    0.4 s to reach the master, which is killed as soon as the drone executed the
    TakePicture. The new master gets that reply with the TakeOver, among the replies the
    drone retained, and answers its program from it: the camera counts one picture per
    waypoint."""
    plan = three_controllers(2 * 2**20, drone_link=WIFI_DRONE_LINK)
    async with LocalTestbed(plan, tmp_path) as testbed:
        stub = testbed.drone_stub
        assert stub is not None

        async def picture_executed() -> bool:
            status = await stub.GetStatus(drone_pb2.GetDroneStatusRequest(include_audit=True))
            return bool(status.audit) and status.audit[-1].method.endswith("/TakePicture")

        await eventually(picture_executed, "a TakePicture executed", 120)
        await testbed.kill_controller(0)
        snapshot = await testbed.run_mission(240)
    assert_mission_promises(snapshot, plan)
    assert takeovers(snapshot) == [(0, 1, LOST)]
    # The picture the lost master never got was answered from the retained tail.
    again = [
        e
        for e in log_events(tmp_path, "controller-1")
        if e.get("msg") == "answered from the retained tail"
        and str(e.get("method")).endswith("/TakePicture")
    ]
    assert again


async def test_a_master_that_dies_while_the_drone_restarts_is_taken_over(
    tmp_path: Path,
) -> None:
    """The drone is killed, then the master; the drone restarts from its state file. It
    never sees the master again, yet counts it as there before the restart (plus a grace
    for the controllers to re-connect), so it is lost, not waited for for good."""
    # The drone is down for as long as its restart takes (7 s on two loaded cores):
    # the autopilot's own GCS failsafe must not take that for its death and land the
    # vehicle (test_failsafe_end_to_end.py covers that it does past its bound).
    plan = three_controllers(0, handovers=((8, 1),), safety={"autopilot_gcs_timeout": "10min"})
    async with LocalTestbed(plan, tmp_path) as testbed:

        async def handed_over() -> bool:
            drone = (await testbed.snapshot(audit=False)).drone
            return drone.master == 1 and drone.last_reqnr >= 14

        await eventually(handed_over, "controller 1 master and flying", 120)
        await testbed.supervisor.kill("drone")
        await testbed.kill_controller(1)
        await testbed.supervisor.restart("drone")
        snapshot = await testbed.run_mission(240)
    assert_mission_promises(snapshot, plan)
    assert takeovers(snapshot) == [(1, 2, LOST)]
    messages = [e.get("msg") for e in log_events(tmp_path, "drone")]
    assert "state resumed" in messages and "master lost: taken over" in messages


async def test_a_new_master_that_never_connects_is_taken_over_whatever_streams_it_holds(
    tmp_path: Path,
) -> None:
    """The script makes controller 1 master at request 30, but the ring link into 1 is
    frozen from request 24 on: the handover message never reaches it, so it never goes
    ACTIVE nor connects, while its standby stream to the drone stays up. The drone takes
    it over once it has not served (no Connect stream, no request) for the longer of the
    takeover time and the prepare timeout, whatever streams it holds; before, the
    mission waited for as long as the link stayed frozen. When the link thaws, 1 is
    fenced and rejoins as a replica."""
    plan = three_controllers(0, handovers=((30, 1),))
    plan = replace(plan, config=plan.config.model_copy(update={"prepare_timeout": 3.0}))
    async with LocalTestbed(plan, tmp_path) as testbed:
        await until_served(testbed, 24)
        testbed.blackhole_link("link-ring-1")

        async def taken_over() -> bool:
            return bool(takeovers(await testbed.snapshot(audit=False)))

        await eventually(taken_over, "the stuck new master taken over", 60)
        handed, taken = (await testbed.snapshot(audit=False)).drone.handovers[:2]
        testbed.thaw_link("link-ring-1")
        snapshot = await testbed.run_mission(240)
    assert (handed.old_master, handed.new_master, handed.kind) == (
        0,
        1,
        drone_pb2.HANDOVER_KIND_COOPERATIVE,
    )
    assert handed.first_request_at == 0  # 1 never sent a request as master
    # Not served for the prepare timeout (3 s, longer than the takeover time).
    assert taken.decided_at - handed.decided_at >= 3.0
    assert takeovers(snapshot) == [(1, 2, LOST)]
    assert_mission_promises(snapshot, plan)
    rejoined = snapshot.controllers[1]
    assert not rejoined.master and rejoined.mission == ring_pb2.MISSION_STATE_DONE

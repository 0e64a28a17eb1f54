"""The ring's forwarding and prepared handovers across real processes (issue 12).

Cut-through forwarding and the straight catch-up are the default; the paper's
store-and-forward stays available (docs/design.md, "The ring's forwarding",
"Prepared handover"). Every test holds the mission's promises, counted at the
drone's audit and where the side effects happened (``assert_mission_promises``).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.missions import FAST_LINK, SMALL_GRID, assert_mission_promises, fly
from waiting import eventually

from baton.bench.script import BENCH_MISSION, bench_mission_args
from baton.config import LinkSpec
from baton.testbed.local import (
    PAPER_CONTROLLER_LINK,
    LocalTestbed,
    MissionPlan,
    Snapshot,
    TestbedPlan,
    drone_status,
    local_config,
)
from baton.v1 import drone_pb2, ring_pb2

PREPARED, COOPERATIVE = drone_pb2.HANDOVER_KIND_PREPARED, drone_pb2.HANDOVER_KIND_COOPERATIVE


def relayed(status: ring_pb2.ControllerStatus, peer: int) -> ring_pb2.PeerStatus:
    (link,) = [p for p in status.peers if p.id == peer]
    return link


@pytest.mark.parametrize(
    ("forwarding", "prepared"),
    [("store-and-forward", False), ("cut-through", True)],
    ids=["paper", "cut-through-prepared"],
)
async def test_six_controllers_over_one_three_and_five_hops_in_each_mode(
    tmp_path: Path, forwarding: str, prepared: bool
) -> None:
    """The handovers over 1, 3 and 5 hops of the worst-case benchmark, in the paper's
    protocol (forced handovers, whole messages) and in baton's (cut-through, prepared)."""
    plan = TestbedPlan(
        config=local_config(
            6,
            flush_limit=0,
            # A prepared handover waits for its target to be at most 0.25 s of wall time
            # behind (PREPARED_BEHIND_S), which on two loaded cores comes only while a
            # leg is flown; at 20x a leg took 0.2 s, and a preparation the whole mission.
            speedup=5.0 if prepared else 20.0,
            controller_link=FAST_LINK,
            drone_link=FAST_LINK,
            ring={"forwarding": forwarding},
        ),
        handovers=((6, 1), (12, 4), (18, 3)),
        mission=SMALL_GRID,
        prepared=prepared,
    )
    snapshot = await fly(tmp_path, plan)
    scripted = [
        h for h in snapshot.drone.handovers if h.trigger == drone_pb2.HANDOVER_TRIGGER_SCRIPT
    ]
    kinds = {h.kind for h in scripted}
    assert kinds == {PREPARED if prepared else COOPERATIVE}, scripted
    if prepared:
        assert all(0 < h.prepare_started_at <= h.decided_at for h in scripted)
        assert all(h.prepare_lacked_bytes <= 16 << 10 for h in scripted)
    relays = sum(p.relayed_messages for c in snapshot.controllers.values() for p in c.peers)
    if forwarding == "cut-through":
        assert relays > 0
    else:
        assert relays == 0


# On demand (pytest -m slow): about 60 s of CI's 25 minutes; a cut-through message cut
# mid-frame (below) and the six-controller modes keep the forwarding in CI.
@pytest.mark.slow
async def test_a_64_mb_message_crosses_a_six_controller_cut_through_ring_intact(
    tmp_path: Path,
) -> None:
    """Four 17 MB pictures under a 128 MB flush limit: the master's last flush, when its
    program ends, is one 66 MB message, passed on frame by frame by four controllers."""
    plan = TestbedPlan(
        config=local_config(
            6,
            flush_limit=128 * 2**20,
            speedup=20.0,
            controller_link=FAST_LINK,
            drone_link=FAST_LINK,
        ),
        mission=SMALL_GRID,
        resolution="2400x2400",
    )
    snapshot = await fly(tmp_path, plan, timeout=300)
    largest = max(
        int(line.split('"reply_bytes": ')[1].split(",")[0].rstrip("}"))
        for line in (tmp_path / "logs" / "drone.log").read_text().splitlines()
        if '"executed"' in line and "TakePicture" in line
    )
    assert largest > 17 * 10**6
    # Controllers 1-4 passed the big message on to their successor as it came (5's
    # successor is its origin); every replica replayed the same replies
    # (assert_mission_promises), so it arrived whole everywhere.
    for cid in (1, 2, 3, 4):
        link = relayed(snapshot.controllers[cid], cid + 1)
        assert link.relayed_messages >= 1 and link.relays_aborted == 0, link


async def test_a_ring_link_cut_in_the_middle_of_a_cut_through_message_loses_nothing(
    tmp_path: Path,
) -> None:
    """Controller 1 is passing a 5.8 MB picture on to 2 over a 25 Mbit/s link when the
    link breaks: 1 gives the relay up, and 2 gets the message whole once the link is
    back, from 1's re-send; nothing is lost or handled twice."""
    plan = TestbedPlan(
        config=local_config(
            3,
            flush_limit=0,
            speedup=20.0,
            controller_link=PAPER_CONTROLLER_LINK,
            drone_link=FAST_LINK,
        ),
        mission=MissionPlan(grid=2, spacing_m=20.0, altitude_m=5.0, speed_m_s=5.0, poll_s=1.0),
        resolution="1600x1200",
    )
    async with LocalTestbed(plan, tmp_path) as testbed:
        stub = testbed.controller_stubs[1]

        async def relaying() -> int:
            status = await stub.GetStatus(ring_pb2.GetControllerStatusRequest(), timeout=10)
            return relayed(status, 2).relaying

        lognr = await eventually(relaying, "controller 1 relaying a message to 2", 120)
        await testbed.cut_link("link-ring-2")
        await testbed.restore_link("link-ring-2")
        snapshot = await testbed.run_mission(300)
    assert_mission_promises(snapshot, plan)
    link = relayed(snapshot.controllers[1], 2)
    assert link.relays_aborted >= 1 and link.connects >= 2, (lognr, link)


async def test_a_prepared_handover_whose_target_never_catches_up_is_forced(
    tmp_path: Path,
) -> None:
    """The target's link is frozen (it hears nothing, its streams stay open): the drone
    forces the handover at prepare_timeout, and the mission completes once the link
    carries again."""
    plan = TestbedPlan(
        config=local_config(
            3,
            flush_limit=0,
            prepare_timeout=1.0,
            # Long enough that the mission goes on well after the forced handover.
            speedup=5.0,
            controller_link=FAST_LINK,
            drone_link=FAST_LINK,
        ),
        handovers=((8, 2),),
        prepared=True,
        mission=MissionPlan(grid=3, spacing_m=20.0, altitude_m=5.0, speed_m_s=5.0, poll_s=1.0),
    )
    async with LocalTestbed(plan, tmp_path) as testbed:
        testbed.blackhole_link("link-ring-2")
        try:

            async def forced() -> list:
                assert testbed.drone_stub is not None
                status = await drone_status(testbed.drone_stub, audit=False)
                return [h for h in status.handovers if h.prepare_timed_out]

            (record,) = await eventually(forced, "the prepared handover forced", 120)
        finally:
            testbed.thaw_link("link-ring-2")
        snapshot = await testbed.run_mission(300)
    assert_mission_promises(snapshot, plan)
    assert (record.kind, record.new_master) == (COOPERATIVE, 2)
    assert record.decided_at - record.prepare_started_at >= 1.0
    assert not any(h.kind == PREPARED for h in snapshot.drone.handovers)


async def test_a_prepared_handover_moves_the_master_between_requests_on_the_masters_word(
    tmp_path: Path,
) -> None:
    """The master's program sleeps right after the handover begins: no request comes for
    3 s. The master tells the drone between requests once its target caught up
    (ReportPreparation), so the master moves during the sleep, and the request after it
    is the new master's. (At the next request instead, the old master would serve it,
    and the preparation would last the whole sleep.)"""
    script = "p,p,c,s3,p,p"  # reqnr 3 is the picture, 4 the sleep, 5 the next request
    plan = TestbedPlan(
        config=local_config(
            3, flush_limit=0, speedup=1.0, controller_link=FAST_LINK, drone_link=FAST_LINK
        ),
        handovers=((3, 2),),
        prepared=True,
        mission_file=BENCH_MISSION,
        mission_args=bench_mission_args(script),
    )
    async with LocalTestbed(plan, tmp_path) as testbed:
        snapshot = await testbed.run_mission(120)
    for cid, c in snapshot.controllers.items():
        assert c.mission == ring_pb2.MISSION_STATE_DONE, (
            f"controller {cid}: mission {c.mission}: {c.mission_error}"
        )
    drone = snapshot.drone
    assert drone.executed == 5  # the five drone calls, once each
    (record,) = [h for h in drone.handovers if h.trigger == drone_pb2.HANDOVER_TRIGGER_SCRIPT]
    assert (record.kind, record.new_master, record.after_reqnr) == (PREPARED, 2, 3)
    assert record.decided_at - record.prepare_started_at < 2.0
    served_by = {a.reqnr: a.controller_id for a in drone.audit}
    assert (served_by[3], served_by[5], served_by[6]) == (0, 2, 2)
    words = (tmp_path / "logs" / "controller-0.log").read_text()
    assert "drone moves the master on our word" in words


async def test_scripted_handovers_closer_than_a_preparation_each_happen_in_order(
    tmp_path: Path,
) -> None:
    """The script's second line is due at the request after the first's: the first
    preparation cannot have caught up by then (20 ms ring links). The second line
    waits for the first handover; it does not replace the first preparation, which
    dropped a scripted handover (CI at 5e5646f, the 3-hop one of the six-controller
    test, under load)."""
    plan = TestbedPlan(
        config=local_config(
            3,
            flush_limit=0,
            speedup=1.0,
            controller_link=LinkSpec(latency=0.02, bandwidth=None),
            drone_link=FAST_LINK,
        ),
        handovers=((3, 1), (4, 2)),
        prepared=True,
        mission_file=BENCH_MISSION,
        mission_args=bench_mission_args("p,p,p,p,p,s1,p,p"),
    )

    def scripted_of(snapshot: Snapshot) -> list[drone_pb2.HandoverRecord]:
        return [
            h for h in snapshot.drone.handovers if h.trigger == drone_pb2.HANDOVER_TRIGGER_SCRIPT
        ]

    async with LocalTestbed(plan, tmp_path) as testbed:
        snapshot = await testbed.run_mission(120)
        for cid, c in snapshot.controllers.items():
            assert c.mission == ring_pb2.MISSION_STATE_DONE, (
                f"controller {cid}: mission {c.mission}: {c.mission_error}"
            )

        # The second preparation may still be under way as the last request is served
        # (under load its target catches up later): the master's word between requests
        # moves the master once it has, after the mission's end too.
        async def both_handed_over() -> bool:
            return len(scripted_of(await testbed.snapshot(audit=False))) >= 2

        await eventually(both_handed_over, "the second scripted handover", 30)
        snapshot = await testbed.snapshot(audit=False)
    scripted = scripted_of(snapshot)
    assert [(h.old_master, h.new_master, h.kind) for h in scripted] == [
        (0, 1, PREPARED),
        (1, 2, PREPARED),
    ], scripted
    assert scripted[1].prepare_started_at >= scripted[0].decided_at
    assert snapshot.drone.master == 2

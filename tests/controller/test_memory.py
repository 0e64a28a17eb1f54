"""Bounded memory across real processes (issue 9, defect 8).

Every controller used to keep every log message it ever sent, once per peer
(120 pictures left 120-145 MB in each controller after a mission). Now a
message is held in memory only until its successor acknowledges it; the
history a restarted successor needs is on disk (controller/history.py).
"""

from __future__ import annotations

from pathlib import Path

from helpers.memory import rss_bytes
from waiting import eventually

from baton.testbed.local import LocalTestbed, TestbedPlan, local_config
from baton.v1 import ring_pb2

MISSIONS = Path(__file__).parent / "missions"
PICTURES = 200
MB = 2**20


async def test_a_200_picture_mission_leaves_the_controllers_memory_flat(tmp_path: Path) -> None:
    plan = TestbedPlan(
        config=local_config(3, flush_limit=0, speedup=20.0),
        handovers=((60, 1), (140, 2)),
        emulate_links=False,
        mission_file=MISSIONS / "pictures.py",
        mission_args=(f"count={PICTURES}",),
    )
    async with LocalTestbed(plan, tmp_path) as testbed:
        pids = {}
        for cid in plan.config.ring_order:
            process = testbed.supervisor.parts[f"controller-{cid}"].process
            assert process is not None
            pids[cid] = process.pid

        async def pictures_taken() -> bool:
            return (await testbed.snapshot(audit=False)).drone.last_reqnr >= 20

        await eventually(pictures_taken, "20 pictures taken", 120)
        early = {cid: rss_bytes(pid) for cid, pid in pids.items()}
        snapshot = await testbed.run_mission(300)
        late = {cid: rss_bytes(pid) for cid, pid in pids.items()}
    for cid, c in snapshot.controllers.items():
        assert c.mission == ring_pb2.MISSION_STATE_DONE, f"controller {cid}: {c.mission_error}"
    assert len({c.reply_chain for c in snapshot.controllers.values()}) == 1
    # Each picture taken once: the drone's audit, and the camera's own count.
    assert [a.reqnr for a in snapshot.drone.audit] == list(range(1, PICTURES + 1))
    assert snapshot.camera_effects is not None and len(snapshot.camera_effects) == PICTURES
    assert [h.new_master for h in snapshot.drone.handovers] == [1, 2]
    carried = sum(a.reply_bytes for a in snapshot.drone.audit)
    assert carried > 150 * MB  # the pictures went round the ring
    growth = {cid: (late[cid] - early[cid]) / MB for cid in pids}
    print(f"controller RSS growth over {PICTURES - 20} pictures, MB: {growth}")
    for cid, grew in growth.items():
        assert grew < 40, (
            f"controller {cid} grew by {grew:.0f} MB over {carried / MB:.0f} MB of log"
        )

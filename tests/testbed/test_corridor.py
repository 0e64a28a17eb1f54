"""The corridor survey across real processes: the drone picks its masters from where it is.

examples/corridor.yaml on free ports: four stations of 500 m range along a
1.5 km line, radio range on every controller's link to the drone (the link
emulators follow the sim vehicle), a handover policy and no handover script.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
import yaml
from helpers.testbed_runs import CORRIDOR, corridor_on_free_ports, run_testbed
from waiting import eventually

from baton.config import LinkSpec, load_config
from baton.drone.policy import FLY_ON, HANDOVER, HOLD
from baton.link.radio import RadioRange
from baton.sdk import Position, offset
from baton.sdk.geo import north_east_m
from baton.testbed.local import LocalTestbed, TestbedPlan, free_port
from baton.testbed.report import build_report
from baton.v1 import drone_pb2

MARGIN_M, SPEED_M_S = 50.0, 5.0
# The predictive policy's lead, in mission seconds. The example's 10 s is 0.95 s
# of wall time at the test's speed-up 10, while the preparation runs in wall time:
# a 1 MB picture in the master's tail, over the drone link at the range's faded
# edge, took longer than that on CI, and the vehicle left the old station's range
# first (a takeover, not a prepared handover). 20 s gives it 1.9 s.
LEAD_S = 20.0
# The waits about a link to the drone: a station's own, and the drone's about it.
LINK_KEYS = ("standby", "drone", "link 0", "link 1", "link 2", "link 3")


def link_lines(workdir: Path, cid: int) -> list[dict]:  # type: ignore[type-arg]
    log = workdir / "logs" / f"link-drone-{cid}.log"
    return [json.loads(line) for line in log.read_text().splitlines() if line.startswith("{")]


# predictive on demand (pytest -m slow): about 60 s of CI's 25 minutes; its decisions
# are covered in CI by the simulation's --policy predictive seeds.
# Both on demand (~60 s each; CI's 25 minutes): in CI, `make compose-test`'s radio run flies
# this corridor by the range policy in containers, and the simulation sweeps both policies.
@pytest.mark.slow
@pytest.mark.parametrize("policy", ["nearest", "predictive"])
def test_the_corridor_is_flown_with_the_masters_its_stations_reach(
    tmp_path: Path, policy: str
) -> None:
    config_path = corridor_on_free_ports(tmp_path, policy, lead=f"{LEAD_S:g}s")
    config = load_config(config_path)
    report = run_testbed(
        tmp_path, "--config", str(config_path), "--mission", "corridor", "--spacing", "100"
    )
    assert report["completed"] and report["replicas_consistent"]
    assert report["exactly_once"] and report["side_effects"]["exactly_once"] is True
    assert report["side_effects"]["pictures_taken"] == report["mission"]["waypoints"] == 16
    assert report["handovers_planned"] == []
    # Every station was out of range for a while, as planned, and said so quietly: no
    # warning about a station's link to the drone, on the progress line or in the
    # report (the drone would warn of one in range without its stream).
    assert "out of range, as planned: " in report["stdout"]
    expected = {w["part"] for w in report["waits"]["expected"] if w["text"] == "out of range"}
    assert expected == {"c0", "c1", "c2", "c3"}, report["waits"]
    links = [w for w in report["waits"]["needs_person"] if w["key"] in LINK_KEYS]
    assert links == [] and "stream to the drone" not in report["stdout"], report["waits"]
    assert report["policy"] == {
        "name": policy,
        "radio_range": True,
        "holds": 0,
        "resumes": 0,
        "flown_on": 0,
    }
    # One station after the other, each by the policy, each prepared (the new master
    # caught up while the vehicle flew on), each within both stations' range.
    assert report["masters"] == [0, 1, 2, 3]
    assert [(h["trigger"], h["kind"]) for h in report["handovers"]] == [("policy", "prepared")] * 3
    for h in report["handovers"]:
        old, new = (
            RadioRange(s.location.latitude_deg, s.location.longitude_deg, s.range_m)
            for s in (config.controller(h["from"]), config.controller(h["to"]))
            if s.location is not None and s.range_m is not None
        )
        from_old, from_new = old.distance_m(*h["position"]), new.distance_m(*h["position"])
        assert from_old <= old.range_m and from_new <= new.range_m, h  # both in range
        if policy == "nearest":
            assert from_new + MARGIN_M < from_old, h
            assert "nearer" in h["reason"]
        else:
            # On the line, flying away from the old station at 5 m/s: handed over once its
            # range would run out within the lead, with a tick of slack.
            assert old.range_m - LEAD_S * SPEED_M_S - 5 <= from_old <= old.range_m, h
            assert "range runs out in" in h["reason"]
        assert 0 < h["delay_s"] < 5, h
    # The map beside the report: the path in one part per master, each handover on it.
    geojson = json.loads((tmp_path / "report.geojson").read_text())
    kinds = [f["properties"]["kind"] for f in geojson["features"]]
    assert kinds.count("station") == kinds.count("range") == 4
    paths = [
        f["properties"]["master"] for f in geojson["features"] if f["properties"]["kind"] == "path"
    ]
    assert paths == [0, 1, 2, 3] and kinds.count("handover") == 3
    assert (tmp_path / "report.png").read_bytes()[:4] == b"\x89PNG"
    # The radio was real: station 0 lost the vehicle beyond 500 m and cut the link;
    # station 3 was refused until the vehicle came within 500 m of it.
    workdir = tmp_path / "w"
    zero, three = link_lines(workdir, 0), link_lines(workdir, 3)
    assert any(line.get("msg") == "vehicle out of radio range" for line in zero)
    assert next(line for line in zero if line.get("msg") == "link stopped")["cut"] >= 1
    # From the start (a "radio fade" line may come first: the vehicle's position was
    # known by then, 1.5 km out, deep in the fade).
    ranged = [line["msg"] for line in three if "radio range" in line.get("msg", "")]
    assert ranged[0] == "vehicle out of radio range", ranged
    assert any(line.get("msg") == "vehicle in radio range" for line in three)
    assert next(line for line in three if line.get("msg") == "link stopped")["refused"] >= 1


# Across the boundary between stations 0 and 1 (east 250 m; `nearest` moves the
# master about 25 m past it): first dithering within 15 m of it, then three full
# crossings. Distinct targets: the exactly-once check counts a goto to one place twice.
DITHER = [240, 262, 242, 264, 244]
CROSSINGS = [340, 160, 342]
# Then station 1's link to the drone gets slow: 500 ms each way, over the 0.8 s
# bound on the round trip the drone measures (its own is 2 ms each way). The
# mission done, a master does not report its preparation (it sends no request):
# the drone forces a prepared handover after 3 s (the mission's took 0.1-0.3 s).
SLOW_LINK_S, MAX_RTT_S, PREPARE_TIMEOUT_S = 0.5, 0.8, 3.0


async def test_back_and_forth_across_a_boundary_moves_the_master_once_per_crossing(
    tmp_path: Path,
) -> None:
    """And, the mission done (landed 342 m east, in 0's and 1's range, master 1):
    master 1's link to the drone gets slow. The drone measures its round trip
    rising over the bound, the policy leaves it for 0 and keeps off it while it
    is slow, and goes back to it, the nearer, once it is fast again."""
    config_path = corridor_on_free_ports(
        tmp_path, "nearest", max_rtt=f"{MAX_RTT_S}s", prepare_timeout=f"{PREPARE_TIMEOUT_S}s"
    )
    config = load_config(config_path)
    eastings = [0, *DITHER, *CROSSINGS]
    plan = TestbedPlan(
        config=config,
        from_file=True,
        mission_file=Path(__file__).parent / "missions" / "back_and_forth.py",
        mission_args=(f"eastings={','.join(map(str, eastings))}",),
        resolution="160x120",
    )
    started = time.monotonic()
    async with LocalTestbed(plan, tmp_path / "w") as testbed:
        snapshot = await testbed.run_mission(240)
        await a_slow_link_is_measured_and_avoided(testbed, config.drone_link.latency)
    targets = [(0.0, float(east)) for east in eastings]
    report = build_report(config, snapshot, 0, time.monotonic() - started, [], targets=targets)
    assert report["completed"] and report["replicas_consistent"] and report["exactly_once"]
    assert report["side_effects"]["exactly_once"] is True, report["side_effects"]
    # The dither moved nothing; each crossing moved the master once.
    assert report["masters"] == [0, 1, 0, 1], report["handovers"]
    assert {h["trigger"] for h in report["handovers"]} == {"policy"}
    decisions = [(d.action, d.target) for d in snapshot.drone.policy_decisions]
    assert decisions.count((HANDOVER, 1)) == 2 and decisions.count((HANDOVER, 0)) == 1


async def a_slow_link_is_measured_and_avoided(testbed: LocalTestbed, latency_s: float) -> None:
    """The second half of the test above (its docstring)."""

    async def drone() -> drone_pb2.DroneStatus:
        return (await testbed.snapshot(audit=False)).drone

    def links(status: drone_pb2.DroneStatus) -> dict[int, drone_pb2.ControllerLink]:
        return {link.controller_id: link for link in status.links}

    async def measured_fast() -> drone_pb2.DroneStatus | None:
        status = await drone()
        return status if all(links(status)[c].answers >= 1 for c in (0, 1)) else None

    status = await eventually(measured_fast, "both links measured")
    assert status.master == 1, status.policy_decision
    for cid in (0, 1):
        link = links(status)[cid]
        assert link.healthy and link.standby and link.max_rtt_s == MAX_RTT_S, link
        # Twice the emulator's latency, and what the processes add (a loaded box).
        assert 2 * latency_s <= link.rtt_s < 2 * latency_s + 0.3, link
        assert 0 <= link.rtt_age_s <= link.rtt_stale_s, link
    testbed.reshape_link("link-drone-1", LinkSpec(latency=SLOW_LINK_S))

    async def left_for_0() -> drone_pb2.DroneStatus | None:
        status = await drone()
        return status if status.master == 0 else None

    status = await eventually(left_for_0, "the policy to leave master 1's slow link", 60)
    one = links(status)[1]
    assert not one.healthy and one.rtt_s >= 2 * SLOW_LINK_S, one
    assert one.problem.startswith("link too slow (round trip"), one.problem
    moved = status.handovers[-1]
    assert (moved.trigger, moved.old_master, moved.new_master) == (
        drone_pb2.HANDOVER_TRIGGER_POLICY,
        1,
        0,
    ), moved
    assert moved.reason.startswith("master 1 link too slow (round trip"), moved.reason
    # 1 is the nearer (166 m against 346 m) but slow: not chosen while it is.

    async def staying_with_0() -> drone_pb2.DroneStatus | None:
        status = await drone()
        decision = status.policy_decision
        return (
            status
            if (decision.master, decision.action) == (0, drone_pb2.POLICY_ACTION_STAY)
            else None
        )

    status = await eventually(staying_with_0, "the policy to stay with 0")
    assert not links(status)[1].healthy, links(status)[1]
    testbed.reshape_link("link-drone-1", LinkSpec(latency=latency_s))

    async def back_to_1() -> drone_pb2.DroneStatus | None:
        status = await drone()
        return status if status.master == 1 else None

    status = await eventually(back_to_1, "the policy to go back to 1, fast again", 60)
    assert links(status)[1].healthy and "1 nearer" in status.handovers[-1].reason
    log = [
        json.loads(line)
        for line in (testbed.workdir / "logs" / "drone.log").read_text().splitlines()
        if line.startswith("{")
    ]
    health = [
        (line["msg"], line.get("problem", "")[:13])
        for line in log
        if line.get("controller") == 1 and str(line.get("msg")).startswith("controller link")
    ]
    assert ("controller link unhealthy", "link too slow") in health, health
    assert health[-1][0] == "controller link healthy", health


def gapped_corridor(tmp_path: Path) -> Path:
    """Three stations 600 m apart with 400 m of range, on free ports: between 400 m
    and 800 m east only station 1 reaches the vehicle. A station flown into has 60 s
    of the mission (6 s of wall time) for its link to come up: the vehicle flies on
    meanwhile (a loaded CI box may take over 2 s, the default)."""
    document = yaml.safe_load(CORRIDOR.read_text())
    home = document["drone"]["home"]
    document["drone"]["address"] = f"127.0.0.1:{free_port()}"
    controllers = document["controllers"][:3]
    for k, controller in enumerate(controllers):
        controller["address"] = f"127.0.0.1:{free_port()}"
        controller["range_m"] = 400
        where = offset(Position(home["latitude_deg"], home["longitude_deg"]), 50.0, 600.0 * k)
        controller["location"] = {
            "latitude_deg": where.latitude_deg,
            "longitude_deg": where.longitude_deg,
        }
    document["controllers"], document["ring"] = controllers, [0, 1, 2]
    document["handover_policy"]["link_up"] = "60s"
    # The policy's hold is what these tests watch: the lost-link failsafe (30 mission-s
    # by default) would end a hold that waits for a restarted station.
    document.setdefault("safety", {})["lost_link"] = "10min"
    config = tmp_path / "gapped.yaml"
    config.write_text(yaml.safe_dump(document))
    return config


async def test_no_controller_usable_holds_the_vehicle_or_flies_on_into_a_range(
    tmp_path: Path,
) -> None:
    """The master is killed while the vehicle is in its range only, twice.

    First on a leg that ends in that range (to 700 m east): the drone holds the
    vehicle where it is and the mission waits; the master restarted, the
    vehicle flies on to where it was going. Then on the leg to 1,000 m, which
    leads into station 2's range (from 803 m): the vehicle flies on, no hold,
    and station 2 takes the mission over as soon as the vehicle reaches it. The
    mission ends with every effect once and the replicas agreeing."""
    config_path = gapped_corridor(tmp_path)
    config = load_config(config_path)
    home = Position(config.drone.home.latitude_deg, config.drone.home.longitude_deg)
    eastings = [0, 450, 700, 1000]
    plan = TestbedPlan(
        config=config,
        from_file=True,
        mission_file=Path(__file__).parent / "missions" / "back_and_forth.py",
        mission_args=(f"eastings={','.join(map(str, eastings))}",),
        resolution="160x120",
    )
    station_2 = RadioRange(
        config.controller(2).location.latitude_deg,  # type: ignore[union-attr]
        config.controller(2).location.longitude_deg,  # type: ignore[union-attr]
        400.0,
    )

    def east_m(position) -> float:  # type: ignore[no-untyped-def]
        return north_east_m(home, Position(position.latitude_deg, position.longitude_deg))[1]

    started = time.monotonic()
    async with LocalTestbed(plan, tmp_path / "w") as testbed:

        def master_1_past(east: float):  # type: ignore[no-untyped-def]
            async def check() -> bool:
                drone = (await testbed.snapshot(audit=False)).drone
                return drone.master == 1 and east_m(drone.position) > east

            return check

        await eventually(master_1_past(470), "master 1, past 470 m east", 120)
        await testbed.kill_controller(1)

        async def held() -> object:
            drone = (await testbed.snapshot(audit=False)).drone
            return drone if drone.holding else None

        holding = await eventually(held, "the drone to hold the vehicle", 30)
        where = east_m(holding.position)
        assert 470 < where < 700, where
        assert "no controller usable" in holding.policy_decision.reason
        assert "1 link down" in holding.policy_decision.reason
        assert "the leg leads into no station's range" in holding.policy_decision.reason

        # Held: the vehicle stops at once (the sim's next tick; its telemetry comes at
        # 20 Hz), then stays put while nobody can command it: 1 s of wall time, 10 s of
        # the mission's.
        def held_for(seconds: float, since: float):  # type: ignore[no-untyped-def]
            async def check() -> object:
                return await held() if time.monotonic() - since >= seconds else None

            return check

        settled = await eventually(held_for(0.5, time.monotonic()), "the vehicle held 0.5 s", 30)
        stop = east_m(settled.position)  # type: ignore[attr-defined]
        later = await eventually(held_for(1.0, time.monotonic()), "the vehicle held 1 s more", 30)
        assert abs(east_m(later.position) - stop) < 0.1  # type: ignore[attr-defined]

        # Station 1's link should be up (the vehicle is in its range) and is not: once it
        # has had its time to come up, the drone says a person should look. Stations 0
        # and 2, out of range as planned, are not waited for.
        async def link_1_needs_a_person() -> object:
            drone = (await testbed.snapshot(audit=False)).drone
            waits = {w.key: w.needs_person for w in drone.waits}
            return waits if waits.get("link 1") else None

        waits = await eventually(link_1_needs_a_person, "the drone to warn of link 1", 30)
        assert "link 0" not in waits and "link 2" not in waits, waits  # type: ignore[operator]
        await testbed.restart_controller(1)

        # On the leg to 1,000 m, in station 1's range only (2's begins at 803 m).
        await eventually(master_1_past(705), "master 1, past 705 m east", 120)
        await testbed.kill_controller(1)

        async def flying_on() -> object:
            drone = (await testbed.snapshot(audit=False)).drone
            decision = drone.policy_decision
            return drone if decision.action in (FLY_ON, HANDOVER) else None

        flying = await eventually(flying_on, "the drone to fly on", 30)
        assert not flying.holding  # type: ignore[attr-defined]
        # Killed in 1's range only, 2 out of range: a takeover cannot happen before
        # 803 m, and the vehicle was there with no master, flying on.
        assert east_m(flying.position) < 803 or flying.master == 2  # type: ignore[attr-defined]

        async def taken_over() -> object:
            drone = (await testbed.snapshot(audit=False)).drone
            return drone if drone.master == 2 else None

        await eventually(taken_over, "station 2 to take the mission over", 60)
        snapshot = await testbed.run_mission(180)
    targets = [(0.0, float(east)) for east in eastings]
    report = build_report(config, snapshot, 0, time.monotonic() - started, [], targets=targets)
    assert report["completed"] and report["replicas_consistent"] and report["exactly_once"]
    # The resume's goto is the drone's own, taken off before counting.
    assert report["side_effects"]["exactly_once"] is True, report["side_effects"]
    assert report["side_effects"]["vehicle_commands"]["goto"] == len(eastings) + 1
    assert report["side_effects"]["pictures_taken"] == len(eastings)
    # One hold (and its resume) for the first kill; none for the second.
    assert report["policy"]["holds"] == 1 and report["policy"]["resumes"] == 1
    assert report["policy"]["flown_on"] >= 1
    assert report["masters"] == [0, 1, 2]
    takeover = report["handovers"][-1]
    assert takeover["kind"] == "takeover" and takeover["to"] == 2, takeover
    # Taken over in 2's range, while the vehicle flew on (before the leg's end, 206 m
    # from 2): 2's link comes up within gRPC's reconnect backoff (at most 2 s of wall
    # time, 100 m at 5 m/s and 10x) of the vehicle coming into range.
    assert station_2.covers(*takeover["position"]), takeover
    assert station_2.distance_m(*takeover["position"]) > 210, takeover
    assert not snapshot.drone.holding
    decisions = [d.action for d in snapshot.drone.policy_decisions]
    assert HOLD not in decisions[decisions.index(drone_pb2.POLICY_ACTION_RESUME) :], decisions

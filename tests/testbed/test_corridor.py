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
from test_testbed import run_testbed

from baton.config import load_config
from baton.link.radio import RadioRange
from baton.testbed.local import LocalTestbed, TestbedPlan, free_port
from baton.testbed.report import build_report

EXAMPLE = Path(__file__).parents[2] / "examples" / "corridor.yaml"
MARGIN_M, LEAD_S, SPEED_M_S = 50.0, 10.0, 5.0


def corridor_on_free_ports(tmp_path: Path, policy: str) -> Path:
    document = yaml.safe_load(EXAMPLE.read_text())
    document["drone"]["address"] = f"127.0.0.1:{free_port()}"
    for controller in document["controllers"]:
        controller["address"] = f"127.0.0.1:{free_port()}"
    document["handover_policy"]["name"] = policy
    config = tmp_path / "corridor.yaml"
    config.write_text(yaml.safe_dump(document))
    return config


def link_lines(workdir: Path, cid: int) -> list[dict]:  # type: ignore[type-arg]
    log = workdir / "logs" / f"link-drone-{cid}.log"
    return [json.loads(line) for line in log.read_text().splitlines() if line.startswith("{")]


@pytest.mark.parametrize("policy", ["nearest", "predictive"])
def test_the_corridor_is_flown_with_the_masters_its_stations_reach(
    tmp_path: Path, policy: str
) -> None:
    config_path = corridor_on_free_ports(tmp_path, policy)
    config = load_config(config_path)
    report = run_testbed(
        tmp_path, "--config", str(config_path), "--mission", "corridor", "--spacing", "100"
    )
    assert report["completed"] and report["replicas_consistent"]
    assert report["exactly_once"] and report["side_effects"]["exactly_once"] is True
    assert report["side_effects"]["pictures_taken"] == report["mission"]["waypoints"] == 16
    assert report["handovers_planned"] == []
    assert report["policy"] == {"name": policy, "radio_range": True, "holds": 0, "resumes": 0}
    # One station after the other, each by the policy, each the paper's handover.
    assert report["masters"] == [0, 1, 2, 3]
    assert [(h["trigger"], h["kind"]) for h in report["handovers"]] == [
        ("policy", "cooperative")
    ] * 3
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
            # range would run out within the lead (10 s), with a tick of slack.
            assert old.range_m - LEAD_S * SPEED_M_S - 5 <= from_old <= old.range_m, h
            assert "range runs out in" in h["reason"]
        assert 0 < h["delay_s"] < 5, h
    # The radio was real: station 0 lost the vehicle beyond 500 m and cut the link;
    # station 3 was refused until the vehicle came within 500 m of it.
    workdir = tmp_path / "w"
    zero, three = link_lines(workdir, 0), link_lines(workdir, 3)
    assert any(line.get("msg") == "vehicle out of radio range" for line in zero)
    assert next(line for line in zero if line.get("msg") == "link stopped")["cut"] >= 1
    assert three[0].get("msg") == "vehicle out of radio range"  # from the start
    assert any(line.get("msg") == "vehicle in radio range" for line in three)
    assert next(line for line in three if line.get("msg") == "link stopped")["refused"] >= 1


# Across the boundary between stations 0 and 1 (east 250 m; `nearest` moves the
# master about 25 m past it): first dithering within 15 m of it, then three full
# crossings. Distinct targets: the exactly-once check counts a goto to one place twice.
DITHER = [240, 262, 242, 264, 244]
CROSSINGS = [340, 160, 342]


async def test_back_and_forth_across_a_boundary_moves_the_master_once_per_crossing(
    tmp_path: Path,
) -> None:
    config_path = corridor_on_free_ports(tmp_path, "nearest")
    config = load_config(config_path)
    eastings = [0, *DITHER, *CROSSINGS]
    plan = TestbedPlan(
        controllers=len(config.controllers),
        base_config=config,
        speedup=config.speedup,
        mission_file=Path(__file__).parent / "missions" / "back_and_forth.py",
        mission_args=(f"eastings={','.join(map(str, eastings))}",),
        resolution="160x120",
    )
    started = time.monotonic()
    async with LocalTestbed(plan, tmp_path / "w") as testbed:
        snapshot = await testbed.run_mission(240)
    targets = [(0.0, float(east)) for east in eastings]
    report = build_report(config, snapshot, 0, time.monotonic() - started, [], targets=targets)
    assert report["completed"] and report["replicas_consistent"] and report["exactly_once"]
    assert report["side_effects"]["exactly_once"] is True, report["side_effects"]
    # The dither moved nothing; each crossing moved the master once.
    assert report["masters"] == [0, 1, 0, 1], report["handovers"]
    assert {h["trigger"] for h in report["handovers"]} == {"policy"}
    decisions = [(d.action, d.target) for d in snapshot.drone.policy_decisions]
    assert decisions.count(("handover", 1)) == 2 and decisions.count(("handover", 0)) == 1

"""``baton testbed --fault`` and ``--restart-parts`` (issue 32, item 8): the testbed lives
through what baton lives through, across real processes."""

from __future__ import annotations

import json
import re
import subprocess
import time
from pathlib import Path

import pytest
from helpers.missions import FAST_LINK, log_events
from helpers.testbed_runs import baton, run_testbed
from waiting import eventually

from baton.config import merge
from baton.effects import read_effects
from baton.sdk import Position, distance_m
from baton.signing import write_key
from baton.sim_vehicle.kinematics import FlightParams, GeoPoint
from baton.sim_vehicle.server import SimVehicle
from baton.testbed.battery import BatteryResetError, reset_battery
from baton.testbed.faults import (
    Fault,
    FaultRecord,
    check_parts,
    fault_lines,
    fault_outcomes,
    parse_fault,
)
from baton.testbed.local import (
    VEHICLE_EFFECTS_FILE,
    LocalTestbed,
    MissionPlan,
    TestbedPlan,
    local_config,
)
from baton.testbed.report import build_report
from baton.testbed.run import add_faults
from baton.testbed.supervisor import PartNotReady
from baton.testbed.waits import LOUD

SMALL = ["--grid", "3", "--spacing", "20", "--altitude", "5", "--speedup", "20"]
HOME = GeoPoint(47.397742, 8.545594, 488.0)
BATTERY = "battery:sim-vehicle@reqnr=20,to=15%"


def test_faults_parse_with_their_time_and_duration() -> None:
    assert parse_fault("kill:controller-1@reqnr=130") == Fault(
        "kill:controller-1@reqnr=130", "kill", "controller-1", reqnr=130
    )
    assert parse_fault("stop:controller-0@reqnr=60,for=20s") == Fault(
        "stop:controller-0@reqnr=60,for=20s", "stop", "controller-0", reqnr=60, for_s=20.0
    )
    cut = parse_fault("cut:link-ring-1@t=30s,for=500ms")
    assert (cut.kind, cut.part, cut.at_s, cut.for_s) == ("cut", "link-ring-1", 30.0, 0.5)
    pause = parse_fault("pause:drone@reqnr=20,for=5s")
    assert (pause.kind, pause.part, pause.reqnr, pause.for_s) == ("pause", "drone", 20, 5.0)
    assert parse_fault("land-now:drone@t=30s").kind == "land-now"
    battery = parse_fault(BATTERY)
    assert (battery.kind, battery.part, battery.reqnr, battery.to_pct) == (
        "battery",
        "sim-vehicle",
        20,
        15.0,
    )
    assert battery.to_json()["to_pct"] == 15.0
    assert [parse_fault(f"battery:sim-vehicle@t=1s,to={to}").to_pct for to in ("0", "100%")] == [
        0.0,
        100.0,
    ]
    assert "to_pct" not in parse_fault("kill:drone@t=1s").to_json()


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("explode:controller-1@reqnr=3", "unknown fault 'explode', expected one of kill"),
        ("kill:controller-1", "no time: add @reqnr=N"),
        ("kill:ctl-1@reqnr=3", "unknown part 'ctl-1'"),
        ("cut:controller-1@reqnr=3", "cut is for a link emulator"),
        ("full:link-ring-0@reqnr=3", "full is for a controller's log file (controller-N) or"),
        ("kill:controller-1@reqnr=x", "reqnr='x' is not a request number >= 1"),
        ("kill:controller-1@reqnr=3,t=4s", "give the time once"),
        ("stop:drone@t=3s,for=soon", "expected a duration like '20ms'"),
        ("stop:drone@t=3s,for=0s", "must be longer than 0"),
        (
            "stop:drone@t=3s,when=now",
            "'when=now' is not reqnr=N, t=DURATION, for=DURATION or to=PERCENT",
        ),
        ("pause:controller-0@reqnr=3", "pause is the operator's command to the drone"),
        ("abort:drone@reqnr=3,for=2s", "abort ends the mission: it takes no for="),
        ("battery:drone@reqnr=3,to=15%", "battery is the vehicle's (sim-vehicle), not drone"),
        ("battery:sim-vehicle@reqnr=3", "battery needs the percentage it drops to: add to="),
        ("battery:sim-vehicle@reqnr=3,to=150%", "to='150%' is not a percentage from 0 to 100"),
        ("battery:sim-vehicle@reqnr=3,to=-1", "to='-1' is not a percentage from 0 to 100"),
        ("battery:sim-vehicle@reqnr=3,to=nan", "to='nan' is not a percentage from 0 to 100"),
        ("battery:sim-vehicle@reqnr=3,to=half", "to='half' is not a percentage from 0 to 100"),
        ("battery:sim-vehicle@t=3s,to=15%,for=5s", "a battery is not recharged in flight"),
        ("kill:controller-1@reqnr=3,to=15%", "to= is the battery's percentage"),
        ("battery:sitl@reqnr=3,to=15%", "battery is not supported on sitl: "),
    ],
)
def test_a_bad_fault_names_the_option_and_the_fix(text: str, why: str) -> None:
    with pytest.raises(ValueError) as caught:
        parse_fault(text)
    message = str(caught.value)
    assert message.startswith(f"--fault {text!r}: ") and why in message, message
    assert "e.g. kill:controller-1@reqnr=130" in message


def test_a_failsafe_is_listed_under_the_fault_it_followed() -> None:
    """The failsafe the vehicle is in at the end goes with the last fault fired before the
    drone entered it, as the handovers do; the summary line says it."""
    first, second = (FaultRecord(parse_fault(text)) for text in ("pause:drone@t=1s", BATTERY))
    first.fired_at_s, first.fired_wall = 1.0, 1000.0
    second.fired_at_s, second.fired_wall = 2.0, 1001.0
    failsafe = {"cause": "battery", "action": "rtl", "since": 1001.25, "reason": "battery 15 %"}
    report = {"drone": {"failsafe": failsafe}, "handovers": []}
    entries = fault_outcomes([first, second], report, "NOT COMPLETED")
    assert entries[0]["failsafe_after"] is None
    assert entries[1]["failsafe_after"] == {
        "cause": "battery",
        "action": "rtl",
        "reason": "battery 15 %",
        "entered_after_s": 0.25,
    }
    line = fault_lines({"faults": entries})[1]
    assert line.startswith(f"fault {BATTERY}: at 2.0 s, "), line
    assert "; no handover; failsafe battery (rtl) 0.2 s later; mission NOT COMPLETED" in line


def test_a_fault_on_a_part_the_testbed_lacks_is_refused_before_anything_starts() -> None:
    with pytest.raises(ValueError, match="this testbed has no controller-7; its parts: "):
        check_parts([parse_fault("kill:controller-7@reqnr=3")], ["drone", "controller-0"])
    result = subprocess.run(
        baton("testbed", "--no-links", "--fault", "cut:link-ring-0@reqnr=3"),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert "--fault 'cut:link-ring-0@reqnr=3': this testbed has no link-ring-0" in result.stderr


async def test_a_link_cut_from_the_start_must_be_one_of_the_testbed_s(tmp_path: Path) -> None:
    """``TestbedPlan.links_cut`` names link emulators: anything else is refused before a
    part starts, naming the links there are."""
    for plan, links in (
        (TestbedPlan(links_cut=("link-ring-9",)), "link-ring-0, link-drone-0, "),
        (TestbedPlan(links_cut=("link-ring-0",), emulate_links=False), "none (emulate_links"),
    ):
        name = plan.links_cut[0]
        with pytest.raises(PartNotReady) as caught:
            await LocalTestbed(plan, tmp_path).start()
        expected = f"TestbedPlan.links_cut: {name} is no link emulator of this testbed; "
        assert str(caught.value).startswith(f"{expected}its links: {links}"), caught.value


# On demand (~24 s; CI's 25 minutes): in CI the kill fault is test_stop_cut_and_a_kill_...'s,
# and tests/controller/test_takeover.py takes over killed masters.
@pytest.mark.slow
def test_the_master_killed_by_a_fault_is_taken_over_and_the_mission_completes_once(
    tmp_path: Path,
) -> None:
    """kill -9 of the master mid-mission from the command line: the run goes on, the
    drone takes the master over, and the report lists the fault with the takeover
    and the mission's verdict; exactly once by the drone's audit and by the vehicle's
    and the camera's own counts."""
    report = run_testbed(
        tmp_path, *SMALL, "--no-handovers", "--fault", "kill:controller-0@reqnr=20"
    )
    [fault] = report["faults"]
    assert fault["fault"] == "kill:controller-0@reqnr=20" and fault["fired"]
    assert fault["fired_at_reqnr"] >= 20 and fault["master_before"] == 0
    [takeover] = fault["handovers_after"]
    assert (takeover["from"], takeover["to"], takeover["kind"]) == (0, 1, "takeover")
    assert fault["mission_verdict"].startswith("COMPLETED, exactly once: True")
    [death] = report["parts_died"]
    assert death["part"] == "controller-0" and death["cause"] == fault["fault"]
    assert report["completed"] and report["exactly_once"] and report["replicas_consistent"]
    assert report["side_effects"]["exactly_once"] is True
    effects = report["side_effects"]["vehicle_commands"]
    assert effects["arm"] == effects["takeoff"] == effects["land"] == 1
    assert report["drone"]["master"] == 1
    assert "fault kill:controller-0@reqnr=20: killed controller-0 (kill -9)" in report["stdout"]
    assert "takeover 0 -> 1" in report["stdout"]


def test_stop_cut_and_a_kill_restarted_by_restart_parts(tmp_path: Path) -> None:
    """A frozen replica thawed, a ring link cut and restored, the master killed with
    --restart-parts (back with its log file), and the operator's pause resumed a second
    later (the drone's own record says both): every fault ends, the mission completes
    once, and every controller, the restarted one too, ends with the same replies. The
    cut ring link is a stall that needs a person: the progress line and the report say
    so loudly."""
    report = run_testbed(
        tmp_path,
        *SMALL,
        "--no-handovers",
        "--restart-parts",
        "--fault",
        "stop:controller-2@reqnr=10,for=2s",
        "--fault",
        "cut:link-ring-2@reqnr=60,for=6s",
        "--fault",
        "kill:controller-0@reqnr=40",
        "--fault",
        "pause:drone@reqnr=20,for=1s",
    )
    stop, cut, kill, pause = report["faults"]
    assert all(f["fired"] and not f["problem"] for f in (stop, cut, kill, pause))
    assert pause["ended_at_s"] >= pause["fired_at_s"] + 1.0
    commands = report["drone"]["operator_commands"]
    assert [c["command"] for c in commands] == ["pause", "resume"], commands
    assert stop["ended_at_s"] >= stop["fired_at_s"] + 2.0
    assert cut["ended_at_s"] >= cut["fired_at_s"] + 6.0
    # Controller 1 (ring 0 -> 1 -> 2, master since the kill) lost its successor for
    # 6 s: its stream down, then the ring routed around 2; each, held 3 s, is shown
    # as needing a person.
    stalls = [w for w in report["waits"]["needs_person"] if w["part"] == "c1"]
    assert {"ring", "routed"} & {w["key"] for w in stalls}, report["waits"]
    assert f"{LOUD}: c1: ring " in report["stdout"]
    [death] = report["parts_died"]
    assert death["part"] == "controller-0" and death["restarted_at_s"] is not None
    assert [c["id"] for c in report["controllers"]] == [0, 1, 2]
    assert report["completed"] and report["exactly_once"] and report["replicas_consistent"]
    assert report["side_effects"]["exactly_once"] is True


def test_the_drone_killed_is_restarted_with_its_state_and_the_mission_completes_once(
    tmp_path: Path,
) -> None:
    """--restart-parts: the drone service back with its state file (same command line);
    the controllers re-send what was in flight and nothing runs twice, by the vehicle's
    own count. The autopilot's own GCS failsafe is given 10 min: a restart on two loaded
    cores took longer than its 5 s wall floor, and the vehicle landed meanwhile (which
    the restarted drone rightly reports as the autopilot's failsafe)."""
    report = run_testbed(
        tmp_path,
        *SMALL,
        "--no-handovers",
        "--restart-parts",
        "--autopilot-gcs-timeout",
        "10min",
        "--fault",
        "kill:drone@reqnr=20",
    )
    [death] = report["parts_died"]
    assert death["part"] == "drone" and death["restarted_at_s"] > death["at_s"]
    assert report["completed"] and report["exactly_once"] and report["replicas_consistent"]
    assert report["side_effects"]["exactly_once"] is True
    assert len(report["files"]["tlogs"]) == 2  # one a drone process


def test_without_restart_parts_a_dead_drone_ends_the_run_with_a_report(tmp_path: Path) -> None:
    """The mission cannot go on without the drone: the run stops, says why, and still
    writes the report with the fault in it; exit 1."""
    report_path = tmp_path / "report.json"
    result = subprocess.run(
        baton(
            "testbed",
            *SMALL,
            "--no-handovers",
            "--fault",
            "kill:drone@reqnr=20",
            "--report",
            str(report_path),
            "--workdir",
            str(tmp_path / "w"),
        ),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 1, result.stdout + result.stderr
    assert "run ended early: drone died and is not restarted" in result.stdout
    report = json.loads(report_path.read_text())
    assert report["ended_early"].startswith("drone died and is not restarted")
    assert report["faults"][0]["fired"] and not report["completed"]


def log_lines(path: Path) -> list[dict]:  # type: ignore[type-arg]
    """A part's structured log lines."""
    return [json.loads(line) for line in path.read_text().splitlines() if line.startswith("{")]


def test_a_controller_whose_disk_fills_says_so_at_once_and_the_mission_completes_once(
    tmp_path: Path,
) -> None:
    """``full:controller-1``: controller 1's log file may grow no more (RLIMIT_FSIZE, its
    writes fail with EFBIG as on a full disk; a log file only grows, so its next message
    fails). Its first failed write is an ERROR in its log within a second (measured:
    ``said_after_s``), the progress line and the report say the file is not durable and
    up to which log message it is whole, and ``baton replay`` of its file names what is
    missing. The mission completes exactly once by the vehicle's own count, every
    replica consistent (controller 1 replicates from memory). (The drone's side is
    ``tests/drone/test_drone_store.py``: its file reuses its own free pages, so when a
    full disk stops it depends on the run.)"""
    report = run_testbed(
        tmp_path, *SMALL, "--no-handovers", "--fault", "full:controller-1@reqnr=40"
    )
    [fault] = report["faults"]
    assert fault["fired"] and fault["mission_verdict"].startswith("COMPLETED, exactly once: True")
    assert report["side_effects"]["exactly_once"] and report["replicas_consistent"]
    c1 = next(c for c in report["controllers"] if c["id"] == 1)
    log_file = c1["log_file"]
    assert not log_file["durable"] and "RLIMIT_FSIZE" in log_file["error"]
    whole = log_file["whole_up_to_lognr"]
    assert whole < c1["lognr"], (whole, c1["lognr"])
    assert f"c1 log file NOT DURABLE (whole up to {whole})" in report["stdout"]
    logs = tmp_path / "w" / "logs"
    [error] = [
        line for line in log_lines(logs / "controller-1.log") if line.get("level") == "error"
    ]
    assert error["msg"].startswith(f"cannot write {tmp_path / 'w' / 'controller-1-log.sqlite'}")
    assert error["said_after_s"] < 1.0, error
    mission = report["files"]["mission"]
    replay = subprocess.run(
        baton(
            "replay",
            report["files"]["controller_logs"]["1"],
            "--mission",
            mission["file"],
            *(arg for value in mission["args"] for arg in ("--mission-arg", value)),
        ),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert replay.returncode == 1, replay.stdout + replay.stderr
    held = f"log messages 1-{whole}" if whole else "no log message"
    # The file says where it stops being whole if the full disk still took that one small
    # write (the mark); else replay names where the file ends, at that same message.
    marked = f"the file holds only {held} whole" in replay.stdout
    ends = f"in log message {whole}: a file saved before the mission ended" in replay.stdout
    assert marked or ends, replay.stdout
    assert "Traceback" not in replay.stdout + replay.stderr


def test_the_battery_fault_signs_its_command_with_the_vehicle_s_key(tmp_path: Path) -> None:
    """The battery fault's way into the vehicle (testbed/battery.py), against one that
    holds a MAVLink key: signed with the key, the reset is taken and the vehicle reads the
    percentage back; unsigned, or signed with another key, the vehicle ignores it, the
    error says why, and the battery stays as it was."""
    key = write_key(tmp_path / "vehicle.key")
    other = write_key(tmp_path / "other.key")
    with SimVehicle(HOME, params=FlightParams(warmup_s=0.0), signing_key=key) as vehicle:
        assert reset_battery(vehicle.url, 15.0, key) == 15
        assert vehicle.state().battery_pct == 15.0
        with pytest.raises(BatteryResetError, match=r"ignores unsigned frames: drone\.mavlink_key"):
            reset_battery(vehicle.url, 40.0, None, timeout_s=1.0)
        with pytest.raises(BatteryResetError, match="not signed with the testbed's MAVLink key"):
            reset_battery(vehicle.url, 40.0, other, timeout_s=1.0)
        assert vehicle.state().battery_pct == 15.0 and vehicle.refused_frames > 0
        with pytest.raises(ValueError, match="is not from 0 to 100 %"):
            reset_battery(vehicle.url, 101.0, key)
        with pytest.raises(ValueError, match="expected udpout://HOST:PORT"):
            reset_battery("tcp:127.0.0.1:5760", 15.0, key)


# 8 legs of 100 m at 5 m/s: 160 mission seconds, 8 s of wall time at 20x. The fault fires
# on the first leg, and the drone reads the battery once a second: the vehicle still flies
# a leg when it does, on a loaded machine too.
BATTERY_GRID = MissionPlan(grid=3, spacing_m=100.0, altitude_m=5.0, speed_m_s=5.0, poll_s=1.0)
RESERVE_PCT = 20.0


def returning(effect: dict[str, object]) -> bool:
    """A return the vehicle acted on: MAV_CMD_NAV_RETURN_TO_LAUNCH, or PX4's mode."""
    return effect["effect"] == "return_to_launch" or effect.get("mode") == "RETURN_TO_LAUNCH"


async def test_a_battery_below_the_reserve_returns_the_vehicle_and_ends_the_mission(
    tmp_path: Path,
) -> None:
    """``battery:sim-vehicle@reqnr=20,to=15%`` on a signed link (drone.mavlink_key): the
    testbed sets the vehicle's battery through the vehicle's own MAVLink port, the drone
    reads it in the vehicle's telemetry below the mission's 20 % reserve and commands the
    return. The vehicle's own records say so: its effects file has the reset, then one
    return and no flight command after it, and its log has it landed at home. Every
    controller's program ends with the failsafe's error, and the report lists the fault
    with when it fired, what the vehicle read and the failsafe it led to."""
    key = tmp_path / "mavlink.key"
    write_key(key)
    config = local_config(
        2,
        flush_limit=0,
        speedup=20.0,
        controller_link=FAST_LINK,
        drone_link=FAST_LINK,
        safety={"battery_reserve": RESERVE_PCT, "battery_action": "rtl"},
    )
    config = merge(config, [("drone.mavlink_key", "drone.mavlink_key", str(key))])
    fault = parse_fault(BATTERY)
    plan = TestbedPlan(config=config, mission=BATTERY_GRID, faults=(fault,))
    started = time.monotonic()
    async with LocalTestbed(plan, tmp_path) as testbed:
        assert testbed.config is not None
        snapshot = await testbed.run_mission(120)

        def landed_after_the_return() -> dict[str, object] | None:
            states = [
                e for e in log_events(tmp_path, "sim-vehicle") if e.get("msg") == "vehicle state"
            ]
            phases = [state["phase"] for state in states]
            last = states[-1]
            done = "return" in phases and last["phase"] == "on_ground" and not last["armed"]
            return last if done else None

        landed = await eventually(landed_after_the_return, "the vehicle landed after its return")
        report = build_report(
            testbed.config,
            snapshot,
            BATTERY_GRID.grid,
            time.monotonic() - started,
            [],
            BATTERY_GRID.spacing_m,
        )
        add_faults(report, testbed)
    where = Position(float(landed["lat"]), float(landed["lon"]))  # type: ignore[arg-type]
    assert distance_m(where, Position(HOME.latitude_deg, HOME.longitude_deg)) < 1.0, landed
    effects = read_effects(tmp_path / VEHICLE_EFFECTS_FILE)
    [reset] = [e for e in effects if e["effect"] == "battery_reset"]
    assert reset["percent"] == 15.0 and reset["was_percent"] > RESERVE_PCT, reset
    [back] = [e for e in effects if returning(e)]
    assert back["seq"] > reset["seq"] and back["seq"] == effects[-1]["seq"], effects
    errors = [c.mission_error for c in snapshot.controllers.values()]
    assert len(errors) == 2 and all(
        "in failsafe (battery: battery " in e and f"below the reserve of {RESERVE_PCT:g} %" in e
        for e in errors
    ), errors
    assert (
        report["setup"]["vehicle"]["signing"] and report["setup"]["vehicle"]["refused_frames"] == 0
    )
    assert "MAVLink frames refused" not in (tmp_path / "logs" / "sim-vehicle.log").read_text()
    [entry] = report["faults"]
    assert entry["fired"] and not entry["problem"] and entry["fired_at_reqnr"] >= 20, entry
    # What the vehicle read back at once: 15 %, less what it drained meanwhile (1.4 % a
    # second of wall time at 20x).
    reads = re.search(r"the vehicle reads (\d+) %", entry["applied"])
    assert reads is not None and 10 <= int(reads[1]) <= 15, entry["applied"]
    failsafe = entry["failsafe_after"]
    assert (failsafe["cause"], failsafe["action"]) == ("battery", "rtl"), entry
    # The drone booked the failsafe before it commanded the return the vehicle counted.
    assert failsafe["entered_after_s"] >= 0 and report["drone"]["failsafe"]["since"] <= back["time"]
    assert entry["mission_verdict"].startswith("NOT COMPLETED"), entry
    [line] = [text for text in fault_lines(report) if text.startswith(f"fault {fault.text}: ")]
    assert "failsafe battery (rtl)" in line and "mission NOT COMPLETED" in line, line
    print(f"battery fault to the drone's failsafe: {failsafe['entered_after_s']:.2f} s wall")

"""``baton replay``'s core: a saved log against a mission program, every way they part."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
from pathlib import Path

import grpc
import pytest
from google.protobuf.message import Message
from helpers.storage import failing_writes

from baton.controller.history import LogHistory, NotALogFile, read_log
from baton.digest import request_digest
from baton.replay.replayer import InconsistentLog, replay_log
from baton.v1 import drone_api_pb2 as api
from baton.v1 import ring_pb2

POSITION = api.GetPositionReply(
    position=api.Position(latitude_deg=47.0, longitude_deg=8.0, relative_altitude_m=10.0)
)
# (method, request, reply or a failure status)
Call = tuple[str, Message, Message | tuple[grpc.StatusCode, str]]

# What the mission below asks, in order, with the replies the drone gave.
CALLS: list[Call] = [
    ("/baton.v1.Mobility/Arm", api.ArmRequest(), api.ArmReply()),
    ("/baton.v1.Mobility/Takeoff", api.TakeoffRequest(altitude_m=10.0), api.TakeoffReply()),
    ("/baton.v1.Mobility/GetPosition", api.GetPositionRequest(), POSITION),
    ("/baton.v1.Clock/Sleep", api.SleepRequest(seconds=1.0), api.SleepReply()),
    (
        "/baton.v1.Mobility/Goto",
        api.GotoRequest(latitude_deg=47.0, longitude_deg=8.001, relative_altitude_m=10.0),
        (grpc.StatusCode.ABORTED, "the autopilot refused the goto"),
    ),
    ("/baton.v1.Mobility/Land", api.LandRequest(), api.LandReply()),
]

MISSION = """
from baton.sdk import DroneCallError, Position


def mission(drone, altitude_m=10.0, east_deg=0.001):
    drone.mobility.arm()
    drone.mobility.takeoff(altitude_m)
    here = drone.mobility.position()
    drone.clock.sleep(1)
    try:
        east = Position(here.latitude_deg, here.longitude_deg + east_deg, 0, 0)
        drone.mobility.goto(east, altitude_m)
    except DroneCallError as exc:
        print("goto refused:", exc.code.name)
    drone.mobility.land()
"""


def write_log(path: Path, calls: list[Call], per_message: int = 2) -> Path:
    """A controller's log file of ``calls``, ``per_message`` entries to a message."""
    entries = []
    for reqnr, (method, request, outcome) in enumerate(calls, start=1):
        payload = request.SerializeToString()
        entry = ring_pb2.LogEntry(
            reqnr=reqnr,
            method=method,
            request=payload,
            request_digest=request_digest(method, payload),
        )
        if isinstance(outcome, tuple):
            entry.status_code, entry.status_message = outcome[0].value[0], outcome[1]
        else:
            entry.reply = outcome.SerializeToString()
        entries.append(entry)
    history = LogHistory(path)
    for k in range(0, len(entries), per_message):
        history.add(
            ring_pb2.LogMessage(
                lognr=k // per_message + 1,
                origin=0,
                epoch=1,
                entries=entries[k : k + per_message],
                after_reqnr=k,
            )
        )
    history.close()
    return path


@pytest.fixture
def mission_file(tmp_path: Path) -> Path:
    path = tmp_path / "mission.py"
    path.write_text(MISSION)
    return path


def edited(tmp_path: Path, old: str, new: str) -> Path:
    path = tmp_path / "edited.py"
    source = MISSION.replace(old, new)
    assert source != MISSION
    path.write_text(source)
    return path


def test_the_programs_own_log_replays_clean_failures_included(
    tmp_path: Path, mission_file: Path
) -> None:
    log = write_log(tmp_path / "log.sqlite", CALLS)
    outcome = replay_log(log, str(mission_file), [])
    assert outcome.clean, outcome.divergence
    assert outcome.replayed == outcome.logged == len(CALLS)
    # The logged failure reached the program as the SDK's DroneCallError.
    assert "goto refused: ABORTED" in outcome.output


def test_a_changed_field_is_shown_on_both_sides_with_its_request_number(
    tmp_path: Path, mission_file: Path
) -> None:
    log = write_log(tmp_path / "log.sqlite", CALLS)
    outcome = replay_log(log, str(mission_file), ["altitude_m=12"])
    divergence = outcome.divergence
    assert divergence is not None and outcome.replayed == 1
    assert divergence.reqnr == 2
    assert divergence.logged == "Mobility.Takeoff {altitude_m: 10.0}"
    assert divergence.program == "Mobility.Takeoff {altitude_m: 12.0}"
    assert divergence.fields == ("altitude_m",)


def test_another_method_past_the_end_and_an_early_end_diverge(
    tmp_path: Path, mission_file: Path
) -> None:
    log = write_log(tmp_path / "log.sqlite", CALLS)
    other = replay_log(
        log, str(edited(tmp_path, "drone.clock.sleep(1)", "drone.mobility.hold()")), []
    )
    assert other.divergence is not None and other.divergence.reqnr == 4
    assert other.divergence.logged == "Clock.Sleep {seconds: 1.0}"
    assert other.divergence.program == "Mobility.Hold {}"
    longer = replay_log(
        log,
        str(edited(tmp_path, "drone.mobility.land()", "drone.mobility.land(); drone.clock.now()")),
        [],
    )
    assert longer.divergence is not None and longer.divergence.reqnr == 7
    assert (
        "more than the log holds (it ends at request 6, in log message 3" in longer.divergence.why
    )
    assert longer.divergence.program == "Clock.Now {}" and not longer.divergence.logged
    shorter = replay_log(log, str(edited(tmp_path, "drone.mobility.land()", "pass")), [])
    assert shorter.divergence is not None and shorter.divergence.reqnr == 6
    assert "returned after request 5; the log goes on to request 6" in shorter.divergence.why
    assert shorter.divergence.logged == "Mobility.Land {}"


def test_a_mission_that_catches_everything_still_stops_at_the_divergence(
    tmp_path: Path, mission_file: Path
) -> None:
    log = write_log(tmp_path / "log.sqlite", CALLS)
    catching = edited(
        tmp_path,
        "    drone.mobility.takeoff(altitude_m)\n",
        "    try:\n        drone.mobility.takeoff(altitude_m + 1)\n"
        "    except Exception:\n        print('swallowed')\n",
    )
    outcome = replay_log(log, str(catching), [])
    assert outcome.divergence is not None and outcome.divergence.reqnr == 2
    assert "swallowed" not in outcome.output


def test_a_log_with_a_gap_or_not_a_log_is_refused_by_name(tmp_path: Path) -> None:
    log = write_log(tmp_path / "gap.sqlite", CALLS, per_message=1)
    with sqlite3.connect(log) as db:
        db.execute("DELETE FROM messages WHERE lognr IN (3, 4)")
    with pytest.raises(InconsistentLog, match="lacks log messages 3-4"):
        replay_log(log, str(tmp_path / "unused.py"), [])
    other = tmp_path / "other.sqlite"
    with sqlite3.connect(other) as db:
        db.execute("CREATE TABLE state (k TEXT)")
    with pytest.raises(NotALogFile, match="not a controller log file"):
        read_log(other)
    text = tmp_path / "notes.sqlite"
    text.write_text("not a database at all, just some text that is long enough" * 20)
    with pytest.raises(NotALogFile, match=str(text)):
        read_log(text)


def baton_replay(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "baton.cli", "replay", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_the_cli_replays_a_folder_and_exits_by_the_worst_verdict(
    tmp_path: Path, mission_file: Path
) -> None:
    logs = tmp_path / "logs"
    write_log(logs / "a.sqlite", CALLS)
    write_log(logs / "nested" / "b.sqlite", CALLS, per_message=4)
    clean = baton_replay(str(logs), "--mission", str(mission_file))
    assert clean.returncode == 0, clean.stdout + clean.stderr
    assert clean.stdout.count("6 requests replayed clean") == 2
    assert clean.stdout.splitlines()[-1] == "2 clean, 0 diverged, 0 unreadable"

    diverged = baton_replay(
        str(logs), "--mission", str(mission_file), "--mission-arg", "east_deg=0.002"
    )
    assert diverged.returncode == 1
    assert "diverged at request 5" in diverged.stdout
    assert "the log holds:    Mobility.Goto {latitude_deg: 47.0 longitude_deg: 8.001" in (
        diverged.stdout
    )
    assert "fields that differ: longitude_deg" in diverged.stdout

    (logs / "junk.sqlite").write_text("junk" * 100)
    unreadable = baton_replay(str(logs), "--mission", str(mission_file))
    assert unreadable.returncode == 2
    assert "2 clean, 0 diverged, 1 unreadable" in unreadable.stdout

    for args, expected in [
        ((str(tmp_path / "nowhere"), "--mission", str(mission_file)), "no such file or folder"),
        ((str(logs), "--mission", str(tmp_path / "none.py")), "no such file"),
        ((str(logs / "a.sqlite"), "--mission", str(mission_file), "--mission-arg", "x=1"), "x=1"),
    ]:
        bad = baton_replay(*args)
        assert bad.returncode == 2 and expected in bad.stderr, bad.stderr


def test_the_replay_bench_writes_a_log_that_replays_clean_and_measures_it(tmp_path: Path) -> None:
    from baton.bench.offline_replay import run_replay_bench

    result = run_replay_bench(tmp_path, calls=501, passes=1)
    assert result["calls"] == 501 and len(result["seconds"]) == 1
    assert result["calls_per_s"] > 0 and Path(result["log"]).is_file()
    assert len(read_log(Path(result["log"]))) == 6  # 100 entries a message
    assert (tmp_path / "replay.json").is_file()


ASYNC_MISSION = """
from baton.sdk import DroneCallError, Position


async def mission(drone, altitude_m=10.0, east_deg=0.001):
    await drone.mobility.arm()
    await drone.mobility.takeoff(altitude_m)
    here = await drone.mobility.position()
    await drone.clock.sleep(1)
    try:
        east = Position(here.latitude_deg, here.longitude_deg + east_deg, 0, 0)
        await drone.mobility.goto(east, altitude_m)
    except DroneCallError as exc:
        print("goto refused:", exc.code.name)
    await drone.mobility.land()
"""


def test_an_async_mission_replays_the_same_log_and_diverges_where_it_differs(
    tmp_path: Path,
) -> None:
    """``async def mission`` (baton.sdk.aio) replays as the blocking one does."""
    log = write_log(tmp_path / "log.sqlite", CALLS)
    program = tmp_path / "async_mission.py"
    program.write_text(ASYNC_MISSION)
    outcome = replay_log(log, str(program), [])
    assert outcome.clean, outcome.divergence
    assert outcome.replayed == outcome.logged == len(CALLS)
    assert "goto refused: ABORTED" in outcome.output  # the logged failure, as DroneCallError
    program.write_text(ASYNC_MISSION.replace("takeoff(altitude_m)", "takeoff(altitude_m + 1)"))
    diverged = replay_log(log, str(program), [])
    assert diverged.divergence is not None and diverged.divergence.reqnr == 2
    assert diverged.divergence.fields == ("altitude_m",)


def test_a_file_cut_by_a_failed_write_or_saved_early_names_what_it_lacks(
    tmp_path: Path, mission_file: Path
) -> None:
    """A controller whose file failed a write marked it whole up to log message 3 (the
    storage layer fails its fourth message on): the replay stops there and says what is
    missing and where to look. A file without the mark that ends early says it ends
    before the program does. A file cut in its bytes is named damaged, never a
    traceback."""
    messages = read_log(write_log(tmp_path / "whole.sqlite", CALLS, per_message=1))
    cut = tmp_path / "cut.sqlite"
    history = LogHistory(cut)
    disk = failing_writes(history)
    for message in messages:
        disk.failing = "INTO messages" if message.lognr > 3 else None
        history.add(message)
    history.close()
    outcome = replay_log(cut, str(mission_file), [])
    assert outcome.divergence is not None and outcome.divergence.reqnr == 4
    assert outcome.divergence.why.startswith(
        "the file holds only log messages 1-3 whole (it ends at request 3, in log message 3): "
        "its controller could not write to it after that"
    ), outcome.divergence.why
    assert "replay another controller's log file" in outcome.divergence.why

    early = write_log(tmp_path / "early.sqlite", CALLS, per_message=1)
    with sqlite3.connect(early) as db:
        db.execute("DELETE FROM messages WHERE lognr > 3")
    outcome = replay_log(early, str(mission_file), [])
    assert outcome.divergence is not None and outcome.divergence.why == (
        "the program asks for more than the log holds (it ends at request 3, in log message "
        "3: a file saved before the mission ended, or of a controller still catching up)"
    )

    damaged = tmp_path / "damaged.sqlite"
    whole = (tmp_path / "whole.sqlite").read_bytes()
    damaged.write_bytes(whole[: len(whole) // 3])
    result = baton_replay(str(damaged), "--mission", str(mission_file))
    assert result.returncode == 2, result.stdout + result.stderr
    assert f"ERROR {damaged}: {damaged}: a damaged file" in result.stdout, result.stdout
    assert "Traceback" not in result.stdout + result.stderr

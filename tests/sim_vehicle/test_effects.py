"""The sim vehicle counts what it acted on in its effects file, and a retransmission once.

The effects file is the testbed's witness of exactly once that does not rest
on the drone's own audit (docs/design.md, "Counting side effects where they
happen"). Seen by a pymavlink ground station over real UDP, as in
test_mavlink.py: a command sent again because its ACK did not come must not
count twice, and a command genuinely sent twice must
(``retransmissions.py`` has the rule).
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.mobility import connected_mobility
from waiting import eventually

from baton.effects import EffectsFile, read_effects
from baton.sim_vehicle.kinematics import FlightParams, GeoPoint
from baton.sim_vehicle.retransmissions import CommandKey, Retransmissions
from baton.sim_vehicle.server import MAV_CMD_BATTERY_RESET, SimVehicle
from baton.v1 import drone_api_pb2 as api

from .ground_station import UNSET, GroundStation, mavlink
from .sim_process import start_sim

HOME = (47.397742, 8.545594, 488.0)
ARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
TAKEOFF = mavlink.MAV_CMD_NAV_TAKEOFF
REPOSITION = mavlink.MAV_CMD_DO_REPOSITION
SPEED = mavlink.MAV_CMD_DO_CHANGE_SPEED
ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
BATTERY_RESET = MAV_CMD_BATTERY_RESET  # ardupilotmega.xml's, not in common.xml
REQUEST_MESSAGE = mavlink.MAV_CMD_REQUEST_MESSAGE


@pytest.fixture
def vehicle(tmp_path: Path) -> Iterator[SimVehicle]:
    """A warmed-up vehicle that counts into ``tmp_path/effects.jsonl``."""
    effects = EffectsFile(tmp_path / "effects.jsonl")
    home = GeoPoint(*HOME)
    with SimVehicle(
        home, speedup=10.0, params=FlightParams(warmup_s=0.0), effects=effects
    ) as vehicle:
        yield vehicle


def counted(vehicle: SimVehicle) -> list[dict[str, Any]]:
    """What the vehicle's effects file says it acted on."""
    assert vehicle.effects.path is not None
    return read_effects(vehicle.effects.path)


def test_a_command_long_retransmitted_with_a_confirmation_is_counted_once(
    vehicle: SimVehicle,
) -> None:
    with GroundStation(vehicle.port) as gcs:
        gcs.say_hello()
        assert gcs.command(ARM, 1, confirmation=0).result == ACCEPTED
        # The ACK was lost, as far as the sender knows: it sends the same
        # command again with the confirmation counted up, as MAVSDK does.
        assert gcs.command(ARM, 1, confirmation=1).result == ACCEPTED
        assert gcs.command(ARM, 1, confirmation=2).result == ACCEPTED
        # Telemetry requests change no flight: not counted.
        assert gcs.set_interval(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 100_000) == ACCEPTED
    (arm,) = counted(vehicle)
    assert (arm["seq"], arm["effect"], arm["system_id"]) == (1, "arm", 1)
    assert abs(arm["time"] - time.time()) < 60
    assert vehicle.state().armed


def test_a_command_long_sent_again_as_new_is_counted_twice(vehicle: SimVehicle) -> None:
    with GroundStation(vehicle.port) as gcs:
        gcs.say_hello()
        assert gcs.command(ARM, 1, confirmation=0).result == ACCEPTED
        assert gcs.command(ARM, 1, confirmation=0).result == ACCEPTED  # a new command
    assert [(e["seq"], e["effect"]) for e in counted(vehicle)] == [(1, "arm"), (2, "arm")]


def test_a_refused_command_is_not_counted_and_its_retransmission_is_new(
    vehicle: SimVehicle,
) -> None:
    with GroundStation(vehicle.port) as gcs:
        gcs.say_hello()
        refused = gcs.command(TAKEOFF, 0, 0, 0, 0, 0, 0, UNSET)  # not armed
        assert refused.result == mavlink.MAV_RESULT_DENIED
        assert gcs.command(ARM, 1).result == ACCEPTED
        # The same takeoff, marked as a retransmission: the first was not acted on.
        again = gcs.command(TAKEOFF, 0, 0, 0, 0, 0, 0, UNSET, confirmation=1)
        assert again.result == ACCEPTED
    assert [e["effect"] for e in counted(vehicle)] == ["arm", "takeoff"]
    assert counted(vehicle)[1]["relative_altitude_m"] == pytest.approx(2.5)  # MIS_TAKEOFF_ALT


def test_a_battery_reset_is_read_back_counted_once_and_a_bad_one_denied(
    vehicle: SimVehicle,
) -> None:
    """ArduPilot's MAV_CMD_BATTERY_RESET (param1 the battery mask, param2 the percentage),
    the testbed's battery fault: the vehicle reads that percentage in BATTERY_STATUS and
    SYS_STATUS, and counts the reset once (a copy with a confirmation is not acted on
    again); a mask without its battery, or a percentage that is not one, is DENIED and
    changes nothing."""
    with GroundStation(vehicle.port) as gcs:
        gcs.say_hello()
        assert gcs.command(BATTERY_RESET, 1, 15).result == ACCEPTED
        assert gcs.command(BATTERY_RESET, 1, 15, confirmation=1).result == ACCEPTED
        for mask, percent in ((0, 40), (1, 101), (1, UNSET), (UNSET, 40)):
            refused = gcs.command(BATTERY_RESET, mask, percent)
            assert refused.result == mavlink.MAV_RESULT_DENIED, (mask, percent)
        assert gcs.command(REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_BATTERY_STATUS).result == (
            ACCEPTED
        )
        assert gcs.receive("BATTERY_STATUS").battery_remaining == 15
        assert gcs.command(REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_SYS_STATUS).result == ACCEPTED
        assert gcs.receive("SYS_STATUS").battery_remaining == 15
    [reset] = counted(vehicle)
    assert (reset["effect"], reset["percent"], reset["was_percent"]) == ("battery_reset", 15, 100)
    assert vehicle.state().battery_pct == 15.0


def test_a_goto_sent_again_once_acknowledged_is_counted_twice(vehicle: SimVehicle) -> None:
    """An identical COMMAND_INT right after its ACK: the sender asked again (the drone
    executing one Goto twice), not a retransmission, which would come 0.5 s later."""
    north = round((HOME[0] + 0.0002) * 1e7)
    east = round(HOME[1] * 1e7)
    with GroundStation(vehicle.port) as gcs:
        gcs.say_hello()
        assert gcs.command(ARM, 1).result == ACCEPTED
        assert gcs.command(TAKEOFF, 0, 0, 0, 0, 0, 0, HOME[2] + 10).result == ACCEPTED
        for _ in range(2):
            ack = gcs.command_int(REPOSITION, -1, 0, 0, UNSET, x=north, y=east, z=HOME[2] + 10)
            assert ack.result == ACCEPTED
    effects = counted(vehicle)
    assert [e["effect"] for e in effects] == ["arm", "takeoff", "goto", "goto"]
    assert effects[1]["relative_altitude_m"] == pytest.approx(10.0)
    goto = effects[2]
    assert (goto["latitude_deg"], goto["longitude_deg"]) == (north / 1e7, east / 1e7)
    assert goto["altitude_amsl_m"] == pytest.approx(HOME[2] + 10)
    assert effects[3] | {"seq": 3, "time": goto["time"]} == goto
    assert [e["seq"] for e in effects] == [1, 2, 3, 4]


def stopped(pid: int) -> bool:
    """Whether every thread of process ``pid`` is stopped (a SIGSTOP took effect)."""
    states = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        stat = (task / "stat").read_text()
        states.append(stat[stat.rindex(")") + 2])  # the field after "pid (comm)"
    return all(state in "tT" for state in states)


async def test_copies_queued_while_the_vehicle_was_stopped_are_acted_on_once(
    tmp_path: Path,
) -> None:
    """MAVSDK re-sends every 0.5 s, COMMAND_LONG with confirmation still 0: copies that
    reached the vehicle before it acknowledged the first are retransmissions."""
    path = tmp_path / "effects.jsonl"
    sim = await start_sim("--speedup", "10", "--warmup", "0", "--effects-file", str(path))
    north = round((HOME[0] + 0.0002) * 1e7)
    east = round(HOME[1] * 1e7)
    try:
        with GroundStation(sim.port) as gcs:
            gcs.say_hello()
            assert gcs.command(ARM, 1).result == ACCEPTED
            assert gcs.command(TAKEOFF, 0, 0, 0, 0, 0, 0, HOME[2] + 10).result == ACCEPTED
            os.kill(sim.process.pid, signal.SIGSTOP)
            # kill() returns before the stop takes effect: a vehicle still running read
            # the first copy and acknowledged it before the others were sent (a goto
            # acted on twice, seen once on a loaded machine).
            await eventually(lambda: stopped(sim.process.pid), "the vehicle stopped", 10)
            try:
                for _ in range(3):
                    gcs.send_command_int(REPOSITION, -1, 0, 0, UNSET, x=north, y=east, z=498.0)
                    gcs.link.mav.command_long_send(1, 1, SPEED, 0, 1, 7.0, -1, 0, 0, 0, 0)
            finally:
                os.kill(sim.process.pid, signal.SIGCONT)
            for command in [REPOSITION, SPEED] * 3:
                ack = gcs.receive("COMMAND_ACK", lambda ack, c=command: ack.command == c)  # type: ignore[misc]
                assert ack.result == ACCEPTED
    finally:
        assert await sim.terminate() == 0
    effects = read_effects(path)
    assert [e["effect"] for e in effects] == ["arm", "takeoff", "goto", "set_speed"]
    assert effects[3]["speed_m_s"] == 7.0


async def test_commands_mavsdk_sent_again_as_their_acks_were_lost_are_acted_on_once(
    vehicle: SimVehicle, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What the rule is for: the vehicle acted, its ACK was lost, and MAVSDK sent the same
    command again 0.5 s later (a takeoff as COMMAND_LONG, confirmation still 0; a goto as
    COMMAND_INT), through the drone service's own Mobility backend."""
    assert vehicle._mav is not None
    send_ack = vehicle._mav.command_ack_send
    lost = {TAKEOFF: 2, REPOSITION: 2}  # ACKs lost per command

    def lossy(command: int, *rest: Any) -> None:
        if lost.get(command, 0) > 0:
            lost[command] -= 1
            return
        send_ack(command, *rest)

    monkeypatch.setattr(vehicle._mav, "command_ack_send", lossy)
    mobility = await connected_mobility(vehicle.url)
    try:
        await mobility.Arm(api.ArmRequest())
        await mobility.Takeoff(api.TakeoffRequest(altitude_m=5))
        target = api.GotoRequest(
            latitude_deg=HOME[0] + 0.0002, longitude_deg=HOME[1], relative_altitude_m=5
        )
        await mobility.Goto(target)
        await mobility.Goto(target)  # the caller asks again: a second goto, counted
    finally:
        await mobility.close()
    assert lost == {TAKEOFF: 0, REPOSITION: 0}, "MAVSDK got every ACK: nothing was re-sent"
    assert [e["effect"] for e in counted(vehicle)] == ["arm", "takeoff", "goto", "goto"]


def test_the_retransmission_rule_in_time() -> None:
    """Arrived before the ACK, or 0.4 to 1 s after the previous copy, or a COMMAND_LONG
    marked by its sender (confirmation > 0) within 1 s: a copy."""
    rule = Retransmissions()
    assert (rule.retry_after_s, rule.window_s) == (0.4, 1.0)
    goto = CommandKey((255, 190), "COMMAND_INT", REPOSITION, (-1.0, 0.0, 0.0, "nan", 6, 1, 2, 3.0))
    assert rule.original(goto, None, 0.0) is None
    rule.acted(goto, 7, arrived_at=0.0, acked_at=0.002)
    assert rule.original(goto, None, 0.001) == 7  # queued before the ACK went out
    assert rule.original(goto, None, 0.1) is None  # asked again once acknowledged
    assert rule.original(goto, None, 0.5) == 7  # the sender's timeout ran out
    assert rule.original(goto, None, 1.0) == 7  # 0.5 s after the previous copy
    assert rule.original(goto, None, 2.1) is None  # too late: a new goto
    elsewhere = CommandKey(goto.sender, goto.message, goto.command, (*goto.params[:-1], 4.0))
    other_sender = CommandKey((254, 190), goto.message, goto.command, goto.params)
    rule.acted(goto, 8, arrived_at=10.0, acked_at=10.002)
    assert rule.original(elsewhere, None, 10.001) is None
    assert rule.original(other_sender, None, 10.001) is None
    # Only the sender's latest flight command can be copied: the cruise speed
    # the drone re-sends after each goto is a new command.
    speed = CommandKey(goto.sender, "COMMAND_LONG", SPEED, (1.0, 5.0, -1.0, 0.0, 0.0, 0.0, 0.0))
    rule.acted(speed, 12, arrived_at=40.0, acked_at=40.002)
    rule.acted(goto, 13, arrived_at=40.1, acked_at=40.102)
    assert rule.original(speed, None, 40.6) is None

    arm = CommandKey((255, 190), "COMMAND_LONG", ARM, (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    rule.acted(arm, 9, arrived_at=20.0, acked_at=20.002)
    assert rule.original(arm, 0, 20.1) is None  # confirmation 0, once acknowledged: new
    assert rule.original(arm, 1, 20.1) == 9  # marked as a retransmission by its sender
    assert rule.original(arm, 2, 25.0) is None  # marked, but long after
    # An arm after a disarm is new.
    disarm = CommandKey(arm.sender, arm.message, ARM, (0.0, *arm.params[1:]))
    rule.acted(arm, 10, arrived_at=30.0, acked_at=30.002)
    rule.acted(disarm, 11, arrived_at=30.1, acked_at=30.102)
    assert rule.original(arm, None, 30.6) is None


def test_the_gimbal_points_at_a_region_of_interest_until_it_is_cleared(
    vehicle: SimVehicle,
) -> None:
    lat, lon = 47.3978, 8.5457
    with GroundStation(vehicle.port) as gcs:
        gcs.say_hello()
        # As MAVSDK's Gimbal.set_roi_location sends it (here in MAV_FRAME_GLOBAL: AMSL).
        located = gcs.command_int(
            mavlink.MAV_CMD_DO_SET_ROI_LOCATION, 0, x=int(lat * 1e7), y=int(lon * 1e7), z=490
        )
        assert located.result == ACCEPTED
        looking = vehicle.state().looking_at
        assert looking is not None and looking.altitude_amsl_m == pytest.approx(490)
        assert gcs.command(mavlink.MAV_CMD_DO_SET_ROI_NONE).result == ACCEPTED
        assert vehicle.state().looking_at is None
        # DO_SET_ROI: location mode (3) points, none (0) clears, another mode is refused.
        roi = mavlink.MAV_CMD_DO_SET_ROI
        assert gcs.command(roi, 3, 0, 0, 0, lat, lon, 495).result == ACCEPTED
        assert vehicle.state().looking_at is not None
        assert gcs.command(roi, 1).result == mavlink.MAV_RESULT_DENIED
        assert gcs.command(roi, 0).result == ACCEPTED
        assert vehicle.state().looking_at is None
    assert [e["effect"] for e in counted(vehicle)] == ["roi", "roi_none", "roi", "roi_none"]
    first = counted(vehicle)[0]
    assert (round(first["latitude_deg"], 6), round(first["longitude_deg"], 6)) == (lat, lon)

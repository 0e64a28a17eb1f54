"""The autopilot taking the vehicle over, as the pure rule decides it
(``safety.autopilot_takeover``, ``DroneCore.autopilot_due``): a flight mode, a landing
or a disarm the drone did not command while it flies the mission is a failsafe; the
modes the drone itself commands, the transients around a command and the arming are
not. The end-to-end witness is tests/drone/test_failsafe_end_to_end.py."""

from __future__ import annotations

import grpc

from baton.digest import request_digest
from baton.drone.core import DroneCore
from baton.drone.safety import (
    AUTOPILOT,
    FLY,
    HOLD,
    LAND,
    MODE_SETTLE_S,
    RTL,
    Failsafe,
    ModeSeen,
    VehicleCommand,
    autopilot_takeover,
    mode_seen,
)
from baton.drone.sequencer import Sequencer
from baton.rpc.errors import StatusError
from baton.rpc.methods import path
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

GET = "/baton.v1.Mobility/GetPosition"
LATER = MODE_SETTLE_S + 1.0  # a look well after the command


def flying(mode: str) -> ModeSeen:
    return ModeSeen(mode, armed=True, in_air=True)


def decide(command: VehicleCommand, seen: ModeSeen, now: float = LATER) -> Failsafe | None:
    return autopilot_takeover(now, command, seen)[1]


def drone() -> DroneCore:
    return DroneCore(Sequencer([0, 1], initial_master=0))


def refusal_of_first(core: DroneCore, method: str, now: float) -> StatusError:
    """Why ``core`` refused master 0's first request, a ``method`` call, when admitted."""
    admitted = core.admit(
        drone_pb2.InvokeRequest(controller_id=0, epoch=1, reqnr=1, method=method),
        request_digest(method, b""),
        now,
    )
    assert admitted.refused is not None
    return admitted.refused


def test_a_return_or_landing_the_drone_did_not_command_is_the_autopilot_s() -> None:
    """Flying a leg (ArduPilot GUIDED, PX4 and the sim vehicle HOLD), a return, a landing
    or a pilot's mode is a takeover named after the mode; the drone commands nothing."""
    leg = VehicleCommand((FLY,), 0.0)
    for mode in ("RETURN_TO_LAUNCH", "LAND", "POSCTL", "MISSION", "RTL", "SMART_RTL", "LOITER"):
        due = decide(leg, flying(mode))
        assert due is not None, mode
        assert (due.cause, due.action) == (AUTOPILOT, mode)
        assert due.reason.startswith(f"autopilot took over: {mode} (the drone commanded fly)")
        assert not due.drone_acts
        assert "in failsafe (autopilot: autopilot took over: " in due.refusal("GetPosition").message


def test_the_modes_the_drone_commands_are_never_a_takeover() -> None:
    """GUIDED/OFFBOARD/HOLD/TAKEOFF while flying; a hold's BRAKE or LOITER; a landing's
    LAND; a return's RTL and the landing it ends in; modes that say nothing."""
    cases = {
        FLY: ("GUIDED", "OFFBOARD", "HOLD", "TAKEOFF", "UNKNOWN", ""),
        HOLD: ("BRAKE", "LOITER", "HOLD", "GUIDED"),
        LAND: ("LAND", "GUIDED"),
        RTL: ("RTL", "RETURN_TO_LAUNCH", "SMART_RTL", "LAND"),
    }
    for action, modes in cases.items():
        for mode in modes:
            assert decide(VehicleCommand((action,), 0.0), flying(mode)) is None, (action, mode)


def test_a_mode_reported_late_after_a_command_is_not_a_takeover() -> None:
    """After a return and a Goto back (a resume), RTL is still reported for a moment: the
    earlier command's modes count for MODE_SETTLE_S, then only the new one's."""
    command = VehicleCommand((RTL,), 0.0).commanding(FLY, 10.0)
    assert decide(command, flying("RTL"), 10.1) is None  # while the Goto executes
    command = command.commanded(FLY, 10.2)
    assert command.actions == (FLY,) and RTL in command.before
    assert decide(command, flying("RTL"), 10.2 + MODE_SETTLE_S - 0.1) is None
    due = decide(command, flying("RTL"), 10.2 + MODE_SETTLE_S)
    assert due is not None and due.action == "RTL"


def test_a_return_at_once_after_a_goto_is_a_takeover() -> None:
    """Modes no command explains count at once, even right after a command: an autopilot
    that returns the vehicle a moment after the Goto is not hidden by the settling."""
    command = VehicleCommand((FLY,), 0.0).commanding(FLY, 5.0).commanded(FLY, 5.1)
    due = decide(command, flying("RETURN_TO_LAUNCH"), 5.2)
    assert due is not None and due.action == "RETURN_TO_LAUNCH"


def test_a_failed_command_leaves_both_modes_possible() -> None:
    """A Land that failed (a timeout: the vehicle may have taken it) leaves LAND expected
    beside the leg's modes, until the next command the vehicle accepts."""
    command = VehicleCommand((FLY,), 0.0).commanding(LAND, 5.0)  # never commanded()
    assert decide(command, flying("LAND"), 100.0) is None
    assert decide(command, flying("GUIDED"), 100.0) is None
    assert decide(command, flying("RETURN_TO_LAUNCH"), 100.0) is not None


def test_landing_or_disarming_while_flown_is_a_takeover_once_seen_in_the_air() -> None:
    """Armed on the ground waiting for the takeoff, or climbing: nothing. Once seen in the
    air since the command, on the ground or disarmed is the autopilot's (a landing
    commanded, or a return, is not)."""
    command = VehicleCommand((FLY,), 0.0)
    on_ground = ModeSeen("HOLD", armed=True, in_air=False)
    command, due = autopilot_takeover(LATER, command, on_ground)
    assert due is None and not command.airborne
    command, due = autopilot_takeover(LATER, command, flying("HOLD"))
    assert due is None and command.airborne
    landed = autopilot_takeover(LATER, command, on_ground)[1]
    assert landed is not None and landed.action == "landed"
    disarmed = autopilot_takeover(LATER, command, ModeSeen("HOLD", armed=False, in_air=True))
    assert disarmed[1] is not None and disarmed[1].action == "disarmed"
    returned = VehicleCommand((RTL,), 0.0, airborne=True)
    assert decide(returned, ModeSeen("LAND", armed=False, in_air=False)) is None
    # Its link out (a reboot): back on the ground is the outage's, not a takeover.
    assert decide(command.unseen(), on_ground) is None
    # A new flight's Arm on the ground starts unseen in the air again.
    rearmed = returned.commanding(FLY, 50.0).commanded(FLY, 50.1)
    assert decide(rearmed, on_ground, 50.1 + LATER) is None


def test_on_the_ground_a_mode_is_no_takeover() -> None:
    """ArduCopter sits in LAND after a landing and switches to GUIDED to arm: on the
    ground no mode counts."""
    command = VehicleCommand((FLY,), 0.0)
    assert decide(command, ModeSeen("LAND", armed=False, in_air=False)) is None
    assert decide(command, ModeSeen("STABILIZE", armed=True, in_air=False)) is None


def test_arduPilot_is_read_by_its_own_mode_names() -> None:
    """MAVSDK names ArduPilot's GUIDED OFFBOARD and its BRAKE and LOITER both HOLD: the
    rule reads ArduPilot's heartbeat name, MAVSDK's for PX4 and the sim vehicle."""
    ardupilot = api.GetFlightStateReply(
        armed=True, in_air=True, flight_mode="HOLD", autopilot_mode="LOITER", autopilot="ArduPilot"
    )
    assert mode_seen(ardupilot).mode == "LOITER"
    assert decide(VehicleCommand((FLY,), 0.0), mode_seen(ardupilot)) is not None
    px4 = api.GetFlightStateReply(
        armed=True, in_air=True, flight_mode="HOLD", autopilot_mode="LOITER", autopilot="PX4"
    )
    assert decide(VehicleCommand((FLY,), 0.0), mode_seen(px4)) is None


def test_the_core_takes_it_only_while_it_flies_the_mission() -> None:
    """Nothing commanded yet, in a failsafe, paused, ended or after a ground station's
    override: no takeover. Taken, every admitted request is refused and booked; an
    operator's resume takes the mode as it is until the next command."""
    core = drone()
    assert core.autopilot_due(LATER, flying("RETURN_TO_LAUNCH")) is None  # nothing commanded
    core.commanding(FLY, 0.0)
    core.commanded(FLY, 0.0)
    core.operator.pause(1.0, 0)
    assert core.autopilot_due(LATER, flying("RETURN_TO_LAUNCH")) is None
    assert core.autopilot_due(LATER, flying("HOLD")) is None  # the pause's hold, last seen
    core.resume_mission(2.0)
    due = core.autopilot_due(2.0 + LATER, flying("RETURN_TO_LAUNCH"))
    assert due is not None
    core.enter_failsafe(due)
    assert core.vehicle_command is not None and core.vehicle_command.actions == (FLY,)
    assert core.autopilot_due(3.0 + LATER, flying("RETURN_TO_LAUNCH")) is None  # in failsafe
    refused = refusal_of_first(core, GET, 20.0)
    assert refused.code is grpc.StatusCode.FAILED_PRECONDITION
    assert "autopilot took over: RETURN_TO_LAUNCH" in refused.message
    cleared, _ = core.resume_mission(30.0)
    assert cleared is due
    # Resumed in the autopilot's return: neither it nor the landing it ends in counts.
    assert core.autopilot_due(30.0 + LATER, flying("RETURN_TO_LAUNCH")) is None
    assert core.autopilot_due(30.0 + LATER, ModeSeen("LAND", False, False)) is None
    core.station_took_over()
    assert core.autopilot_due(30.0 + LATER, flying("POSCTL")) is None


def test_a_failsafe_the_drone_commands_sets_what_it_expects() -> None:
    """A lost-link rtl commands RTL: after a resume the vehicle returning is not a
    takeover of the autopilot."""
    core = drone()
    core.commanded(FLY, 0.0)
    core.enter_failsafe(Failsafe("lost_link", "rtl", 10.0, "no usable controller"))
    assert core.vehicle_command is not None and core.vehicle_command.actions == (RTL,)
    core.resume_mission(11.0)
    assert core.autopilot_due(11.0 + LATER, flying("RETURN_TO_LAUNCH")) is None


def test_a_vehicle_flown_before_a_restart_and_found_landed_is_the_autopilot_s() -> None:
    """The state file keeps the command and that the vehicle was seen in the air
    (``kept_command``). Restored from it, the first sight of the vehicle on the ground
    or disarmed is the autopilot's landing while the drone was down; one found still
    flying, or one the drone had sent home or down, is not. The look is repeated until a
    failsafe holds it (the driver looks again under its lock)."""
    before = drone()
    before.commanded(FLY, 0.0)
    before.autopilot_due(LATER, flying("GUIDED"))
    kept = before.kept_command()
    assert kept == {"actions": [FLY], "airborne": True}

    restarted = drone()
    restarted.restore_command(kept, 100.0)
    on_ground = ModeSeen("LOITER", armed=False, in_air=False)
    dues = [restarted.autopilot_due(100.5, on_ground) for _ in range(2)]
    for due in dues:
        assert due is not None and (due.cause, due.action) == (AUTOPILOT, "landed")
        assert "while the drone service was down (it flew fly)" in due.reason
    assert dues[0] is not None
    restarted.enter_failsafe(dues[0])
    assert restarted.autopilot_due(101.0, on_ground) is None

    still_flying = drone()
    still_flying.restore_command(kept, 100.0)
    assert still_flying.autopilot_due(100.5, flying("GUIDED")) is None
    assert not still_flying.airborne_before_restart  # the ordinary rule from here

    sent_home = drone()
    sent_home.restore_command({"actions": [RTL], "airborne": True}, 100.0)
    assert sent_home.autopilot_due(100.5, on_ground) is None

    older_file = drone()  # a list of actions: never seen in the air as far as it says
    older_file.restore_command([FLY], 100.0)
    assert older_file.autopilot_due(100.5, on_ground) is None


def test_a_vehicle_seen_in_the_air_before_the_first_command_is_kept_as_flown() -> None:
    """A mission that finds the vehicle flying (its first command a Goto): the look before
    that command saw it in the air, so the state file says it flew, and a restart that
    finds it landed (the autopilot's GCS failsafe, with no drone speaking to it) is the
    autopilot's landing. Seen first on the ground, the first command flies nothing yet."""
    in_the_air = drone()
    assert in_the_air.autopilot_due(0.0, flying("HOLD")) is None  # nothing commanded yet
    in_the_air.commanding(FLY, 1.0)  # killed right after: no look since
    kept = in_the_air.kept_command()
    assert kept == {"actions": [FLY], "airborne": True}
    restarted = drone()
    restarted.restore_command(kept, 100.0)
    due = restarted.autopilot_due(100.5, ModeSeen("LAND", armed=False, in_air=False))
    assert due is not None and (due.cause, due.action) == (AUTOPILOT, "landed")

    on_the_ground = drone()
    on_the_ground.autopilot_due(0.0, ModeSeen("HOLD", armed=False, in_air=False))
    on_the_ground.commanding(FLY, 1.0)
    assert on_the_ground.kept_command() == {"actions": [FLY], "airborne": False}


def test_a_vehicle_seen_in_the_air_stays_so_through_the_commands_that_fly_it_on() -> None:
    """What the state file keeps right after a Goto or a Hold acknowledged in the air
    still says the vehicle flew (a kill of the drone then must not forget it); after a
    Land or a return, a new flight is looked at afresh."""
    command = VehicleCommand((FLY,), 0.0, airborne=True)
    for action in (FLY, HOLD, FLY):
        command = command.commanding(action, 1.0).commanded(action, 1.1)
        assert command.airborne, action
    landed = command.commanding(LAND, 2.0).commanded(LAND, 2.1)
    assert not landed.airborne
    assert not landed.commanding(FLY, 9.0).commanded(FLY, 9.1).airborne


def test_a_drone_restarted_with_the_vehicle_in_the_air_commands_it_only_after_a_look() -> None:
    """Until the restarted drone has seen the vehicle's flight state, a Mobility call or a
    picture is UNAVAILABLE (nothing executed, the number stays unused): the autopilot may
    have landed the vehicle or sent it home meanwhile, and a picture re-sent then would be
    taken away from its waypoint. After the look, the ordinary rules."""
    restarted = drone()
    restarted.restore_command({"actions": [FLY], "airborne": True}, 100.0)
    goto, picture = path("Mobility.Goto"), path("Camera.TakePicture")
    for method in (goto, picture):
        refused = restarted.unreachable(method, True, "")
        assert refused is not None and refused.code is grpc.StatusCode.UNAVAILABLE
        assert "has not seen its flight state yet" in refused.message
    assert restarted.unreachable(path("Camera.SetResolution"), True, "") is None
    assert restarted.autopilot_due(100.1, flying("GUIDED")) is None
    assert restarted.unreachable(goto, True, "") is None
    assert restarted.unreachable(picture, True, "") is None
    again = drone()  # killed again before its first look: it still knows the vehicle flew
    again.restore_command(restarted_before_look := {"actions": [FLY], "airborne": True}, 100.0)
    assert again.kept_command() == restarted_before_look
    never_flown = drone()
    never_flown.restore_command({"actions": [FLY], "airborne": False}, 100.0)
    assert never_flown.unreachable(goto, True, "") is None


def test_a_picture_re_sent_to_a_drone_restarted_while_its_autopilot_returned_is_refused() -> None:
    """The drone killed with a picture in flight; the autopilot's own GCS failsafe sends
    the vehicle home while the drone service is down. The picture re-sent after the
    restart is not taken before the first look (UNAVAILABLE: nothing executed), and the
    first look finds the return: the autopilot failsafe, in which the picture is refused
    and booked (FAILED_PRECONDITION), never taken on the way home."""
    restarted = drone()
    restarted.restore_command({"actions": [FLY], "airborne": True}, 100.0)
    picture = path("Camera.TakePicture")
    before_look = restarted.unreachable(picture, True, "")
    assert before_look is not None and not restarted.books(before_look)
    due = restarted.autopilot_due(100.1, flying("RETURN_TO_LAUNCH"))
    assert due is not None and (due.cause, due.action) == (AUTOPILOT, "RETURN_TO_LAUNCH")
    restarted.enter_failsafe(due)
    assert restarted.unreachable(picture, True, "") is None
    refused = refusal_of_first(restarted, picture, 100.2)
    assert refused.code is grpc.StatusCode.FAILED_PRECONDITION and restarted.books(refused)

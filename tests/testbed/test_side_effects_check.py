"""``check_side_effects``: what the vehicle acted on against the mission, with the
gotos the drone's handover policy sent itself (resumes) taken out."""

from __future__ import annotations

from baton.missions.grid import waypoints
from baton.sdk import Position, offset
from baton.testbed.local import Effects, Snapshot
from baton.testbed.report import check_side_effects
from baton.v1 import drone_pb2

HOME = Position(47.3977, 8.5456, 0.0, 0.0)
SPACING_M = 20.0


def flown(resumed_after: int | None) -> Effects:
    """The 2x2 grid as the vehicle acted on it; the Goto of waypoint ``resumed_after``
    sent once more by the policy (a leg flown on after a hold), if given."""
    effects: Effects = [{"effect": "arm"}, {"effect": "takeoff"}]
    for k, (north, east) in enumerate(waypoints(2, SPACING_M), start=1):
        target = offset(HOME, north, east)
        goto = {
            "effect": "goto",
            "latitude_deg": target.latitude_deg,
            "longitude_deg": target.longitude_deg,
        }
        effects += [goto, goto] if k == resumed_after else [goto]
    return [*effects, {"effect": "land"}]


def checked(effects: Effects, resumes: int) -> dict:
    snapshot = Snapshot(drone_pb2.DroneStatus(policy_resumes=resumes), vehicle_effects=effects)
    return check_side_effects(snapshot, 2, SPACING_M)


def test_a_resume_the_drone_counted_is_not_held_against_the_mission() -> None:
    """The drone restarted (or took over 100 decisions) since it resumed: no decision
    says so any more, and a count kept in its state file still does. Counted from the
    decisions, the report called this mission's goto a duplicate."""
    effects = checked(flown(resumed_after=2), resumes=1)
    assert effects["problems"] == [] and effects["exactly_once"] is True


def test_a_goto_sent_twice_without_a_resume_is_a_duplicate() -> None:
    effects = checked(flown(resumed_after=2), resumes=0)
    assert effects["exactly_once"] is False
    assert "2 times" in effects["problems"][0], effects["problems"]
    assert checked(flown(resumed_after=None), resumes=0)["problems"] == []

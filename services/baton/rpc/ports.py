"""Each port's admission (admission.py): who may call its methods, from the
certificate alone, and the largest request it reads.

The limits are what the calls legitimately carry, so that one caller cannot
make a port read (and hold) more than that per call:

- The drone's port: a drone-API request is under a kilobyte (a Goto, a
  TakePicture request); what makes an Invoke bigger is its
  ``master_answers``, the master's Clock answers since its last drone call,
  about 80 bytes each. 4 MiB holds some 50,000 of them: a program that only
  sleeps and reads the clock for hours between two drone calls.
- A controller's ring port: a log frame is one slice of a log message
  (``ring.frame_bytes``, 16 KiB by default, at most 4 MiB) and, on a
  message's first frame, the message's head without its entries.
- The mission port (loopback, the mission token): the program's drone-API
  calls, as small as the drone's; and at most ``PROGRAM_PORT_CALLS`` calls in
  flight, whoever makes them (admission.port_full).
- The fleet's port (``baton fleet serve``): what the largest call carries is an
  Admit's QGroundControl plan, its text, a few hundred bytes a waypoint;
  4 MiB holds some 10,000 waypoints.
"""

from __future__ import annotations

from collections.abc import Iterable

from baton.rpc.admission import ANY_PART, CALLS_PER_CALLER, PortPolicy, Rule, controllers, only
from baton.rpc.tls import OPERATOR

DRONE_REQUEST_BYTES = 4 << 20
FLEET_REQUEST_BYTES = 4 << 20
# Room beside a frame's slice for its head (a log message without its entries).
FRAME_HEAD_BYTES = 64 << 10

_DRONE = "/baton.v1.Drone/"
_RING = "/baton.v1.ControllerRing/"
_STATION = "/baton.v1.Station/"
# A mission port's calls in flight: its program's stream of calls, a call it gave up
# and the next (controller/program_calls.py BUSY_GRACE_S), its MissionDone, and a few
# GetStatus, health or grpcurl calls beside them.
PROGRAM_PORT_CALLS = 16
# The largest ring frame any mission may choose (config.RingConfig.frame_bytes).
MAX_FRAME_BYTES = 4 << 20
# A peer station holds a ring stream or two per mission the two share: on a
# station's port its calls in flight are capped per mission as a lone controller's
# port caps them, and over all its missions at that cap times this many.
SHARED_MISSIONS = 64


def drone_policy(controller_ids: Iterable[int]) -> PortPolicy:
    """The drone's: the mission's controllers call what a master or standby does,
    an operator moves the master, pauses, resumes or ends the mission; anyone of the
    mission reads status."""
    stations = controllers(controller_ids, "the mission")
    operator = only(OPERATOR, "an operator")
    rules = {
        _DRONE + method: stations
        for method in (
            "Invoke",
            "InvokeStream",
            "Connect",
            "Standby",
            "ReportPreparation",
            "AnswerPing",
        )
    }
    rules |= {
        _DRONE + method: operator for method in ("Handover", "Resume", "Pause", "Abort", "LandNow")
    }
    rules[_DRONE + "GetStatus"] = ANY_PART
    return PortPolicy("drone's port", DRONE_REQUEST_BYTES, rules)


def ring_policy(ring_order: Iterable[int], frame_bytes: int) -> PortPolicy:
    """A controller's ring port: log frames from the ring's controllers only."""
    rules = {_RING + "LogRing": controllers(ring_order, "the ring")}
    return PortPolicy("ring port", frame_bytes + FRAME_HEAD_BYTES, rules)


def mission_policy() -> PortPolicy:
    """A controller's mission port: its program's calls (the token decides who)."""
    return PortPolicy("mission port", DRONE_REQUEST_BYTES, calls_in_flight=PROGRAM_PORT_CALLS)


ANY_STATION = Rule(
    "only a station (a controller certificate) may",
    lambda who: who.role == "controller",
)


def station_policy() -> PortPolicy:
    """A station's port: log frames from any station, each session then admitting only
    its own ring's (controller/service.py); the sessions started and stopped by an
    operator; any part reads a mission's status."""
    operator = only(OPERATOR, "an operator")
    rules = {_RING + "LogRing": ANY_STATION}
    rules |= {_STATION + m: operator for m in ("StartMission", "StopMission", "GetStation")}
    return PortPolicy(
        "station's port",
        MAX_FRAME_BYTES + FRAME_HEAD_BYTES,
        rules,
        calls_per_caller_all_missions=CALLS_PER_CALLER * SHARED_MISSIONS,
    )


def fleet_policy() -> PortPolicy:
    """The fleet's port (baton fleet serve): the operator only, for every method
    (health and reflection too): it admits missions and starts, stops and drains
    them on the stations as the operator."""
    return PortPolicy("fleet's port", FLEET_REQUEST_BYTES, default=only(OPERATOR, "an operator"))

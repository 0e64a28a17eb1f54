"""Random but deterministic mission programs: a list of drone-API calls per seed.

Every controller runs the same list, one call at a time, as a mission
program on a real controller does through the SDK. The calls are of the
kinds a real mission makes:

- reads (``GetPosition``, ``GetFlightState``) with an empty request, as the
  real ones are, so two polls in a row are the same request;
- commands (``Goto``, ``SetSpeed``, ``Takeoff``...) whose request names the
  call (``b"Goto #17"``): each one is unique, so the vehicle can count it;
- ``TakePicture``, unique too, whose reply is large (the paper's "e");
- calls the drone refuses after accepting them (a request it cannot parse:
  INVALID_ARGUMENT, booked like any outcome);
- Clock calls (``Now``, ``Sleep``), which the controller answers and logs
  and which never reach the drone.

Simplification: requests other than Sleep's are not real protobuf messages
(the simulated drone does not parse them); the method names are real, so
the drone's read/command split (``dispatch.Route.is_read``) applies.
"""

from __future__ import annotations

import enum
import random
from dataclasses import dataclass

from baton.controller.core import CLOCK_NOW, CLOCK_SLEEP
from baton.rpc.methods import path
from baton.v1 import drone_api_pb2 as api

GET_POSITION = path("Mobility.GetPosition")
GET_FLIGHT_STATE = path("Mobility.GetFlightState")
COMMANDS = tuple(path(f"Mobility.{n}") for n in ("Goto", "SetSpeed", "Takeoff", "Hold", "Land"))
TAKE_PICTURE = path("Camera.TakePicture")
# A request that starts with this byte does not parse at the simulated drone.
UNPARSABLE = b"\xff"


class Kind(enum.Enum):
    """What a mission call is, for the drone and for the oracles."""

    READ = "read"
    COMMAND = "command"
    PICTURE = "picture"
    BAD = "bad"  # a command the drone refuses with INVALID_ARGUMENT
    NOW = "now"
    SLEEP = "sleep"


@dataclass(frozen=True)
class MissionCall:
    """One call of the mission program: its position, kind, method and serialized request."""

    index: int
    kind: Kind
    method: str
    request: bytes

    @property
    def reqnr(self) -> int:
        """The request number every controller logs this call under (one per call)."""
        return self.index + 1

    @property
    def to_drone(self) -> bool:
        """Whether the call reaches the drone (Clock calls do not)."""
        return self.kind not in (Kind.NOW, Kind.SLEEP)

    @property
    def has_effect(self) -> bool:
        """Whether executing it changes the world (a flight command, a picture)."""
        return self.kind in (Kind.COMMAND, Kind.PICTURE)


_WEIGHTS = {
    Kind.READ: 38,
    Kind.COMMAND: 20,
    Kind.PICTURE: 12,
    Kind.BAD: 5,
    Kind.NOW: 10,
    Kind.SLEEP: 15,
}


def random_mission(rng: random.Random, calls: int) -> tuple[MissionCall, ...]:
    """``calls`` calls drawn from ``rng``."""
    kinds = list(_WEIGHTS)
    weights = list(_WEIGHTS.values())
    program = []
    for index in range(calls):
        kind = rng.choices(kinds, weights)[0]
        if kind is Kind.READ:
            method, request = rng.choice((GET_POSITION, GET_POSITION, GET_FLIGHT_STATE)), b""
        elif kind is Kind.COMMAND:
            method = rng.choice(COMMANDS)
            request = f"{method.rsplit('/', 1)[1]} #{index}".encode()
        elif kind is Kind.PICTURE:
            method, request = TAKE_PICTURE, f"picture #{index}".encode()
        elif kind is Kind.BAD:
            method, request = COMMANDS[0], UNPARSABLE + f"bad goto #{index}".encode()
        elif kind is Kind.NOW:
            method, request = CLOCK_NOW, b""
        else:
            seconds = round(rng.uniform(0.02, 0.4), 3)
            method = CLOCK_SLEEP
            request = api.SleepRequest(seconds=seconds).SerializeToString()
        program.append(MissionCall(index, kind, method, request))
    return tuple(program)

"""Waits that last too long, named and judged: the one way a part says it is stuck. Pure.

A controller whose next log message does not come, a ring stream that stays
down, a drone whose master holds no stream: each is normal for a moment and
a wait worth showing after a few seconds. A part lists the conditions that
hold now (a key and a text for a person); ``StallWatch`` remembers since when
each one holds and returns those older than its threshold as ``Wait``s, with
their age and whether a person should look (the part's judge:
``controller_judge``, ``drone_judge``). A wait that needs no person is the
design at work (a station out of range on the policy's own map, a new master
catching up within its bound) and is shown quietly; every other one is a
stall, logged as a warning and shown loudly. Times are given by the caller,
so the rules are tested with chosen times.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterable
from dataclasses import dataclass, field

from baton.v1 import waits_pb2

# A condition that holds this long is shown (seconds of wall time).
STALL_AFTER_S = 3.0
# A stall goes on being logged this often.
LOG_EVERY_S = 5.0
# A station's standby stream gets at least this long (wall seconds) to come up
# once the vehicle is in its range: the controller's channel retries a refused
# connection every 2 s at most (jittered by a fifth), its stream re-opens after
# at most 1 s, and a handshake over a fading link takes its round trips.
LINK_UP_AFTER_S = 5.0

# Controllers get this long (wall seconds) to reach a drone that has just started
# (a testbed starts the drone first, then each controller's process).
START_BOUND_S = 60.0


@dataclass(frozen=True)
class Wait:
    """A condition that has held ``age_s`` wall seconds; ``needs_person``: a stall."""

    key: str
    text: str
    age_s: float
    needs_person: bool = True

    def __str__(self) -> str:
        return f"{self.text} for {self.age_s:.0f} s"

    def to_proto(self) -> waits_pb2.Wait:
        """GetStatus's ``Wait``."""
        return waits_pb2.Wait(
            key=self.key, text=self.text, age_s=self.age_s, needs_person=self.needs_person
        )


# Whether a wait needs a person, from its key and its age.
Judge = Callable[[str, float], bool]


def always(key: str, age_s: float) -> bool:
    """The judge of a part that knows no wait to be expected: each needs a person."""
    return True


def one_line(waits: Iterable[Wait]) -> str:
    """The waits that need a person as GetStatus's ``waiting`` line ("; "-separated)."""
    return "; ".join(str(w) for w in waits if w.needs_person)


@dataclass
class StallWatch:
    """Since when each named condition has held; which ones to show, judged."""

    threshold_s: float = STALL_AFTER_S
    log_every_s: float = LOG_EVERY_S
    _since: dict[str, float] = field(default_factory=dict)
    _logged_at: float | None = None

    def update(self, now: float, holding: dict[str, str], judge: Judge = always) -> list[Wait]:
        """The waits held at least the threshold; ``holding`` maps key -> text."""
        for key in [k for k in self._since if k not in holding]:
            del self._since[key]
        waits = []
        for key, text in holding.items():
            since = self._since.setdefault(key, now)
            age = now - since
            if age >= self.threshold_s:
                waits.append(Wait(key, text, age, judge(key, age)))
        if not any(w.needs_person for w in waits):
            self._logged_at = None
        return waits

    def due_for_log(self, now: float, waits: list[Wait]) -> bool:
        """True when some wait needs a person and none was logged in the last
        ``log_every_s``: an expected wait is never a warning."""
        if not any(w.needs_person for w in waits):
            return False
        if self._logged_at is None or now - self._logged_at >= self.log_every_s:
            self._logged_at = now
            return True
        return False


def controller_judge(on_map: bool, master: bool, catch_up_bound_s: float) -> Judge:
    """How a controller judges its waits. ``on_map``: it is a station on the handover
    policy's map (a location and a range); ``master``: it is master now.

    A station that is not master has no stream to the drone (its standby stream,
    or the Connect with which it asks the drone whether it is master) while the
    vehicle is out of its range, as the policy plans: expected. It cannot see
    where the vehicle is;
    the drone can, and its own waits say when a station in range has no stream
    (``drone_judge``). A new master catching up with the ring is expected for as
    long as a prepared handover's target is given (``catch_up_bound_s``, the
    prepare timeout). A request waiting at the drone while an operator paused the
    mission is the operator's own doing: expected. Everything else, the master's
    own link included, needs a person.
    """

    def judge(key: str, age_s: float) -> bool:
        if key == "paused":
            return False
        if key in ("standby", "drone"):
            return master or not on_map
        if key == "catch-up":
            return age_s > catch_up_bound_s
        return True

    return judge


def drone_conditions(
    master: int,
    master_connected: bool,
    ring: Iterable[int],
    reachable: Collection[int],
    in_range: Collection[int] | None,
    reached: bool,
) -> dict[str, str]:
    """What the drone waits for now: its master's Connect stream and its controllers'
    standby streams (``station_links``). Until a controller has reached this drone
    process at all (``reached``), the controllers are still starting: one wait,
    "start", instead."""
    if not reached:
        return {"start": "no controller has reached the drone since it started"}
    holding = station_links(ring, reachable, in_range)
    if not master_connected:
        holding["master"] = f"the master, controller {master}, holds no Connect stream"
    return holding


def station_links(
    ring: Iterable[int], reachable: Collection[int], in_range: Collection[int] | None
) -> dict[str, str]:
    """The drone's conditions about its controllers' standby streams: each controller
    without one that the vehicle is in range of on the policy's map (``in_range``),
    or, without a map (None), every controller without one."""
    holding = {}
    for cid in ring:
        if cid in reachable or (in_range is not None and cid not in in_range):
            continue
        where = " though the vehicle is in its range" if in_range is not None else ""
        holding[f"link {cid}"] = f"controller {cid} holds no standby stream{where}"
    return holding


def drone_judge(link_up_bound_s: float) -> Judge:
    """How the drone judges its waits. A controller's standby stream missing while
    the vehicle is in its range is expected for ``link_up_bound_s`` (the time the
    link has to come up, at least ``LINK_UP_AFTER_S``) and needs a person after;
    controllers still starting get ``START_BOUND_S``; an operator's pause is the
    operator's own doing (expected); every other wait (the master holding no
    Connect stream) needs a person."""
    bound = max(link_up_bound_s, LINK_UP_AFTER_S)

    def judge(key: str, age_s: float) -> bool:
        if key == "paused":
            return False
        if key.startswith("link "):
            return age_s >= bound
        if key == "start":
            return age_s >= START_BOUND_S
        return True

    return judge

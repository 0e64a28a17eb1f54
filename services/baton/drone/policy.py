"""The handover policy: which controller should be master, from where the drone is.

The paper's drone "picks the controller deemed most suitable, e.g. the one
that is closer to its current position; the drone knows the location of the
edge nodes, their communication range, and the initial assignment of the
master role". This module is that choice, as a pure function: no sockets, no
tasks, no clock of its own. ``decide`` takes the vehicle's position and
velocity (``Fix``), each controller's location and range (``Station``, from
the testbed file), each controller's link as the drone sees it
(``LinkState``: is its standby or Connect stream up, for how long has it been
down, its last round trip and how old that is), the current master and the policy's own small
state (``PolicyState``), and returns a ``Decision`` with a reason a person can
read, and the next state. The drone service (``service.py``) feeds it its
own telemetry every tick and carries the decision out; the tests feed it
positions by hand.

Two policies (docs/design.md, "Range-driven handovers"):

- ``nearest`` (the paper's example): hand over to the nearest usable station
  once it has been nearer than the master by ``margin_m`` for ``dwell_s``,
  so that a drone on a boundary does not flap; at once when the master is
  unusable.
- ``predictive``: from the velocity, the time the vehicle stays in the
  master's range; once that is below ``lead_s`` (enough for a handover to
  finish), hand over to the usable station whose range the vehicle will
  stay in longest, if that is longer than the master's.

Both never choose a station that is out of range or whose link is not
healthy (``link_problem``: down, its last round trip over ``LinkBounds.max_rtt_s``
or older than ``rtt_stale_s``). When no station is usable the vehicle *flies on*
(``fly_on``) if the leg it flies (``Fix.leg_to``, the master's last Goto)
leads into the range of a station not known to be dead, or it is in such a
range whose station's link has had less than ``link_up_s`` to come up since
the vehicle came into it;
else it holds position (``hold``) until one is usable. Either way the mission
waits: no master can command the vehicle. The master's link going down while
it is in range is waited out for ``link_lost_after_s``, so a stream that is
re-opened does not move the master; after that another usable station takes
over (``takeover``: the old master cannot be told, so its log is not waited
for). A master chosen by the handover script or the operator is kept while it
is usable (``PolicyState.pinned``): they override the policy.

Distances are horizontal, on a local flat Earth around each station (good to
centimetres over a few kilometres, ``baton.sdk.geo``); a vehicle exactly on a
station's circle is in its range. Times are mission seconds (wall seconds
times the speed-up), as is the velocity the autopilot reports.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

from baton.sdk.geo import north_east_m
from baton.sdk.types import Position
from baton.v1 import drone_pb2

# The policies a drone can run; "none" leaves the master to the script and the operator.
POLICIES = ("none", "nearest", "predictive")
# Mobility commands after which the vehicle flies no leg to resume (it lands, goes
# home, holds or climbs on the master's word): a resume flies on only after a Goto.
ENDS_A_LEG = frozenset({"Land", "ReturnToLaunch", "Hold", "Takeoff", "Disarm", "Arm"})

# A decision's action: the contract's PolicyAction (GetStatus shows it as it is).
STAY = drone_pb2.POLICY_ACTION_STAY
HANDOVER = drone_pb2.POLICY_ACTION_HANDOVER
HOLD = drone_pb2.POLICY_ACTION_HOLD
FLY_ON = drone_pb2.POLICY_ACTION_FLY_ON


@dataclass(frozen=True)
class Station:
    """A controller's antenna: where it is and how far it reaches (metres)."""

    id: int
    location: Position
    range_m: float


@dataclass(frozen=True)
class Fix:
    """Where the vehicle is and where it is going: position, ground velocity (m/s)
    and the end of the leg it flies (the master's last Goto), when known."""

    position: Position
    north_m_s: float = 0.0
    east_m_s: float = 0.0
    leg_to: Position | None = None


@dataclass(frozen=True)
class LinkState:
    """A controller's link as the drone sees it now (``drone/link_probe.py`` measures
    the round trip: the drone's ping on the standby stream, the controller's answer)."""

    up: bool  # it holds a standby or Connect stream
    down_for_s: float = 0.0  # mission seconds since it was last up; 0 while up
    rtt_s: float | None = None  # its last round trip (wall seconds), once measured
    # Wall seconds since that round trip was measured (before the first, since the
    # first ping was sent); None before any ping: nothing is known yet.
    rtt_age_s: float | None = None


def _check_finite(owner: object, fields: tuple[str, ...], what: str) -> None:
    """ValueError unless each of ``owner``'s ``fields`` is >= 0 and finite."""
    for name in fields:
        value = getattr(owner, name)
        if not 0 <= value < math.inf:
            raise ValueError(f"{what} {name} must be >= 0 and finite, got {value!r}")


@dataclass(frozen=True)
class LinkBounds:
    """What a healthy link is (``link_problem``): its last round trip took at most
    ``max_rtt_s`` and is at most ``rtt_stale_s`` old. Wall seconds: a network does not
    speed up with the mission. The policy's (``PolicyParams.link_bounds``) and the
    drone's GetStatus and log (``link_probe.LinkProbes``), whatever the policy."""

    max_rtt_s: float = 2.0
    rtt_stale_s: float = 3.0

    def __post_init__(self) -> None:
        _check_finite(self, ("max_rtt_s", "rtt_stale_s"), "policy")


def link_problem(link: LinkState, bounds: LinkBounds) -> str:
    """Why ``link`` is not healthy, for a person; empty if it is: up, and its last
    round trip within ``bounds``.

    A link whose pings were never answered is judged by the age of its first ping:
    a stream that carries nothing (a frozen link) goes stale like one that stopped.
    Nothing measured yet (no ping sent) is no problem: a stream just opened.
    """
    if not link.up:
        return f"link down ({link.down_for_s:.1f} s)"
    max_rtt_s, rtt_stale_s = bounds.max_rtt_s, bounds.rtt_stale_s
    if link.rtt_s is not None and link.rtt_s > max_rtt_s:
        return f"link too slow (round trip {link.rtt_s:.2f} s over {max_rtt_s:g} s)"
    if link.rtt_age_s is not None and link.rtt_age_s > rtt_stale_s:
        if link.rtt_s is None:
            return f"link silent (no answer to a ping of {link.rtt_age_s:.1f} s ago)"
        return f"link stale (last round trip {link.rtt_age_s:.1f} s ago, over {rtt_stale_s:g} s)"
    return ""


@dataclass(frozen=True)
class PolicyParams:
    """A policy and its thresholds (times in mission seconds, but a link's round trip
    in wall seconds: a network does not speed up with the mission)."""

    name: str = "nearest"
    # nearest: another station must be this much nearer than the master...
    margin_m: float = 50.0
    # ... for this long, before the master moves to it.
    dwell_s: float = 3.0
    # predictive: hand over once the master's range runs out within this time.
    lead_s: float = 10.0
    # The master's link down this long while in range: another takes over.
    link_lost_after_s: float = 3.0
    # A link not healthy by these bounds is not used (``link_problem``).
    link_bounds: LinkBounds = LinkBounds()
    # No station usable, the vehicle flown into a station's range: its link is
    # given this long to come up (a controller's reconnect backs off to 1 s of
    # wall time, 10 s of the mission's at 10x) before the vehicle holds.
    link_up_s: float = 20.0

    def __post_init__(self) -> None:
        if self.name not in POLICIES[1:]:
            raise ValueError(
                f"unknown handover policy {self.name!r}; use one of {', '.join(POLICIES[1:])}"
            )
        thresholds = ("margin_m", "dwell_s", "lead_s", "link_lost_after_s", "link_up_s")
        _check_finite(self, thresholds, "policy")


@dataclass(frozen=True)
class Decision:
    """What to do now: ``stay``, ``handover`` to ``target``, or with none usable
    ``fly_on`` (towards ``target``'s range) or ``hold``."""

    action: drone_pb2.PolicyAction.ValueType
    reason: str
    target: int | None = None
    # The old master cannot be told (its link is down): the target takes over
    # without waiting for its log.
    takeover: bool = False
    # ``stay`` while the master is not usable (its link lost in range, waited out
    # for ``link_lost_after_s``): no controller can command the vehicle, so a held
    # one is not resumed yet.
    waiting: bool = False


@dataclass(frozen=True)
class PolicyState:
    """What the policy remembers between two decisions."""

    # nearest: the station that has been nearer by the margin, and since when.
    candidate: int | None = None
    candidate_since: float = 0.0
    # A master the script or the operator chose: kept while it is usable.
    pinned: int | None = None
    # Since when the vehicle has been in each station's range (the time its link
    # has had to come up there), as (controller, mission seconds), sorted; None
    # before the first decision (a station in range then counts as entered long
    # ago, -inf: a drone started in the air has not seen it come into range).
    entered: tuple[tuple[int, float], ...] | None = None

    def pin(self, master: int) -> PolicyState:
        """The state after the script or the operator made ``master`` master."""
        return PolicyState(pinned=master, entered=self.entered)


def time_in_range_s(fix: Fix, station: Station) -> float:
    """Mission seconds until the vehicle leaves ``station``'s range on its current
    velocity: 0 if it is outside, infinite if it is inside and not moving."""
    north, east = north_east_m(station.location, fix.position)
    c = north * north + east * east - station.range_m * station.range_m
    if c > 0:
        return 0.0
    a = fix.north_m_s**2 + fix.east_m_s**2
    if a <= 1e-12:
        return math.inf
    b = 2 * (north * fix.north_m_s + east * fix.east_m_s)
    # The later root of |p + v t| = r: where the straight track leaves the circle.
    return (-b + math.sqrt(b * b - 4 * a * c)) / (2 * a)


def entry_m(fix: Fix, station: Station) -> float | None:
    """Metres along the vehicle's leg (its position to ``fix.leg_to``) to where it
    comes into ``station``'s range: 0 if it is in it, None if the leg never does
    (or is not known)."""
    north, east = north_east_m(station.location, fix.position)
    c = north * north + east * east - station.range_m * station.range_m
    if c <= 0:
        return 0.0
    if fix.leg_to is None:
        return None
    to_north, to_east = north_east_m(station.location, fix.leg_to)
    d_north, d_east = to_north - north, to_east - east
    a = d_north * d_north + d_east * d_east
    b = 2 * (north * d_north + east * d_east)
    discriminant = b * b - 4 * a * c
    if a <= 1e-12 or discriminant < 0:
        return None
    # The earlier root of |p + t d| = r, t in [0, 1]: where the leg enters the circle.
    t = (-b - math.sqrt(discriminant)) / (2 * a)
    return t * math.sqrt(a) if 0 <= t <= 1 else None


@dataclass(frozen=True)
class _View:
    """One station as seen from the vehicle now."""

    station: Station
    distance_m: float
    link: LinkState
    # Why its link is not healthy (``link_problem``); empty if it is.
    link_problem: str

    @property
    def id(self) -> int:
        return self.station.id

    @property
    def in_range(self) -> bool:
        return self.distance_m <= self.station.range_m

    @property
    def link_ok(self) -> bool:
        return not self.link_problem

    @property
    def usable(self) -> bool:
        return self.in_range and self.link_ok

    def where(self) -> str:
        return f"{self.distance_m:.0f} m of {self.station.range_m:.0f} m"

    def why_not(self) -> str:
        """Why it cannot be master now (empty if it can)."""
        if not self.in_range:
            return f"{self.id} out of range ({self.where()})"
        if not self.link.up:
            return f"{self.id} link down ({self.link.down_for_s:.1f} s, {self.where()})"
        if not self.link_ok:
            return f"{self.id} {self.link_problem}"
        return ""


def decide(
    params: PolicyParams,
    stations: Mapping[int, Station],
    fix: Fix,
    links: Mapping[int, LinkState],
    master: int,
    state: PolicyState,
    now: float,
) -> tuple[Decision, PolicyState]:
    """The policy's decision now and its next state (see the module docstring).

    ``stations`` must hold every controller, the master too (KeyError
    otherwise: the configuration check makes sure); a controller missing from
    ``links`` counts as down.
    """
    views = {}
    for cid, station in stations.items():
        link = links.get(cid, LinkState(up=False, down_for_s=math.inf))
        problem = link_problem(link, params.link_bounds)
        views[cid] = _View(station, distance_m(station, fix), link, problem)
    since = dict(state.entered) if state.entered is not None else {}
    new = now if state.entered is not None else -math.inf
    entered = {cid: since.get(cid, new) for cid, v in views.items() if v.in_range}
    decision, state = _decide(params, fix, views, master, state, entered, now)
    return decision, replace(state, entered=tuple(sorted(entered.items())))


def _decide(
    params: PolicyParams,
    fix: Fix,
    views: Mapping[int, _View],
    master: int,
    state: PolicyState,
    entered: Mapping[int, float],
    now: float,
) -> tuple[Decision, PolicyState]:
    here = views[master]
    others = [v for cid, v in sorted(views.items()) if cid != master and v.usable]
    if state.pinned is not None and (state.pinned != master or not here.usable):
        state = replace(state, pinned=None)
    if state.candidate is not None and (state.candidate == master or state.candidate not in views):
        state = replace(state, candidate=None)

    if not here.usable:
        if here.in_range and not here.link.up and here.link.down_for_s < params.link_lost_after_s:
            return (
                Decision(
                    STAY,
                    f"master {here.why_not()} but in range: waiting "
                    f"{params.link_lost_after_s:g} s for it before another takes over",
                    waiting=True,
                ),
                state,
            )
        best = _best(params, fix, others)
        if best is None:
            return _fly_on_or_hold(params, fix, views, master, state, entered, now)
        return (
            Decision(
                HANDOVER,
                f"master {here.why_not()}; {_why_best(params, fix, best)}",
                target=best.id,
                takeover=not here.link.up,
            ),
            PolicyState(),
        )

    if state.pinned == master:
        return (
            Decision(STAY, f"master {master} chosen by the script or operator ({here.where()})"),
            state,
        )
    if params.name == "nearest":
        return _nearest(params, here, others, state, now)
    return _predictive(params, fix, here, others, state)


def _fly_on_or_hold(
    params: PolicyParams,
    fix: Fix,
    views: Mapping[int, _View],
    master: int,
    state: PolicyState,
    entered: Mapping[int, float],
    now: float,
) -> tuple[Decision, PolicyState]:
    """No station usable: fly on while the leg leads into a range whose station may
    answer there, else hold (the module docstring)."""
    unusable = "; ".join(v.why_not() for _, v in sorted(views.items()))
    ahead: list[tuple[float, int, str]] = []
    for cid, view in sorted(views.items()):
        if cid == master and view.in_range:
            continue  # its link lost in range was waited out already
        if view.in_range:
            waited = now - entered[cid]
            if waited < params.link_up_s:
                ahead.append(
                    (
                        0.0,
                        cid,
                        f"in {cid}'s range ({view.where()}), its link has "
                        f"{params.link_up_s - waited:.1f} s more to come up",
                    )
                )
            continue
        along = entry_m(fix, view.station)
        if along is not None:
            speed = math.hypot(fix.north_m_s, fix.east_m_s)
            eta = f", {along / speed:.0f} s" if speed > 0.5 else ""
            ahead.append((along, cid, f"the leg enters {cid}'s range in {along:.0f} m{eta}"))
    if not ahead:
        leg = "; the leg leads into no station's range" if fix.leg_to is not None else ""
        return Decision(HOLD, f"no controller usable: {unusable}{leg}"), state
    _, target, why = min(ahead)
    return (
        Decision(FLY_ON, f"no controller usable: {unusable}; flying on: {why}", target=target),
        state,
    )


def distance_m(station: Station, fix: Fix) -> float:
    """Horizontal metres from ``station`` to the vehicle, as the policy measures them."""
    north, east = north_east_m(station.location, fix.position)
    return math.hypot(north, east)


def _best(params: PolicyParams, fix: Fix, usable: list[_View]) -> _View | None:
    """The station to move to when the master must go: the nearest, or for
    ``predictive`` the one the vehicle stays in longest (then the nearest)."""
    if not usable:
        return None
    if params.name == "nearest":
        return min(usable, key=lambda v: (v.distance_m, v.id))
    return min(usable, key=lambda v: (-time_in_range_s(fix, v.station), v.distance_m, v.id))


def _why_best(params: PolicyParams, fix: Fix, best: _View) -> str:
    if params.name == "nearest":
        return f"{best.id} is the nearest usable ({best.where()})"
    return (
        f"{best.id} keeps the vehicle in range longest "
        f"({_seconds(time_in_range_s(fix, best.station))}, {best.where()})"
    )


def _seconds(value: float) -> str:
    return "while it is still" if math.isinf(value) else f"{value:.1f} s"


def _nearest(
    params: PolicyParams, here: _View, others: list[_View], state: PolicyState, now: float
) -> tuple[Decision, PolicyState]:
    best = min(others, key=lambda v: (v.distance_m, v.id), default=None)
    if best is None or best.distance_m + params.margin_m >= here.distance_m:
        nearest = f"; {best.id} at {best.distance_m:.0f} m" if best is not None else ""
        return (
            Decision(
                STAY,
                f"master {here.id} in range ({here.where()}), no usable station nearer by "
                f"{params.margin_m:g} m{nearest}",
            ),
            replace(state, candidate=None),
        )
    if state.candidate != best.id:
        state = replace(state, candidate=best.id, candidate_since=now)
    held = now - state.candidate_since
    nearer = f"{best.id} nearer ({best.distance_m:.0f} m) than master {here.id} ({here.where()})"
    if held < params.dwell_s:
        return (
            Decision(STAY, f"{nearer} for {held:.1f} s of {params.dwell_s:g} s"),
            state,
        )
    # The candidate is kept: until the master has moved (a prepared handover takes its
    # time), the decision stays this handover, not a new dwell and a second decision.
    return (
        Decision(HANDOVER, f"{nearer} by over {params.margin_m:g} m for {held:.1f} s", best.id),
        state,
    )


def _predictive(
    params: PolicyParams, fix: Fix, here: _View, others: list[_View], state: PolicyState
) -> tuple[Decision, PolicyState]:
    left = time_in_range_s(fix, here.station)
    if left > params.lead_s:
        return (
            Decision(
                STAY,
                f"master {here.id}'s range lasts {_seconds(left)} on this track "
                f"(hand over {params.lead_s:g} s before it runs out)",
            ),
            state,
        )
    best = _best(params, fix, others)
    if best is None or time_in_range_s(fix, best.station) <= left:
        return (
            Decision(
                STAY,
                f"master {here.id}'s range runs out in {left:.1f} s and no usable station "
                "keeps the vehicle in range longer",
            ),
            state,
        )
    return (
        Decision(
            HANDOVER,
            f"master {here.id}'s range runs out in {left:.1f} s; {_why_best(params, fix, best)}",
            best.id,
        ),
        PolicyState(),
    )


# What a handover decision does under the execution lock (``handover_step``).
MOVED = "moved meanwhile"  # the master changed since the decision: nothing
SWITCH = "at once"  # a takeover, or a master that cannot prepare: switched now
ALREADY_PREPARING = "already preparing"  # a preparation for the target is under way
PREPARE = "prepare"  # a prepared handover begins


def handover_step(
    decision: Decision,
    decided_for: int,
    master: int,
    can_prepare: bool,
    preparing_for: int | None,
) -> str:
    """What a ``handover`` decision taken for master ``decided_for`` does once the runner
    holds the execution lock, where ``master`` is master now: nothing if the master
    moved meanwhile; at once for a takeover or a master that cannot prepare (it holds
    no Connect stream to hear the PrepareHandover); nothing if it already prepares one
    for the target; else a prepared handover."""
    if master != decided_for:
        return MOVED
    if decision.takeover or not can_prepare:
        return SWITCH
    if preparing_for == decision.target:
        return ALREADY_PREPARING
    return PREPARE


def hold_due(decision: Decision, holding: bool, unsure: bool = False) -> bool:
    """Whether the runner commands the vehicle to hold: the decision says ``hold`` and it
    does not hold it already (or does not know whether the autopilot still holds: a
    restarted drone)."""
    return decision.action == HOLD and (not holding or unsure)


def resume_due(decision: Decision, holding: bool) -> bool:
    """Whether a hold ends: a decision other than ``hold`` that waits for nothing."""
    return holding and decision.action != HOLD and not decision.waiting

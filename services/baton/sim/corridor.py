"""A corridor of stations with radio range, and the simulated vehicle flying it (``--policy``).

With a handover policy (``SimOptions.policy``) the vehicle is not a point
any more: it flies east along a straight corridor past one station per
controller, each with a location and a range (the policy's ``Station``, as
the testbed file gives them), and back to where it started, and hovers there
(a mission that returns to launch; the way back also brings every station
the vehicle left in range again, see docs/design.md on a master taken over
out of range). Everything is drawn
from a random stream of its own, ``random.Random(f"policy {seed}")``, so
that the seed's other draws stay where they were:

- the stations' order along the corridor (the initial master first, where
  the vehicle starts), ``SPACING_M`` apart, each a little north or south of
  the line, with a range of 0.75 to 0.95 of the spacing: neighbouring ranges
  always overlap by half the spacing or more, so some station is always in
  range and a handover has room to be prepared;
- the vehicle's speed (one leg between two stations in 1.5 to 4 s: missions
  here last a few seconds of virtual time) and the policy's thresholds,
  scaled to the corridor (margin up to a tenth of the spacing, dwell up to a
  tenth of a leg's time, the predictive lead 0.2 to 0.6 of it).

The radio is the link emulator's (``link/radio.py``): every
``POSITION_PERIOD_S`` ``radio_tick`` reads the vehicle's ground-truth
position and asks each station's ``RadioRange.covers``; a controller whose
station does not cover the vehicle is cut from the drone (the network's
partition machinery: its drone connection breaks, and nothing passes until
the vehicle is back in range), one that covers it again is healed. As in the
testbed the radio and the policy share no state: the policy measures the
same distance from its own fix (``policy.distance_m``), the radio from the
position it reads.

Simplifications: the vehicle flies the corridor whatever the mission's
flight commands say (they are counted, not flown); the leg it flies
(``Fix.leg_to``) is the corridor's end; its altitude is not modelled. A
``hold`` stops it where it is until the drone resumes it or the master's
Goto (or a command that ends a leg) reaches the vehicle, as a real
autopilot leaves hold mode on a new command.
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from typing import TYPE_CHECKING

from baton.controller.protocol import State
from baton.drone.policy import Fix, PolicyParams, Station
from baton.link.radio import POSITION_PERIOD_S, RadioRange
from baton.sdk import Position, offset
from baton.sim.network import DRONE

if TYPE_CHECKING:
    from baton.sim.world import World

# Where the corridor begins (the PX4/ArduPilot default home), and its stations' spacing.
ORIGIN = Position(47.397742, 8.545594)
SPACING_M = 100.0


@dataclass(frozen=True)
class Placed:
    """One station as drawn: where along the corridor, and its range."""

    cid: int
    east_m: float
    north_m: float
    range_m: float


class Corridor:
    """The stations, the vehicle's flight along them, and the radio that follows it."""

    def __init__(self, world: World, policy: str) -> None:
        self.world = world
        rng = random.Random(f"policy {world.seed}")
        order = world.ring[1:]
        rng.shuffle(order)
        order = [world.ring[0], *order]
        self.placed = [
            Placed(
                cid,
                k * SPACING_M,
                rng.uniform(-0.1, 0.1) * SPACING_M,
                rng.uniform(0.75, 0.95) * SPACING_M,
            )
            for k, cid in enumerate(order)
        ]
        self.stations = {
            p.cid: Station(p.cid, offset(ORIGIN, p.north_m, p.east_m), p.range_m)
            for p in self.placed
        }
        self.radios = {
            cid: RadioRange(s.location.latitude_deg, s.location.longitude_deg, s.range_m)
            for cid, s in self.stations.items()
        }
        self.length_m = (len(order) - 1) * SPACING_M
        self.leg_s = rng.uniform(1.5, 4.0)
        self.speed_m_s = SPACING_M / self.leg_s
        self.params = PolicyParams(
            policy,
            margin_m=rng.uniform(0.0, 0.1) * SPACING_M,
            dwell_s=rng.uniform(0.0, 0.1) * self.leg_s,
            lead_s=rng.uniform(0.2, 0.6) * self.leg_s,
            # A master's link down while in range is lost after the takeover time, as
            # the takeover watch counts it (drone/cli.py's policy_settings).
            link_lost_after_s=world.takeover_after,
        )
        self.end = offset(ORIGIN, 0.0, self.length_m)
        # The vehicle: metres flown (out and back) as of ``since``, and whether it holds.
        self._flown_m = 0.0
        self._since = 0.0
        self.held = False
        self.holds = 0
        # Controllers whose station covers the vehicle, as the radio last read it.
        self.covered: set[int] = set()
        self._ticking = False

    # -- the vehicle --------------------------------------------------------------

    def flown_m(self) -> float:
        """Metres flown so far, out and back (at most twice the corridor's length)."""
        if self.held:
            return self._flown_m
        moved = self.speed_m_s * (self.world.loop.now - self._since)
        return min(2 * self.length_m, self._flown_m + moved)

    def east_m(self) -> float:
        """Metres east of the first station now."""
        flown = self.flown_m()
        return flown if flown <= self.length_m else 2 * self.length_m - flown

    def position(self) -> Position:
        """The vehicle's ground-truth position now."""
        return offset(ORIGIN, 0.0, self.east_m())

    def fix(self) -> Fix:
        """What the drone's telemetry says: position, ground velocity, the leg it flies."""
        flown = self.flown_m()
        out = flown < self.length_m
        moving = not self.held and flown < 2 * self.length_m
        east = (self.speed_m_s if out else -self.speed_m_s) if moving else 0.0
        return Fix(self.position(), 0.0, east, self.end if out else ORIGIN)

    def hold(self) -> None:
        """The vehicle holds where it is (the drone's Hold)."""
        if not self.held:
            self._flown_m, self._since = self.flown_m(), self.world.loop.now
            self.held = True
            self.holds += 1

    def fly_on(self) -> None:
        """The vehicle flies on along the corridor (a resume, or a command of the master)."""
        if self.held:
            self._since, self.held = self.world.loop.now, False

    # -- the radio (link/radio.py) -----------------------------------------------

    def start(self) -> None:
        """The radio's first reading: controllers out of range start cut from the drone
        (nothing to break yet), then it reads again every POSITION_PERIOD_S."""
        self.covered = self._covering()
        for cid in self.stations:
            if cid not in self.covered:
                self.world.net.cut(cid, DRONE, break_links=False)
        self.tick()

    def tick(self) -> None:
        """Starts the radio's readings if they are not running (they stop, to let a run
        end, once no program has anything left to do and no preparation is under way)."""
        if not self._ticking:
            self._ticking = True
            self.world.loop.after(POSITION_PERIOD_S, self._read)

    def _read(self) -> None:
        """LinkProxy's range check: a station that stopped covering the vehicle cuts its
        controller's drone link (open connections reset, new ones refused); one that
        covers it again lets it through."""
        self._ticking = False
        world = self.world
        covered = self._covering()
        for cid in sorted(self.covered - covered):
            world.trace(f"radio: {cid} out of range ({self._where(cid)})")
            world.net.cut(cid, DRONE)
        for cid in sorted(covered - self.covered):
            world.trace(f"radio: {cid} in range ({self._where(cid)})")
            world.net.heal(cid, DRONE)
        changed, self.covered = covered != self.covered, covered
        if changed:  # the programs wait for the stations in range (World.check_start)
            world.check_start()
        if world.mission_open() or world.drone.seq.preparing is not None or self.left_behind():
            self.tick()

    def left_behind(self) -> list[int]:
        """Controllers still ACTIVE as master that the drone's master is not, while the
        vehicle is on its way: a master taken over out of range hears of it only once the
        vehicle is back in its range (its Connect refused), so the flight goes on."""
        if self.flown_m() >= 2 * self.length_m:
            return []
        master = self.world.drone.seq.master
        return [
            c.id
            for c in self.world.live_controllers()
            if c.id != master and c.protocol.state is State.ACTIVE
        ]

    def _covering(self) -> set[int]:
        where = self.position()
        return {
            cid
            for cid, radio in self.radios.items()
            if radio.covers(where.latitude_deg, where.longitude_deg)
        }

    def _where(self, cid: int) -> str:
        where = self.position()
        radio = self.radios[cid]
        metres = radio.distance_m(where.latitude_deg, where.longitude_deg)
        return f"{metres:.0f} m of {radio.range_m:.0f} m, {self.east_m():.0f} m east"

    def describe(self) -> str:
        """One line for the summary."""
        stations = ", ".join(f"{p.cid}@{p.east_m:.0f}m/r{p.range_m:.0f}" for p in self.placed)
        p = self.params
        return (
            f"{p.name} policy, corridor {stations}, {self.speed_m_s:.0f} m/s, margin "
            f"{p.margin_m:.0f} m, dwell {p.dwell_s:.2f}s, lead {p.lead_s:.2f}s"
        )

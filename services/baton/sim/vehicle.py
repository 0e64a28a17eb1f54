"""The simulation's ground truth: the vehicle and the camera the simulated drone acts on.

``SimVehicle`` and ``SimCamera`` record every read, flight command and
picture they act on, by request, below every piece of baton's bookkeeping,
as ``baton.effects`` does for the sim vehicle and the camera. The oracles
count there, not in the audit.
"""

from __future__ import annotations

from dataclasses import dataclass

from baton.drone.safety import FLY, HOLD, LAND, RTL

# The vehicle's flight mode after each command, as MAVSDK names the sim vehicle's (PX4's:
# a reposition flies in Hold).
MODE_AFTER = {FLY: "HOLD", HOLD: "HOLD", LAND: "LAND", RTL: "RETURN_TO_LAUNCH"}


@dataclass(frozen=True)
class Acted:
    """One thing the vehicle or the camera did: when, for which request, and what it answered."""

    time: float
    tag: bytes  # the request bytes (unique per mission call for commands and pictures)
    reqnr: int
    reply: bytes


class SimVehicle:
    """The autopilot: answers reads, acts on flight commands, and counts both.

    ``connected`` is False during an outage: the drone then refuses every
    Mobility request UNAVAILABLE without reaching the vehicle. With a GCS time
    (``gcs_timeout_s``) it keeps the autopilot's own GCS failsafe: a drone service
    silent that long finds it returned and landed (``gcs_failsafe``, ``land``).
    """

    def __init__(self, battery_drain_pct_s: float = 0.0, gcs_timeout_s: float = 0.0) -> None:
        self.connected = True
        self.battery_drain_pct_s = battery_drain_pct_s
        # The autopilot's own GCS failsafe (safety.autopilot_gcs_timeout): with no word from
        # the drone service for this long, the vehicle returns and lands by itself; 0: none.
        self.gcs_timeout_s = gcs_timeout_s
        # Since when the drone service is silent (None: it speaks), and whether the vehicle
        # is on the ground by its own decision (its GCS failsafe landed it).
        self.silent_since: float | None = None
        self.landed = False
        # Whether the mission's commands have it flying: since a flight command (a takeoff,
        # a goto), until one that lands or returns it.
        self.flying = False
        # When the GCS failsafe took the vehicle over and when it landed it.
        self.gcs_failsafes: list[float] = []
        self.landings: list[float] = []
        self.commands: list[Acted] = []
        self.reads: dict[int, list[Acted]] = {}
        # The failsafe actions the drone commanded (no request's: the oracles keep them
        # apart), and the operator's resumes, as (time, what).
        self.failsafes: list[tuple[float, str]] = []
        self.resumes: list[float] = []
        # Every operator command the drone took, as (time, command, what the vehicle
        # was told): a pause holds, an abort returns or lands, a resume may fly on.
        self.operator: list[tuple[float, str, str]] = []
        # Its flight mode, and each time the autopilot took it over (time, mode).
        self.mode = "HOLD"
        self.takeovers: list[tuple[float, str]] = []
        self._serial = 0

    def obey(self, action: str | None) -> None:
        """The flight mode a command for ``action`` (``safety.FLY``, ...) puts it in; a
        flight command takes a vehicle its GCS failsafe landed back into the air."""
        if action is not None:
            self.mode = MODE_AFTER[action]
        if action == FLY:
            self.flying, self.landed = True, False
        elif action in (LAND, RTL):
            self.flying = False

    def in_air(self, flying: bool) -> bool:
        """Whether it is armed and in the air, ``flying`` the mission's (the simulation
        models no take-off nor landing of the mission's own), unless it landed by itself."""
        return flying and not self.landed

    def gcs_silent(self, now: float) -> float | None:
        """The drone service went silent at ``now``: when the GCS failsafe falls due if it
        is still silent then (None: the vehicle has none)."""
        self.silent_since = now
        return now + self.gcs_timeout_s if self.gcs_timeout_s > 0 else None

    def gcs_heard(self) -> None:
        """The drone service speaks again (its heartbeats: it restarted)."""
        self.silent_since = None

    def gcs_failsafe(self, now: float, silent_since: float, flying: bool) -> bool:
        """The GCS failsafe's timer for the silence that began at ``silent_since`` ran
        out: a vehicle the mission flies returns (``RETURN_TO_LAUNCH``) if the drone
        service is still silent since then (one landing or returning goes on doing so).
        True if it did (it lands after its return)."""
        if self.silent_since != silent_since or not (self.flying and self.in_air(flying)):
            return False
        self.take_over(now, "RETURN_TO_LAUNCH")
        self.gcs_failsafes.append(now)
        return True

    def land(self, now: float) -> None:
        """The return ends on the ground, disarmed."""
        self.landed = True
        self.landings.append(now)

    def take_over(self, now: float, mode: str) -> None:
        """The autopilot's own decision (a failsafe of its own, a pilot): ``mode``."""
        self.mode = mode
        self.takeovers.append((now, mode))

    def battery(self, now: float) -> float:
        """The battery left at ``now``, percent (drained at a constant rate from 100)."""
        return max(0.0, 100.0 - self.battery_drain_pct_s * now)

    def act(self, now: float, reqnr: int, method: str, request: bytes) -> bytes:
        """A flight command reaches the vehicle; the vehicle acts on it."""
        self._serial += 1
        reply = b"%s %s: done #%d" % (method.encode(), request, self._serial)
        self.commands.append(Acted(now, request, reqnr, reply))
        return reply

    def read(self, now: float, reqnr: int, method: str) -> bytes:
        """Telemetry read for request ``reqnr``."""
        self._serial += 1
        reply = b"%s @%.6f #%d" % (method.encode(), now, self._serial)
        self.reads.setdefault(reqnr, []).append(Acted(now, b"", reqnr, reply))
        return reply


class SimCamera:
    """The camera: takes a picture (a large reply) per request it is given, and counts it,
    and those taken where the vehicle's place was not known (its link out when the
    camera read it, as ``Camera.TakePicture`` reads it first)."""

    def __init__(self) -> None:
        self.pictures: list[Acted] = []
        self.unplaced: list[Acted] = []

    def take(self, now: float, reqnr: int, request: bytes, size: int, placed: bool) -> bytes:
        """One picture of ``size`` bytes; ``placed``: the vehicle's place was known."""
        head = b"picture for %s #%d;" % (request, len(self.pictures) + 1)
        reply = head + bytes(max(0, size - len(head)))
        self.pictures.append(Acted(now, request, reqnr, reply))
        if not placed:
            self.unplaced.append(self.pictures[-1])
        return reply

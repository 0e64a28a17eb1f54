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
    Mobility request UNAVAILABLE without reaching the vehicle.
    """

    def __init__(self, battery_drain_pct_s: float = 0.0) -> None:
        self.connected = True
        self.battery_drain_pct_s = battery_drain_pct_s
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
        """The flight mode a command for ``action`` (``safety.FLY``, ...) puts it in."""
        if action is not None:
            self.mode = MODE_AFTER[action]

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
    """The camera: takes a picture (a large reply) per request it is given, and counts it."""

    def __init__(self) -> None:
        self.pictures: list[Acted] = []

    def take(self, now: float, reqnr: int, request: bytes, size: int) -> bytes:
        """One picture of ``size`` bytes."""
        head = b"picture for %s #%d;" % (request, len(self.pictures) + 1)
        reply = head + bytes(max(0, size - len(head)))
        self.pictures.append(Acted(now, request, reqnr, reply))
        return reply

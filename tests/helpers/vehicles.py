"""The vehicle an end-to-end test flies, and what that vehicle itself says it did.

The safety net's end-to-end tests run on the embedded sim vehicle and, where a build
is at hand (``BATON_SITL_BINARY``, else ``arducopter`` on PATH), on ArduPilot Copter
SITL: ``VEHICLES`` parametrizes a test over both and ``on_vehicle`` puts its plan on
one (a SITL variant without a build skips, saying how to point baton at one).

The sim vehicle witnesses in its effects file. SITL keeps none: its witness is the
drone's telemetry log (``Tlog``), every MAVLink frame between the drone and the
autopilot, both ways, stamped with the wall time it crossed the drone's relay. The
autopilot's own HEARTBEATs say its flight mode (ArduCopter's custom_mode by pymavlink's
names: GUIDED 4, LOITER 5, RTL 6, LAND 9, BRAKE 17) and whether it is armed; a frame
from any other system is one that reached the vehicle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import pytest
from autopilots import SKIP_REASON, ModeReport, mode_report, sitl_binary
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega

from baton.drone.tlog import tlog_records
from baton.testbed.local import TLOG_GLOB, LocalTestbed, TestbedPlan

mavlink = mavutil.mavlink
VEHICLES = ["sim", pytest.param("sitl", marks=pytest.mark.sitl)]
# ArduCopter's flight modes: name by number (pymavlink's table), number by name.
COPTER_MODE_NAMES: dict[int, str] = mavutil.mode_mapping_acm
COPTER_MODES = {name: number for number, name in COPTER_MODE_NAMES.items()}
# The commands that fly the vehicle or change its mode; reads, parameters, message
# rates and the fence upload do not.
FLIGHT_COMMANDS = frozenset(
    {
        mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
        mavlink.MAV_CMD_NAV_TAKEOFF,
        mavlink.MAV_CMD_NAV_LAND,
        mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH,
        mavlink.MAV_CMD_NAV_LOITER_UNLIM,
        mavlink.MAV_CMD_NAV_WAYPOINT,
        mavlink.MAV_CMD_DO_REPOSITION,
        mavlink.MAV_CMD_DO_SET_MODE,
        mavlink.MAV_CMD_DO_CHANGE_SPEED,
        mavlink.MAV_CMD_DO_PAUSE_CONTINUE,
    }
)
POSITION_TARGETS = frozenset({"SET_POSITION_TARGET_GLOBAL_INT", "SET_POSITION_TARGET_LOCAL_NED"})
# MISSION_ITEM(_INT).current: a guided-mode goto, not an item of an uploaded list.
GUIDED_ITEM = 2


def skip_without_sitl(vehicle: str) -> None:
    """Skips a SITL variant where no build is found, saying how to point baton at one."""
    if vehicle == "sitl" and sitl_binary() is None:
        pytest.skip(SKIP_REASON)


def on_vehicle(plan: TestbedPlan, vehicle: str) -> TestbedPlan:
    """``plan`` flown on ``vehicle`` ("sim": as it is; "sitl": on the SITL build found),
    or a skip saying how to point baton at a build where there is none."""
    skip_without_sitl(vehicle)
    if vehicle == "sim":
        return plan
    return replace(plan, vehicle=vehicle, sitl_binary=sitl_binary())


async def gotos_served(testbed: LocalTestbed) -> int:
    """The Gotos the drone has served (its audit): on any vehicle."""
    audit = (await testbed.snapshot()).drone.audit
    return sum(a.method.endswith("/Goto") for a in audit)


@dataclass(frozen=True)
class Sent:
    """A flight command that reached the vehicle: when, what (``MAV_CMD_NAV_LAND``,
    ``MAV_CMD_DO_SET_MODE RTL``, ``SET_MODE BRAKE``, ``SET_POSITION_TARGET_GLOBAL_INT``),
    and from which system (the drone's, a ground station's)."""

    at: float
    what: str
    system: int

    @property
    def returns(self) -> bool:
        """Whether it sends the vehicle home."""
        return self.what.endswith(("RETURN_TO_LAUNCH", " RTL"))

    @property
    def lands(self) -> bool:
        """Whether it lands the vehicle where it is."""
        return self.what.endswith(("MAV_CMD_NAV_LAND", " LAND"))


def _mode_name(number: float) -> str:
    return COPTER_MODE_NAMES.get(int(number), f"mode {number:g}")


def flight_command(message: Any) -> str | None:
    """What ``message`` commands the vehicle to do (``Sent.what``); None for any other."""
    kind = message.get_type()
    if kind in ("COMMAND_LONG", "COMMAND_INT") and message.command in FLIGHT_COMMANDS:
        name = mavlink.enums["MAV_CMD"][message.command].name
        if message.command == mavlink.MAV_CMD_DO_SET_MODE:
            return f"{name} {_mode_name(message.param2)}"
        return str(name)
    if kind == "SET_MODE":
        return f"SET_MODE {_mode_name(message.custom_mode)}"
    if kind in POSITION_TARGETS:
        return str(kind)
    if kind in ("MISSION_ITEM", "MISSION_ITEM_INT") and message.current == GUIDED_ITEM:
        return f"{kind} guided"
    return None


class Tlog:
    """The drone's telemetry logs in a testbed's workdir (TLOG_GLOB, one per drone
    process), read as they grow: each call reads only what was written since."""

    def __init__(self, workdir: Path) -> None:
        self.workdir = workdir
        self._read: dict[Path, int] = {}
        self._parsers: dict[Path, ardupilotmega.MAVLink] = {}
        self._messages: list[Any] = []  # each with its wall time as ``_timestamp``

    def _refresh(self) -> list[Any]:
        for path in sorted(self.workdir.glob(TLOG_GLOB)):
            offset = self._read.get(path, 0)
            with path.open("rb") as log:
                log.seek(offset)
                records, used = tlog_records(log.read())
            self._read[path] = offset + used
            parser = self._parsers.get(path)
            if parser is None:  # robust: a frame of a dialect it lacks is skipped
                parser = self._parsers[path] = ardupilotmega.MAVLink(None)
                parser.robust_parsing = True
            for at, frame in records:
                for message in parser.parse_buffer(frame) or []:
                    if message.get_type() != "BAD_DATA":
                        message._timestamp = at
                        self._messages.append(message)
        return self._messages

    def messages(self, *types: str) -> list[Any]:
        """Every message of ``types`` in the logs, in order (written so far)."""
        return [m for m in self._refresh() if m.get_type() in types]

    def modes(self) -> list[ModeReport]:
        """What the autopilot said of itself in its HEARTBEATs, in order."""
        reports = (mode_report(m, m._timestamp) for m in self.messages("HEARTBEAT"))
        return [r for r in reports if r is not None]

    def first_mode(self, mode: str, after: float = 0.0) -> ModeReport | None:
        """The autopilot's first report of ``mode`` after wall time ``after``; None yet."""
        return next((r for r in self.modes() if r.mode == mode and r.at > after), None)

    def entered(self, mode: str) -> list[ModeReport]:
        """Each time the autopilot entered ``mode`` (its first report of it after another)."""
        reports = self.modes()
        return [
            r
            for before, r in zip([None, *reports], reports, strict=False)
            if r.mode == mode and (before is None or before.mode != mode)
        ]

    def autopilot_system(self) -> int:
        """The autopilot's MAVLink system id, from its HEARTBEATs (ArduPilot's default: 1)."""
        for message in self.messages("HEARTBEAT"):
            if mode_report(message, 0.0) is not None:
                return int(message.get_srcSystem())
        return 1

    def sent(self, after: float = 0.0) -> list[Sent]:
        """The flight commands that reached the vehicle after wall time ``after``, in order
        (by anyone but the autopilot itself: the drone, a ground station it forwarded)."""
        autopilot = self.autopilot_system()
        found = []
        for message in self._refresh():
            if message._timestamp <= after or message.get_srcSystem() == autopilot:
                continue
            if (what := flight_command(message)) is not None:
                found.append(Sent(message._timestamp, what, message.get_srcSystem()))
        return found

    def battery_remaining(self) -> list[tuple[float, int]]:
        """The autopilot's own estimate of its battery (SYS_STATUS.battery_remaining, %),
        with the wall time it said it; -1 (no estimate) left out."""
        return [
            (m._timestamp, int(m.battery_remaining))
            for m in self.messages("SYS_STATUS")
            if m.battery_remaining >= 0
        ]

    def ground_speed_m_s(self) -> float:
        """The autopilot's latest ground speed (GLOBAL_POSITION_INT); nan before one."""
        positions = self.messages("GLOBAL_POSITION_INT")
        if not positions:
            return math.nan
        return math.hypot(positions[-1].vx, positions[-1].vy) / 100

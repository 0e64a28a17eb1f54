"""The battery fault's way into the vehicle: ArduPilot's ``MAV_CMD_BATTERY_RESET``.

``baton testbed --fault battery:sim-vehicle@...,to=15%`` must change what the vehicle
itself reads, so that the drone learns it from the vehicle's telemetry as it would a
real pack running low. The testbed speaks MAVLink to the vehicle's own port as a second
ground station (the drone service stays its GCS: this one sends no HEARTBEAT, so no
link-loss watch counts it, and it uses a system id of its own, ``TESTBED_SYSTEM_ID``)
and sends the command a real ArduPilot takes to set a battery monitor's remaining
percentage: param1 the batteries (bit 0: the first), param2 the percentage (ArduPilot's
own autotest lowers SITL's battery so). The vehicle reads that from then on and drains
on from there. Then it asks the vehicle for BATTERY_STATUS once, so the fault's record
says what the vehicle reads, in its words.

With MAVLink signing (``drone.mavlink_key``) every frame is signed with the vehicle's
key, and only frames signed with it are believed, as the drone's relay does.

Why not a parameter: ArduPilot SITL's battery simulation parameters (SIM_BATT_VOLTAGE,
SIM_BATT_CAP_AH) move the simulated pack's voltage, not the remaining percentage its
battery monitor counts and the drone reads; PX4 SITL's battery simulator drains towards
SIM_BAT_MIN_PCT over SIM_BAT_DRAIN seconds instead of reading a value at once. The
testbed sends the command to its sim vehicle only (``faults.py`` refuses ``battery:sitl``).
"""

from __future__ import annotations

import math
import select
import socket
import time
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from baton import signing

# The testbed's MAVLink system id as a ground station: neither the drone's (245 unless
# configured) nor a vehicle's, so an autopilot's GCS failsafe (SYSID_MYGCS) never counts it.
TESTBED_SYSTEM_ID = 252
TESTBED_COMPONENT_ID = mavlink.MAV_COMP_ID_MISSIONPLANNER
# ardupilotmega.xml's command; param1 the battery mask (bit 0: the first), param2 the percentage.
MAV_CMD_BATTERY_RESET = mavlink.MAV_CMD_BATTERY_RESET
FIRST_BATTERY = 1
# A copy of an unanswered command goes after this long (MAVSDK's pace), its
# ``confirmation`` one higher; the vehicle acts on the first it gets, once.
RETRY_S = 0.5
# How long the vehicle has to answer at all: a loaded machine's vehicle thread is late.
ANSWER_TIMEOUT_S = 10.0


class BatteryResetError(RuntimeError):
    """The vehicle did not take the reset, or did not answer; the message says which."""


def reset_battery(
    url: str,
    percent: float,
    key: bytes | None = None,
    target_system: int = 1,
    timeout_s: float = ANSWER_TIMEOUT_S,
) -> int:
    """Sets the battery of the vehicle at ``url`` (``udpout://HOST:PORT``, the sim
    vehicle's) to ``percent`` with MAV_CMD_BATTERY_RESET, signed with ``key`` if given,
    and returns the percentage it reads then (its BATTERY_STATUS); BatteryResetError if
    it refused or did not answer within ``timeout_s``. Blocking: call it from a thread."""
    if not (math.isfinite(percent) and 0.0 <= percent <= 100.0):
        raise ValueError(f"battery percentage {percent} is not from 0 to 100 %")
    host, port = _udp_address(url)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.connect((host, port))
        link = _Link(sock, key, timeout_s)
        ack = link.command(MAV_CMD_BATTERY_RESET, target_system, FIRST_BATTERY, percent)
        if ack.result != mavlink.MAV_RESULT_ACCEPTED:
            result = mavlink.enums["MAV_RESULT"][ack.result].name
            raise BatteryResetError(f"the vehicle at {url} refused MAV_CMD_BATTERY_RESET: {result}")
        link.command(
            mavlink.MAV_CMD_REQUEST_MESSAGE, target_system, mavlink.MAVLINK_MSG_ID_BATTERY_STATUS
        )
        return int(link.receive("BATTERY_STATUS").battery_remaining)


def _udp_address(url: str) -> tuple[str, int]:
    scheme, _, rest = url.partition("://")
    host, _, port = rest.rpartition(":")
    if scheme != "udpout" or not host or not port.isdigit():
        raise ValueError(f"vehicle URL {url!r}: expected udpout://HOST:PORT (the sim vehicle's)")
    return host, int(port)


class _Link:
    """One ground station's MAVLink 2 over a connected UDP socket, with a deadline."""

    def __init__(self, sock: socket.socket, key: bytes | None, timeout_s: float) -> None:
        self.sock = sock
        self.deadline = time.monotonic() + timeout_s
        self.timeout_s = timeout_s
        self.signed = key is not None
        self.mav = mavlink.MAVLink(
            self, srcSystem=TESTBED_SYSTEM_ID, srcComponent=TESTBED_COMPONENT_ID
        )
        self.mav.robust_parsing = True
        if key is not None:
            signing.enable(self.mav, key, sign_outgoing=True)
        self.refused = 0  # frames whose signature was not the key's

    def write(self, data: bytes) -> None:
        """pymavlink's file: each frame one datagram."""
        self.sock.send(data)

    def command(self, command: int, target_system: int, *params: float) -> Any:
        """COMMAND_LONG ``command`` (missing params 0) until its COMMAND_ACK comes."""
        padded = [*params, *[0.0] * (7 - len(params))]
        for confirmation in range(256):
            self.mav.command_long_send(target_system, 1, command, confirmation, *padded)
            retry_at = min(time.monotonic() + RETRY_S, self.deadline)
            ack = self.receive("COMMAND_ACK", until=retry_at, command=command)
            if ack is not None:
                return ack
            if time.monotonic() >= self.deadline:
                break
        raise BatteryResetError(self._silence(f"no COMMAND_ACK for command {command}"))

    def receive(self, kind: str, until: float | None = None, command: int | None = None) -> Any:
        """The next ``kind`` message (a COMMAND_ACK of ``command``) before ``until`` (None:
        the deadline, then BatteryResetError)."""
        end = self.deadline if until is None else until
        while (left := end - time.monotonic()) > 0:
            readable, _, _ = select.select([self.sock], [], [], left)
            if not readable:
                continue
            try:
                data = self.sock.recv(65535)
            except ConnectionRefusedError:
                raise BatteryResetError("nothing listens on the vehicle's port") from None
            for msg in self.mav.parse_buffer(data) or []:
                if msg.get_msgId() == mavlink.MAVLINK_MSG_ID_BAD_DATA:
                    self.refused += msg.reason == signing.REFUSED_REASON
                elif msg.get_type() == kind and (command is None or msg.command == command):
                    return msg
        if until is None:
            raise BatteryResetError(self._silence(f"no {kind}"))
        return None

    def _silence(self, what: str) -> str:
        """Why the vehicle said nothing, as far as one can tell from here."""
        why = f"{what} from the vehicle within {self.timeout_s:g} s"
        if self.refused:
            why += f" ({self.refused} of its frames not signed with the testbed's MAVLink key)"
        elif not self.signed:
            why += (
                " (a vehicle that holds a MAVLink key ignores unsigned frames: drone.mavlink_key)"
            )
        return why

"""A pilot switching the vehicle's flight mode behind the drone's back (the sim vehicle,
or ArduPilot SITL through its second MAVLink port).

As the autopilot sees it, a pilot's RC mode switch, a second ground station's mode
command and the autopilot's own failsafe are the same thing: a mode change the drone
service did not send. This helper sends one from a MAVLink client of its own, straight
to the vehicle's port (never through the drone), and waits for the vehicle's answer.
"""

from __future__ import annotations

import asyncio
import time

from pymavlink import mavutil
from waiting import STEP_TIMEOUT_S

mavlink = mavutil.mavlink
# PX4's custom modes, as the sim vehicle speaks them (main mode AUTO and its sub modes).
PX4_AUTO = 4
PX4_AUTO_RTL, PX4_AUTO_LAND = 5, 6
PILOT_SYSTEM_ID = 250


def _switch(url: str, main: int, sub: int, timeout_s: float) -> None:
    link = mavutil.mavlink_connection(
        url.replace("udpout://", "udpout:"), source_system=PILOT_SYSTEM_ID
    )
    try:
        link.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        link.mav.command_long_send(
            1,
            1,
            mavlink.MAV_CMD_DO_SET_MODE,
            0,
            mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
            main,
            sub,
            0,
            0,
            0,
            0,
        )
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            ack = link.recv_match(type="COMMAND_ACK", blocking=True, timeout=left)
            if ack is not None and ack.command == mavlink.MAV_CMD_DO_SET_MODE:
                assert ack.result == mavlink.MAV_RESULT_ACCEPTED, ack
                return
        raise AssertionError(f"the vehicle at {url} did not acknowledge the mode switch")
    finally:
        link.close()


async def switch_mode(url: str, sub: int, timeout_s: float = STEP_TIMEOUT_S) -> None:
    """Switches the sim vehicle at ``url`` (udpout://HOST:PORT) to PX4's AUTO ``sub`` mode
    (``PX4_AUTO_RTL``, ``PX4_AUTO_LAND``), as a pilot would; fails unless it accepts."""
    await asyncio.to_thread(_switch, url, PX4_AUTO, sub, timeout_s)


async def switch_ardupilot_mode(url: str, mode: str, timeout_s: float = STEP_TIMEOUT_S) -> None:
    """Switches ArduCopter at ``url`` (pymavlink's ``tcp:HOST:PORT``: SITL's SERIAL1, not
    the drone's port) to its flight ``mode`` by name ("RTL", "LAND"), as a pilot would;
    fails unless it accepts."""
    number = mavutil.mode_mapping_byname(mavlink.MAV_TYPE_QUADROTOR)[mode]
    await asyncio.to_thread(_switch, url, number, 0, timeout_s)

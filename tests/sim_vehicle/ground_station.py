"""A pymavlink ground station for the sim vehicle: what any MAVLink client sees, no MAVSDK.

Every wait has a deadline and fails with what did arrive, so a test never
sleeps and hopes. Everything received is kept in arrival order in
``received``, so a test can also say what must *not* have come, or in which
order things came.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

from pymavlink import mavutil

from .sim_process import STEP_TIMEOUT_S

mavlink = mavutil.mavlink
UNSET = math.nan  # MAVLink's "unset" command parameter


class GroundStation:
    """A pymavlink connection to a vehicle on ``127.0.0.1:port`` (system id 255)."""

    def __init__(self, port: int, target_system: int = 1) -> None:
        self.link = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255)
        self.target_system = target_system
        self.received: list[Any] = []

    def __enter__(self) -> GroundStation:
        return self

    def __exit__(self, *exc: object) -> None:
        self.link.close()

    def say_hello(self) -> None:
        """Sends a heartbeat, so the vehicle learns our address, and waits for its own."""
        self.link.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        self.receive("HEARTBEAT")

    def receive(
        self,
        kind: str,
        condition: Callable[[Any], bool] | None = None,
        timeout_s: float = STEP_TIMEOUT_S,
    ) -> Any:
        """The next message of ``kind`` (meeting ``condition``); fails after the deadline."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            msg = self.link.recv_match(blocking=True, timeout=left)
            if msg is None:
                continue
            self.received.append(msg)
            if msg.get_type() == kind and (condition is None or condition(msg)):
                return msg
        kinds = sorted({m.get_type() for m in self.received})
        raise AssertionError(f"no {kind} within {timeout_s} s; received so far: {kinds}")

    def command(self, command: int, *params: float, confirmation: int = 0) -> Any:
        """Sends COMMAND_LONG (missing parameters 0) and returns its COMMAND_ACK.

        ``confirmation`` > 0 is how a ground station marks a retransmission.
        """
        assert len(params) <= 7
        padded = [*params, *[0.0] * (7 - len(params))]
        self.link.mav.command_long_send(self.target_system, 1, command, confirmation, *padded)
        return self.receive("COMMAND_ACK", lambda ack: ack.command == command)

    def command_int(
        self, command: int, *params: float, x: int = 0, y: int = 0, z: float = UNSET
    ) -> Any:
        """Sends COMMAND_INT (see ``send_command_int``) and returns its COMMAND_ACK."""
        self.send_command_int(command, *params, x=x, y=y, z=z)
        return self.receive("COMMAND_ACK", lambda ack: ack.command == command)

    def send_command_int(
        self, command: int, *params: float, x: int = 0, y: int = 0, z: float = UNSET
    ) -> None:
        """Sends COMMAND_INT (MAV_FRAME_GLOBAL) with param1..4 (missing ones 0), x, y
        (degrees * 1e7; 0 unset) and z (unset by default), without waiting for its ACK."""
        assert len(params) <= 4
        padded = [*params, *[0.0] * (4 - len(params))]
        self.link.mav.command_int_send(
            self.target_system, 1, mavlink.MAV_FRAME_GLOBAL, command, 0, 0, *padded, x, y, z
        )

    def set_interval(self, msg_id: int, interval_us: float) -> int:
        """MAV_CMD_SET_MESSAGE_INTERVAL; the result of its COMMAND_ACK."""
        ack = self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us)
        return int(ack.result)

    def received_since(self, msg: Any) -> list[Any]:
        """What arrived after ``msg`` (a message this station received)."""
        return self.received[self.index(msg) + 1 :]

    def index(self, msg: Any) -> int:
        """Where ``msg`` is in ``received`` (by identity: equal messages can repeat)."""
        return next(i for i, seen in enumerate(self.received) if seen is msg)

    def kinds_received(self) -> set[str]:
        """The message types received so far."""
        return {m.get_type() for m in self.received}

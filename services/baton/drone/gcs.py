"""Ground stations watching live: the autopilot's MAVLink forwarded to GCS endpoints.

The drone service is the autopilot's only MAVLink client, so without this a
QGroundControl or MAVProxy shows nothing while baton flies. ``baton drone
--gcs udp:HOST:PORT`` (or ``drone.gcs`` in the testbed file) sends every frame
the autopilot sends (after the signature check, when signing is on) to each
endpoint, from a UDP socket of its own, as MAVProxy's ``--out`` does; the
station answers to that socket.

What a station sends is never passed to the autopilot as it is:

- watch only (the default): a COMMAND_LONG or COMMAND_INT is answered with a
  COMMAND_ACK ``MAV_RESULT_DENIED`` and a STATUSTEXT saying who controls the
  vehicle; everything else (SET_MODE, MISSION_*, PARAM_SET, manual control,
  heartbeats) is dropped, and counted;
- override allowed (``--gcs-override``, ``drone.gcs_override: true``): a
  command (and SET_MODE) is the operator taking over. It is passed to the
  autopilot, and the mission is paused as by an operator's Pause (the master's
  next request waits at the drone until an operator's Resume, Abort or LandNow:
  ``operator.py``), the vehicle left to the station. MISSION_* is dropped still:
  baton owns the mission.

With MAVLink signing on (``--mavlink-key``), the station must sign with the
same key: an unsigned or badly signed frame from it is refused and counted,
and what the drone itself sends a station (its acknowledgements and status
texts) is signed. The autopilot's own frames reach the station with the
autopilot's signature.

CONTROL_STATUS and MAV_CMD_REQUEST_OPERATOR_CONTROL (development.xml) are
not in pymavlink 2.4.50's dialects, and two layouts of message 512 with
different CRC extras are in use upstream (mavlink/mavlink #2158, #2313): a
station built on the other would drop every frame. So the drone does not
send CONTROL_STATUS: it says who controls the vehicle in a STATUSTEXT
instead, and answers every command by the rule above (docs/operating.md,
"Who controls the vehicle").
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

from pymavlink.dialects.v20 import common as mavlink

from baton import logs
from baton.signing import Signer

# Frames a station sends that are commands to the vehicle (answered, or an override).
COMMANDS = (mavlink.MAVLINK_MSG_ID_COMMAND_LONG, mavlink.MAVLINK_MSG_ID_COMMAND_INT)
# The drone's own frames to a station come from this component of the vehicle's system.
ONBOARD_COMPUTER = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER


class GcsEndpointError(ValueError):
    """A GCS endpoint that cannot be used; the message names it and the fix."""


@dataclass(frozen=True)
class GcsEndpoint:
    """Where a ground station listens (UDP)."""

    host: str
    port: int

    @classmethod
    def parse(cls, text: str) -> GcsEndpoint:
        """``udp:HOST:PORT`` (also ``udp://HOST:PORT``, ``udpout:``), or GcsEndpointError."""
        scheme, _, rest = text.partition(":")
        rest = rest.removeprefix("//")
        host, _, port = rest.rpartition(":")
        if scheme not in ("udp", "udpout") or not host or not port.isdigit():
            raise GcsEndpointError(
                f"GCS endpoint {text!r}: expected udp:HOST:PORT, e.g. udp:127.0.0.1:14550 "
                "(where QGroundControl or MAVProxy listens)"
            )
        if not 0 < int(port) < 65536:
            raise GcsEndpointError(f"GCS endpoint {text!r}: port {port} is not in 1..65535")
        return cls(host, int(port))

    def __str__(self) -> str:
        return f"udp:{self.host}:{self.port}"


class GcsLink:
    """The drone's side of every ground station: forwards, answers, refuses, counts."""

    def __init__(
        self,
        endpoints: list[GcsEndpoint],
        override: bool = False,
        signer: Signer | None = None,
    ) -> None:
        self.endpoints = endpoints
        self.override = override
        # A separate signer (its own link id and clock) for what the drone sends stations.
        self.signer = signer
        self._checker = Signer(signer.key, link_id=1) if signer is not None else None
        # Passes a station's override command on to the autopilot (the relay's way out).
        self.to_vehicle: Callable[[bytes], None] = lambda frame: None
        # Called with the station and the command of an override (the mission pauses).
        self.on_override: Callable[[str, str], None] = lambda station, what: None
        # Which controller is baton's master now, for the status text.
        self.controller: Callable[[], str] = lambda: "?"
        self.forwarded = 0
        self.denied = 0
        self.dropped = 0
        self.refused = 0
        self.overrides = 0
        self._vehicle_system = 1
        self._parser = mavlink.MAVLink(None)
        self._parser.robust_parsing = True
        self._out = mavlink.MAVLink(None, srcSystem=1, srcComponent=ONBOARD_COMPUTER)
        self._transports: list[asyncio.DatagramTransport] = []
        self._log = logs.get_logger("drone.gcs")

    async def start(self) -> None:
        """Opens one UDP socket per station."""
        loop = asyncio.get_running_loop()
        for endpoint in self.endpoints:
            transport, _ = await loop.create_datagram_endpoint(
                lambda e=endpoint: _FromStation(self, e),  # type: ignore[misc]
                remote_addr=(endpoint.host, endpoint.port),
            )
            self._transports.append(transport)
        self._log.info(
            "ground stations",
            endpoints=[str(e) for e in self.endpoints],
            override=self.override,
            signing=self.signer is not None,
        )

    def close(self) -> None:
        for transport in self._transports:
            transport.close()
        self._transports.clear()

    def forward(self, frames: list[bytes]) -> None:
        """The autopilot's frames, to every station (as they came: signed by it, or not)."""
        for frame in frames:
            if len(frame) > 5 and frame[0] == 0xFD:
                self._vehicle_system = frame[5]
            elif len(frame) > 3 and frame[0] == 0xFE:
                self._vehicle_system = frame[3]
            for transport in self._transports:
                transport.sendto(frame)
        self.forwarded += len(frames)

    def received(self, data: bytes, transport: asyncio.DatagramTransport) -> None:
        """Frames from a station: checked, then answered, refused or taken as an override."""
        if self._checker is not None:
            checked = self._checker.check(data)
            if checked.refused:
                self.refused += len(checked.refused)
                self._log.warning(
                    "ground station frames refused: not signed with the mission's key",
                    refused=len(checked.refused),
                    reason=checked.refused[-1],
                )
            frames = checked.accepted
        else:
            frames = [data]
        for frame in frames:
            for msg in self._parser.parse_buffer(frame) or []:
                self._handle(msg, bytes(msg.get_msgbuf()), transport)

    def _handle(self, msg: Any, raw: bytes, transport: asyncio.DatagramTransport) -> None:
        kind = msg.get_msgId()
        if kind == mavlink.MAVLINK_MSG_ID_BAD_DATA:
            return
        if kind not in COMMANDS and kind != mavlink.MAVLINK_MSG_ID_SET_MODE:
            self.dropped += 1  # watch only: nothing else of a station reaches the autopilot
            return
        station = f"ground station {msg.get_srcSystem()}"
        what = (
            mavlink.enums["MAV_CMD"][msg.command].name
            if kind in COMMANDS and msg.command in mavlink.enums["MAV_CMD"]
            else msg.get_type()
        )
        if self.override:
            self.overrides += 1
            self._log.warning("operator override from a ground station", station=station, what=what)
            self.on_override(station, what)
            self.to_vehicle(raw)
            return
        self.denied += 1
        self._log.info("ground station command refused: watch only", station=station, what=what)
        if kind in COMMANDS:
            self._send(
                transport,
                self._out.command_ack_encode(
                    msg.command,
                    mavlink.MAV_RESULT_DENIED,
                    0,
                    0,
                    msg.get_srcSystem(),
                    msg.get_srcComponent(),
                ),
            )
        # STATUSTEXT holds 50 characters: "baton in control, master 12; GCS watch only".
        text = f"baton in control, master {self.controller()}; GCS watch only"
        self._send(
            transport,
            self._out.statustext_encode(mavlink.MAV_SEVERITY_WARNING, text[:50].encode()),
        )

    def _send(self, transport: asyncio.DatagramTransport, msg: Any) -> None:
        self._out.srcSystem = self._vehicle_system
        frame = bytes(msg.pack(self._out))
        if self.signer is not None:
            frame = self.signer.sign_frame(frame)
        transport.sendto(frame)


class _FromStation(asyncio.DatagramProtocol):
    def __init__(self, link: GcsLink, endpoint: GcsEndpoint) -> None:
        self.link = link
        self.endpoint = endpoint
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.DatagramTransport, transport)  # uvloop's is no subclass

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        if self.transport is None:
            return
        try:
            self.link.received(data, self.transport)
        except Exception as exc:  # a station's garbage never stops the drone
            self.link.dropped += 1
            logs.get_logger("drone.gcs").warning(
                "ground station frame not understood", station=str(self.endpoint), error=str(exc)
            )

    def error_received(self, exc: Exception) -> None:
        pass  # "port unreachable" while no station listens yet: it may come

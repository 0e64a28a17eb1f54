"""The MAVLink relay between MAVSDK and the autopilot: signing, and the telemetry log.

MAVSDK talks to the autopilot itself unless the drone signs its MAVLink or
records it; then MAVSDK talks to this relay on a loopback UDP port, and the
relay holds the autopilot link at the vehicle URL.

*Signing* (docs/design.md, Security; ``baton drone --mavlink-key FILE``):
MAVSDK has no message signing (mavlink/MAVSDK#1060). Every frame MAVSDK
sends is signed on its way out (``Signer.sign``); every frame the autopilot
sends is passed to MAVSDK only with a valid signature (``Signer.check``: the
stream's timestamp must move forward, so a recorded frame cannot be played
again). MAVSDK's parser accepts signed frames without checking them.

*The telemetry log* (``baton drone --tlog-dir DIR``, ``drone/tlog.py``):
every packet that crosses the relay, both ways, is teed into the run's
``.tlog`` as it passes: the frames sent to the autopilot as sent (signed, if
signing), and those passed on from it.

The relay speaks the vehicle URLs a drone uses over a network: ``udpin://``
(``udp://``), ``udpout://``, ``tcpout://`` (``tcp://``) and ``tcpin://``. A
TCP link that drops is dialled again every ``RECONNECT_S``, as MAVSDK does,
so an autopilot that reboots is found again. ``serial://`` is refused with a
message: a serial cable on the airframe is the link signing is off for by
default.

Refused frames are counted and shown in GetStatus (``VehicleLink``), and
logged at most every ``REFUSAL_LOG_S``: a wrong key looks like a silent
autopilot otherwise.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass
from urllib.parse import urlsplit

from baton import logs
from baton.drone.gcs import GcsLink
from baton.drone.tlog import MavlinkFramer, TlogWriter
from baton.signing import REFUSAL_LOG_S, Signer

RECONNECT_S = 1.0
SIGNED_SCHEMES = ("udp", "udpin", "udpout", "tcp", "tcpout", "tcpin")


class RelayUrlError(ValueError):
    """A vehicle URL the relay cannot hold; the message names the URL and the fix."""


@dataclass(frozen=True)
class VehicleEndpoint:
    """Where the autopilot is, and which side dials."""

    scheme: str  # udpin, udpout, tcpout, tcpin
    host: str
    port: int

    @classmethod
    def parse(cls, url: str, tlog: bool = False) -> VehicleEndpoint:
        """The endpoint of a MAVSDK vehicle URL, or ``RelayUrlError`` (for signing, or
        with ``tlog`` for recording the telemetry log)."""
        parts = urlsplit(url)
        scheme = {"udp": "udpin", "tcp": "tcpout"}.get(parts.scheme, parts.scheme)
        if parts.scheme == "serial" and tlog:
            raise RelayUrlError(
                f"vehicle URL {url}: the telemetry log is recorded on a UDP or TCP vehicle "
                "link only; leave out --tlog-dir on a serial link"
            )
        if parts.scheme == "serial":
            raise RelayUrlError(
                f"vehicle URL {url}: MAVLink signing is not available on a serial link "
                "(it is the cable on the airframe signing is off for); use a UDP or TCP "
                "vehicle URL, or leave out --mavlink-key"
            )
        try:
            port = parts.port
        except ValueError:
            port = None
        if parts.scheme not in SIGNED_SCHEMES or not parts.hostname or port is None:
            raise RelayUrlError(
                f"vehicle URL {url}: {'the telemetry log' if tlog else 'signing'} needs one of "
                f"{', '.join(s + '://HOST:PORT' for s in SIGNED_SCHEMES)}"
            )
        return cls(scheme, parts.hostname, port)


class MavlinkRelay:
    """MAVSDK (loopback UDP) to the autopilot (vehicle URL): signing and checking with a
    ``key``, recording into ``tlog`` with one."""

    def __init__(
        self,
        vehicle_url: str,
        key: bytes | None = None,
        tlog: TlogWriter | None = None,
        gcs: GcsLink | None = None,
    ) -> None:
        self.vehicle_url = vehicle_url
        # Ground stations (drone/gcs.py): the autopilot's frames go to them too.
        self.gcs = gcs
        self.endpoint = VehicleEndpoint.parse(vehicle_url, tlog=key is None)
        self.signer = Signer(key) if key is not None else None
        self.tlog = tlog
        # Without a signer (which frames what it signs and checks), whole packets are
        # cut out of the stream here: one per datagram to MAVSDK, one per tlog record.
        self._outgoing = MavlinkFramer()
        self._incoming = MavlinkFramer()
        self.signed = 0
        self.refused = 0
        self.last_refusal = ""
        self._mavsdk_address: tuple[str, int] | None = None
        self._local: asyncio.DatagramTransport | None = None
        self._udp: asyncio.DatagramTransport | None = None
        self._udp_peer: tuple[str, int] | None = None
        self._tcp: asyncio.StreamWriter | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._server: asyncio.Server | None = None
        self._refusals_logged_at = 0.0
        self._refusals_unlogged = 0
        self._log = logs.get_logger("drone.relay", vehicle=vehicle_url)

    async def start(self) -> str:
        """Opens both sides; returns the URL MAVSDK should connect to."""
        loop = asyncio.get_running_loop()
        self._local, _ = await loop.create_datagram_endpoint(
            lambda: _Datagrams(self._from_mavsdk), local_addr=("127.0.0.1", 0)
        )
        port = self._local.get_extra_info("sockname")[1]
        end = self.endpoint
        if end.scheme == "udpin":
            self._udp, _ = await loop.create_datagram_endpoint(
                lambda: _Datagrams(self._from_udp_vehicle), local_addr=(end.host, end.port)
            )
        elif end.scheme == "udpout":
            self._udp_peer = (end.host, end.port)
            self._udp, _ = await loop.create_datagram_endpoint(
                lambda: _Datagrams(self._from_udp_vehicle), remote_addr=self._udp_peer
            )
        elif end.scheme == "tcpout":
            self._tasks.append(asyncio.create_task(self._dial(), name="signing-relay dial"))
        else:
            self._server = await asyncio.start_server(self._accepted, end.host, end.port)
        if self.gcs is not None:
            self.gcs.to_vehicle = self._override_to_vehicle
            await self.gcs.start()
        self._log.info(
            "MAVLink relay started",
            mavsdk_port=port,
            signing=self.signer is not None,
            tlog=str(self.tlog.path) if self.tlog else None,
        )
        return f"udpout://127.0.0.1:{port}"

    async def close(self) -> None:
        """Closes both sides."""
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks.clear()
        if self._server is not None:
            self._server.close()
        for transport in (self._local, self._udp):
            if transport is not None:
                transport.close()
        if self._tcp is not None:
            self._tcp.close()
        if self.tlog is not None:
            self.tlog.close()
        if self.gcs is not None:
            self.gcs.close()

    # --- MAVSDK to the autopilot ---------------------------------------------------

    def _from_mavsdk(self, data: bytes, address: tuple[str, int]) -> None:
        self._mavsdk_address = address
        if self.signer is None:
            frames = self._outgoing.frames(data)
        else:
            frames, dropped = self.signer.sign(data)
            for reason in dropped:
                self._log.warning("frame from MAVSDK not sent", reason=reason)
            self.signed += len(frames)
        self._to_vehicle(frames)

    def _override_to_vehicle(self, frame: bytes) -> None:
        """A ground station's command taken as an operator override, on to the autopilot
        as the drone's own (signed, if signing)."""
        if self.signer is not None:
            frame = self.signer.sign_frame(frame)
        self._to_vehicle([frame])

    def _to_vehicle(self, frames: list[bytes]) -> None:
        if self.tlog is not None:
            self.tlog.record(frames)
        for frame in frames:
            if self._udp is not None and self.endpoint.scheme == "udpout":
                self._udp.sendto(frame)  # a connected socket: to the autopilot's address
            elif self._udp is not None and self._udp_peer is not None:
                self._udp.sendto(frame, self._udp_peer)
            elif self._tcp is not None and not self._tcp.is_closing():
                self._tcp.write(frame)

    # --- the autopilot to MAVSDK ---------------------------------------------------

    def _from_udp_vehicle(self, data: bytes, address: tuple[str, int]) -> None:
        if self.endpoint.scheme == "udpin":
            self._udp_peer = address  # answer the autopilot where it sends from
        self._from_vehicle(data)

    def _from_vehicle(self, data: bytes) -> None:
        if self.signer is None:
            frames = self._incoming.frames(data)
        else:
            checked = self.signer.check(data)
            if checked.refused:
                self._refuse(checked.refused)
            frames = checked.accepted
        if self.tlog is not None:
            self.tlog.record(frames)
        if self.gcs is not None:
            self.gcs.forward(frames)
        if self._local is None or self._mavsdk_address is None:
            return  # MAVSDK has not said where it is yet; it heartbeats at once
        for frame in frames:
            self._local.sendto(frame, self._mavsdk_address)

    def _refuse(self, reasons: list[str]) -> None:
        self.refused += len(reasons)
        self.last_refusal = reasons[-1]
        self._refusals_unlogged += len(reasons)
        now = time.monotonic()
        if now - self._refusals_logged_at >= REFUSAL_LOG_S:
            self._log.warning(
                "frames from the autopilot refused: not signed with the drone's key "
                "(is the autopilot's key the one in --mavlink-key?)",
                refused=self._refusals_unlogged,
                total=self.refused,
                reason=self.last_refusal,
            )
            self._refusals_logged_at, self._refusals_unlogged = now, 0

    # --- TCP -------------------------------------------------------------------------

    async def _dial(self) -> None:
        end = self.endpoint
        while True:
            try:
                reader, writer = await asyncio.open_connection(end.host, end.port)
            except OSError as exc:
                self._log.debug("autopilot not reachable", error=str(exc))
                await asyncio.sleep(RECONNECT_S)
                continue
            self._log.info("autopilot link up")
            await self._hold(reader, writer)
            self._log.warning("autopilot link closed; dialling again")
            await asyncio.sleep(RECONNECT_S)

    async def _accepted(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._tcp is not None:
            self._tcp.close()  # the newest autopilot connection wins, as in MAVSDK
        await self._hold(reader, writer)

    async def _hold(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._tcp = writer
        self._incoming = MavlinkFramer()  # a new stream: no half packet of the last one
        try:
            while data := await reader.read(65536):
                self._from_vehicle(data)
        except OSError as exc:
            self._log.debug("autopilot link error", error=str(exc))
        finally:
            if self._tcp is writer:
                self._tcp = None
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()


class _Datagrams(asyncio.DatagramProtocol):
    def __init__(self, received: Callable[[bytes, tuple[str, int]], None]) -> None:
        self._received = received

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self._received(data, addr)

    def error_received(self, exc: Exception) -> None:
        pass  # an ICMP "port unreachable" while the other side is down: it comes back

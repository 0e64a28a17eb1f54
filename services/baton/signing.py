"""MAVLink 2 message signing: the key file, and signing and checking frames.

Signing (docs/design.md, Security) proves that a MAVLink frame was sent by
someone holding the mission's 32-byte secret key, and a timestamp in each
frame stops replays. The drone service's MAVLink stack, MAVSDK, cannot sign
(mavlink/MAVSDK#1060), so the drone runs a relay (``drone/mavlink_relay.py``)
that signs what MAVSDK sends and checks what the autopilot sends; the sim
vehicle checks and signs on its side as ArduPilot does.

``Signer`` is pure (bytes in, bytes out): it signs a frame as received, byte
for byte, without decoding its message, so messages of any dialect pass. The
signed flag is a header byte covered by the frame's CRC, and the CRC's seed
(``crc_extra``) is known only per message type; X.25 is affine, so the new
CRC is the old one XOR the CRC of the difference XOR the CRC of zeros of the
same length, and the seed cancels out.

The rule for frames that arrive is ArduPilot's (``GCS_Signing.cpp``): a frame
is accepted if its signature is right and its timestamp is newer than the
last of its stream (link id, system, component), or, for a stream never seen,
at most a minute older than our clock; RADIO_STATUS and RADIO, which radio
modems inject into the link unsigned, are accepted unsigned.
"""

from __future__ import annotations

import hashlib
import os
import secrets
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

KEY_BYTES = 32
# MAVLink signing timestamps count 10 µs units since 2015-01-01 00:00 UTC.
EPOCH_2015_S = 1420070400
_V2_MAGIC = 0xFD
_SIGNED = mavlink.MAVLINK_IFLAG_SIGNED
_HEADER_LEN = 10
ACCEPTED_UNSIGNED = frozenset({mavlink.MAVLINK_MSG_ID_RADIO_STATUS, mavlink.MAVLINK_MSG_ID_RADIO})
# What pymavlink says of a frame the rule refuses.
REFUSED_REASON = "Invalid signature"
# Refusals are counted, and logged at most this often (wall seconds).
REFUSAL_LOG_S = 5.0
KEY_HINT = "make one with `baton certs mavlink-key FILE` (64 hexadecimal digits, 32 bytes)"


class SigningKeyError(ValueError):
    """A key file that is missing or not a key; the message names the file and the fix."""


def read_key(path: Path) -> bytes:
    """The 32-byte key in ``path`` (64 hexadecimal digits, whitespace ignored)."""
    try:
        text = path.read_text(encoding="ascii").strip()
    except FileNotFoundError:
        raise SigningKeyError(f"MAVLink signing key {path}: no such file; {KEY_HINT}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SigningKeyError(f"MAVLink signing key {path}: cannot read it ({exc})") from None
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != KEY_BYTES:
        raise SigningKeyError(
            f"MAVLink signing key {path}: not {2 * KEY_BYTES} hexadecimal digits; {KEY_HINT}"
        )
    if key == bytes(KEY_BYTES):
        # An all-zero key is how ArduPilot switches signing off.
        raise SigningKeyError(
            f"MAVLink signing key {path}: all zeros turns signing off; {KEY_HINT}"
        )
    return key


def write_key(path: Path) -> bytes:
    """Writes a new random key to ``path`` (mode 0600); refuses to replace one."""
    key = secrets.token_bytes(KEY_BYTES)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise SigningKeyError(
            f"MAVLink signing key {path} exists; remove it first to make a new one "
            "(and install the new one on the autopilot)"
        ) from None
    with os.fdopen(fd, "w", encoding="ascii") as f:
        f.write(key.hex() + "\n")
    return key


def timestamp_now() -> int:
    """The signing clock now: 10 µs units since 2015-01-01."""
    return int((max(time.time(), EPOCH_2015_S) - EPOCH_2015_S) * 100_000)


def enable(mav: Any, key: bytes, *, sign_outgoing: bool) -> None:
    """Turns signing on in a pymavlink ``MAVLink`` object, with the rule above."""
    mav.signing.secret_key = key
    mav.signing.timestamp = timestamp_now()
    mav.signing.sign_outgoing = sign_outgoing
    mav.signing.allow_unsigned_callback = _radio_only


def _x25(data: bytes) -> int:
    crc = mavlink.x25crc(data)
    return int(crc.crc)


@dataclass
class Checked:
    """What ``Signer.check`` made of some bytes: frames to pass on, and why others were not."""

    accepted: list[bytes] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)


class Signer:
    """Signs frames going out and checks frames coming in, for one link."""

    def __init__(self, key: bytes, link_id: int = 0) -> None:
        if len(key) != KEY_BYTES:
            raise ValueError(f"a MAVLink signing key has {KEY_BYTES} bytes, not {len(key)}")
        self.key = key
        self.link_id = link_id
        self._timestamp = timestamp_now()
        # Frames going out are only framed (whole frames from a byte stream).
        self._outgoing = mavlink.MAVLink(None)
        self._outgoing.robust_parsing = True
        # Frames coming in are checked by pymavlink's implementation of the rule.
        self._incoming = mavlink.MAVLink(None)
        self._incoming.robust_parsing = True
        enable(self._incoming, key, sign_outgoing=False)

    def sign(self, data: bytes) -> tuple[list[bytes], list[str]]:
        """Signed frames for the MAVLink 2 frames in ``data``, and why any were dropped."""
        signed: list[bytes] = []
        dropped: list[str] = []
        for msg in self._outgoing.parse_buffer(data) or []:
            raw = bytes(msg.get_msgbuf())
            if msg.get_msgId() == mavlink.MAVLINK_MSG_ID_BAD_DATA:
                dropped.append(f"not a MAVLink frame ({msg.reason})")
            elif raw[0] != _V2_MAGIC:
                dropped.append(f"MAVLink 1 {msg.get_type()} (cannot be signed)")
            else:
                signed.append(self.sign_frame(raw))
        return signed, dropped

    def sign_frame(self, frame: bytes) -> bytes:
        """``frame`` (one whole MAVLink 2 frame) with the signed flag and a signature."""
        if frame[2] & _SIGNED:
            frame = frame[: -mavlink.MAVLINK_SIGNATURE_BLOCK_LEN]
        crc_at = len(frame) - 2
        (old_crc,) = struct.unpack_from("<H", frame, crc_at)
        covered = crc_at  # the header after the magic, the payload, and crc_extra
        difference = bytearray(covered)
        difference[1] = _SIGNED ^ (frame[2] & _SIGNED)
        new_crc = old_crc ^ _x25(bytes(difference)) ^ _x25(bytes(covered))
        head = bytearray(frame[:crc_at])
        head[2] |= _SIGNED
        # The clock never runs backwards and never repeats: a restarted
        # autopilot accepts a new stream only within a minute of its clock.
        self._timestamp = max(self._timestamp + 1, timestamp_now())
        body = bytes(head) + struct.pack("<HB", new_crc, self.link_id)
        body += struct.pack("<Q", self._timestamp)[:6]
        return body + hashlib.sha256(self.key + body).digest()[:6]

    def check(self, data: bytes) -> Checked:
        """The frames in ``data`` that carry a valid signature (or may come unsigned)."""
        checked = Checked()
        for msg in self._incoming.parse_buffer(data) or []:
            if msg.get_msgId() == mavlink.MAVLINK_MSG_ID_BAD_DATA:
                checked.refused.append(str(msg.reason))
            else:
                checked.accepted.append(bytes(msg.get_msgbuf()))
        return checked


def install_on_ardupilot(setup_address: str, check_address: str, key: bytes) -> None:
    """Gives an ArduPilot the key (SETUP_SIGNING) and checks that it signs with it.

    ``setup_address`` (pymavlink, e.g. ``tcp:127.0.0.1:5760``) is the port the
    key goes over: ArduPilot takes it unsigned only while it has no key, and
    accepts unsigned frames on its first port (``SERIAL0``, the USB port of a
    flight controller) for good. ``check_address`` is another of its ports: a
    signed request there must get a reply signed with the key, or this raises
    ``SigningKeyError``.
    """
    from pymavlink import mavutil

    setup = mavutil.mavlink_connection(setup_address, source_system=255, source_component=190)
    try:
        if setup.wait_heartbeat(timeout=30) is None:
            raise SigningKeyError(f"no heartbeat from the autopilot at {setup_address}")
        for _attempt in range(5):
            setup.mav.setup_signing_send(
                setup.target_system, setup.target_component, key, timestamp_now()
            )
            # A connection opened after the key went (seen with ArduPilot 4.x
            # SITL: one opened before was never answered).
            if _answers_signed(mavutil.mavlink_connection(check_address), key, timeout_s=3.0):
                return
    finally:
        setup.close()
    raise SigningKeyError(
        f"the autopilot at {check_address} does not answer with the key after SETUP_SIGNING "
        f"on {setup_address}"
    )


def _answers_signed(check: Any, key: bytes, timeout_s: float) -> bool:
    """Whether the autopilot answers a signed request with a frame signed with ``key``."""
    try:
        check.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=_radio_only)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            check.mav.command_long_send(
                1, 0, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0,
            )  # fmt: skip
            reply = check.recv_match(type="AUTOPILOT_VERSION", blocking=True, timeout=0.5)
            if reply is not None and reply.get_signed():
                return True
        return False
    finally:
        check.close()


def _radio_only(_mav: object, msg_id: int) -> bool:
    return msg_id in ACCEPTED_UNSIGNED

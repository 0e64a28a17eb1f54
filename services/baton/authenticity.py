"""Replies signed by the drone: what a station relays, it cannot invent or alter.

The drone is the one source of every reply to a drone call, so it signs what
it answered with its own key (the private key of its mutual-TLS certificate),
and every controller checks the signature of every such reply that reaches
it over the ring, whoever relayed it, against the drone's certificate, which
it checks chained to the mission's CA and naming ``spiffe://baton/drone``
(docs/design.md, "Replies signed by the drone").

What is signed (``reply_statement``) is canonical bytes, never a serialized
protobuf (whose encoding is not unique): a domain tag, the request number,
the epoch the drone served it in, the method, the request digest
(``baton.digest``) and the SHA-256 of the reply. So a signature binds a reply
to its request: moved to another request number, another request or another
reply, it no longer verifies.

Which log entries need one (``needs_drone_signature``): a drone method's
reply (status OK). A Clock call is answered by its controller, and a failure
or a give-up is the controller's word (a failure the drone booked reaches
the master as a gRPC status, which carries no signature); those stay the
word of the station that logged them (issue 33, item 2).

Pure: no files, sockets or clocks (the time to check a certificate against is
an argument); the drone service signs, ``ControllerCore.log_arrived`` checks.
"""

from __future__ import annotations

import datetime
import hashlib
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Protocol

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519

from baton.digest import request_digest
from baton.rpc.methods import service_prefix
from baton.rpc.tls import DRONE, Identity
from baton.v1 import drone_pb2, ring_pb2

# Names what the bytes mean, so a signature over a reply is never taken for one
# over anything else the drone's key may sign later.
REPLY_TAG = b"baton.v1 drone reply\0"
_CLOCK = service_prefix("Clock")

SigningKey = ec.EllipticCurvePrivateKey | ed25519.Ed25519PrivateKey
VerifyingKey = ec.EllipticCurvePublicKey | ed25519.Ed25519PublicKey


class AuthenticityError(ValueError):
    """A key or certificate that cannot sign or check replies; the message says why."""


def reply_statement(reqnr: int, epoch: int, method: str, digest: bytes, reply: bytes) -> bytes:
    """The canonical bytes the drone signs for the reply to request ``reqnr``."""
    name = method.encode()
    return b"".join(
        (
            REPLY_TAG,
            struct.pack(">QQI", reqnr, epoch, len(name)),
            name,
            struct.pack(">I", len(digest)),
            bytes(digest),
            hashlib.sha256(reply).digest(),
        )
    )


def _sign(key: SigningKey, data: bytes) -> bytes:
    if isinstance(key, ed25519.Ed25519PrivateKey):
        return key.sign(data)
    return key.sign(data, ec.ECDSA(hashes.SHA256()))


def _verify(key: VerifyingKey, signature: bytes, data: bytes) -> bool:
    try:
        if isinstance(key, ed25519.Ed25519PublicKey):
            key.verify(signature, data)
        else:
            key.verify(signature, data, ec.ECDSA(hashes.SHA256()))
    except InvalidSignature:
        return False
    return True


@dataclass(frozen=True)
class ReplySigner:
    """The drone's key, signing what it answers."""

    key: SigningKey

    @classmethod
    def from_pem(cls, key_pem: bytes) -> ReplySigner:
        """From the drone's private key (``drone.key`` of its certificate folder)."""
        key = serialization.load_pem_private_key(key_pem, password=None)
        if not isinstance(key, ec.EllipticCurvePrivateKey | ed25519.Ed25519PrivateKey):
            raise AuthenticityError(
                f"the drone's key is {type(key).__name__}; replies are signed with an "
                "ECDSA or Ed25519 key (`baton certs init` makes ECDSA P-256)"
            )
        return cls(key)

    def sign(self, reqnr: int, epoch: int, method: str, digest: bytes, reply: bytes) -> bytes:
        return _sign(self.key, reply_statement(reqnr, epoch, method, digest, reply))


def _names(cert: x509.Certificate) -> list[Identity]:
    try:
        sans = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return []
    uris = sans.get_values_for_type(x509.UniformResourceIdentifier)
    return [who for who in map(Identity.from_uri, uris) if who is not None]


@dataclass(frozen=True)
class ReplyVerifier:
    """The drone's public key, from its certificate checked against the mission's CA."""

    key: VerifyingKey

    @classmethod
    def from_pem(cls, cert_pem: bytes, ca_pem: bytes, now: datetime.datetime) -> ReplyVerifier:
        """From the drone's certificate, once it is signed by the CA, valid at ``now``
        and names the drone: a station's certificate would let that station sign."""
        cert = x509.load_pem_x509_certificate(cert_pem)
        ca = x509.load_pem_x509_certificate(ca_pem)
        try:
            cert.verify_directly_issued_by(ca)
        except (ValueError, TypeError, InvalidSignature):
            raise AuthenticityError(
                "the drone's certificate is not signed by the mission's CA (ca.crt)"
            ) from None
        if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
            raise AuthenticityError(
                f"the drone's certificate is valid from {cert.not_valid_before_utc} to "
                f"{cert.not_valid_after_utc}, not at {now}"
            )
        names = _names(cert)
        if DRONE not in names:
            named = ", ".join(map(str, names)) or "no baton identity"
            raise AuthenticityError(f"the drone's certificate names {named}, not {DRONE}")
        key = cert.public_key()
        if not isinstance(key, ec.EllipticCurvePublicKey | ed25519.Ed25519PublicKey):
            raise AuthenticityError(
                f"the drone's certificate holds a {type(key).__name__}; replies are signed "
                "with an ECDSA or Ed25519 key"
            )
        return cls(key)

    def verify(self, entry: ring_pb2.LogEntry) -> bool:
        """Whether ``entry`` carries the drone's signature of its reply, and its request
        bytes (shown when a program diverges) are the ones the signed digest names."""
        if entry.request and request_digest(entry.method, entry.request) != entry.request_digest:
            return False
        statement = reply_statement(
            entry.reqnr, entry.drone_epoch, entry.method, entry.request_digest, entry.reply
        )
        return _verify(self.key, entry.drone_signature, statement)


class _Outcome(Protocol):
    @property
    def method(self) -> str: ...
    @property
    def status_code(self) -> int: ...
    @property
    def given_up(self) -> bool: ...


def needs_drone_signature(outcome: _Outcome) -> bool:
    """A reply the drone made: a call of any method but the Clock's, answered OK (the
    drone refuses anything else among what a master sends along, ``master_answers``)."""
    return not (outcome.given_up or outcome.status_code or outcome.method.startswith(_CLOCK))


def signed_reply(
    signer: ReplySigner | None,
    reqnr: int,
    epoch: int,
    method: str,
    digest: bytes,
    payload: bytes,
    duplicate: bool = False,
) -> drone_pb2.InvokeReply:
    """The drone's InvokeReply, signed if it has a key."""
    reply = drone_pb2.InvokeReply(reqnr=reqnr, payload=payload, duplicate=duplicate, epoch=epoch)
    if signer is not None:
        reply.signature = signer.sign(reqnr, epoch, method, digest, payload)
    return reply


def signed_retained(
    signer: ReplySigner | None, kept: drone_pb2.RetainedReply
) -> drone_pb2.RetainedReply:
    """A retained reply as the drone gives it to a taker: signed if the drone made it."""
    if signer is not None and needs_drone_signature(kept):
        kept.signature = signer.sign(
            kept.reqnr, kept.epoch, kept.method, kept.request_digest, kept.reply
        )
    return kept


def unsigned_reply(
    verifier: ReplyVerifier, entries: Iterable[ring_pb2.LogEntry]
) -> ring_pb2.LogEntry | None:
    """The first entry whose reply needs the drone's signature and lacks a valid one."""
    for entry in entries:
        if needs_drone_signature(entry) and not verifier.verify(entry):
            return entry
    return None

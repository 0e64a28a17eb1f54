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

A mastership a log message claims (its epoch, or the handover flag, which
makes its receiver master) is believed only where the drone's grant backs it
(``unbacked_claim``): the drone signs each grant it makes (``grant_statement``:
the controller, the epoch, how), the master carries it in every message of its
mastership and the old master in its handover message, and every receiver
checks it with the message. The grant travels with the claim, so a receiver
never waits for one: a message is believed or refused on what it carries.

Pure: no files, sockets or clocks (the time to check a certificate against is
an argument); the drone service signs, ``ControllerCore.log_arrived`` checks.
"""

from __future__ import annotations

import datetime
import hashlib
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
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
MESSAGE_TAG = b"baton.v1 log message\0"
GRANT_TAG = b"baton.v1 mastership grant\0"
WORD_TAG = b"baton.v1 master word\0"
PROOF_TAG = b"baton.v1 holds message\0"
_CLOCK = service_prefix("Clock")

SigningKey = ec.EllipticCurvePrivateKey | ed25519.Ed25519PrivateKey
VerifyingKey = ec.EllipticCurvePublicKey | ed25519.Ed25519PublicKey


class AuthenticityError(ValueError):
    """A key or certificate that cannot sign or check replies; the message says why."""


def reply_statement(
    reqnr: int, epoch: int, method: str, digest: bytes, reply: bytes, reply_sha256: bytes = b""
) -> bytes:
    """The canonical bytes the drone signs for the reply to request ``reqnr``
    (``reply_sha256``: the reply's SHA-256, if the caller has it already)."""
    name = method.encode()
    return b"".join(
        (
            REPLY_TAG,
            struct.pack(">QQI", reqnr, epoch, len(name)),
            name,
            struct.pack(">I", len(digest)),
            bytes(digest),
            reply_sha256 or hashlib.sha256(reply).digest(),
        )
    )


def grant_statement(master: int, epoch: int, kind: int, old_master: int) -> bytes:
    """The canonical bytes the drone signs for its grant of ``epoch`` to ``master``, taken
    from ``old_master``."""
    return GRANT_TAG + struct.pack(">iQIi", master, epoch, kind, old_master)


def word_statement(master: int, epoch: int, lognr: int) -> bytes:
    """The canonical bytes a master signs for its word that it went ACTIVE in ``epoch``
    holding every log message up to ``lognr`` (``ring_pb2.MasterWord``)."""
    return WORD_TAG + struct.pack(">iQQ", master, epoch, lognr)


def holding_proof(message: ring_pb2.LogMessage, hashes: list[bytes] | None = None) -> bytes:
    """What a sync frame says to show its sender holds ``message`` (``LogFrame.holds_proof``):
    the SHA-256 of the canonical bytes its creator signed. Those cover every entry's
    reply, request and drone signature through their hashes, so only a holder of the
    whole message computes it; its signature, in the head a cut-through relay passes on
    first, does not give it away. Its creator keeps it (``ControllerProtocol._flush``)
    and compares. ``hashes``: the replies' SHA-256 (``reply_hashes``) if the caller has
    them, as the signature's check does: a message may carry 64 MB of pictures."""
    return proof_of(message_statement(message, hashes))


def proof_of(statement: bytes) -> bytes:
    """``holding_proof`` of the message whose canonical bytes are ``statement``."""
    return hashlib.sha256(PROOF_TAG + statement).digest()


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


def reply_hashes(message: ring_pb2.LogMessage) -> list[bytes]:
    """The SHA-256 of each entry's reply: hashed once for both signatures' checks (a
    log message may carry 64 MB of pictures)."""
    return [hashlib.sha256(entry.reply).digest() for entry in message.entries]


def message_statement(message: ring_pb2.LogMessage, hashes: list[bytes] | None = None) -> bytes:
    """The canonical bytes a controller signs for a log message it creates: what it says
    of itself (sender, log number, epoch, where it follows) and every entry, each with
    the drone's word on it. Not its origin or handover flag: a handover message's new
    master sends it on as a normal message with itself as origin, and a history keeps
    it without the flag; only the drone's word makes a controller master."""
    parts = [
        MESSAGE_TAG,
        struct.pack(
            ">iQQ?QQdI",
            message.sender,
            message.lognr,
            message.epoch,
            message.HasField("after_reqnr"),
            message.after_reqnr,
            message.after_epoch,
            message.created_at,
            len(message.entries),
        ),
    ]
    for entry, reply_sha256 in zip(message.entries, hashes or reply_hashes(message), strict=True):
        method, status = entry.method.encode(), entry.status_message.encode()
        parts += [
            struct.pack(
                ">QiI?QI",
                entry.reqnr,
                entry.status_code,
                len(method),
                entry.given_up,
                entry.drone_epoch,
                len(status),
            ),
            method,
            status,
            hashlib.sha256(entry.request_digest).digest(),
            reply_sha256,
            hashlib.sha256(entry.request).digest(),
            hashlib.sha256(entry.drone_signature).digest(),
        ]
    return b"".join(parts)


@dataclass(frozen=True)
class Signer:
    """A part's own key: the drone signs its replies, a controller its log messages."""

    key: SigningKey

    @classmethod
    def from_pem(cls, key_pem: bytes) -> Signer:
        """From a part's private key (``NAME.key`` of its certificate folder)."""
        key = serialization.load_pem_private_key(key_pem, password=None)
        if not isinstance(key, ec.EllipticCurvePrivateKey | ed25519.Ed25519PrivateKey):
            raise AuthenticityError(
                f"the key is {type(key).__name__}; baton signs with an ECDSA or Ed25519 "
                "key (`baton certs init` makes ECDSA P-256)"
            )
        return cls(key)

    def sign(self, reqnr: int, epoch: int, method: str, digest: bytes, reply: bytes) -> bytes:
        """The drone's signature of its reply to request ``reqnr``."""
        return _sign(self.key, reply_statement(reqnr, epoch, method, digest, reply))

    def seal_grant(self, grant: drone_pb2.Grant) -> None:
        """Signs the drone's grant (``Grant.signature``)."""
        grant.signature = _sign(
            self.key, grant_statement(grant.master, grant.epoch, grant.kind, grant.old_master)
        )

    def seal(self, message: ring_pb2.LogMessage | ring_pb2.MasterWord) -> bytes:
        """Signs what this controller says in its own name: a log message it created
        (``LogMessage.signature``), or its word as master (``MasterWord.signature``).
        Returns the canonical bytes signed (a log message's ``holding_proof`` is their
        hash: computed once, with the signature)."""
        if isinstance(message, ring_pb2.MasterWord):
            statement = word_statement(message.master, message.epoch, message.lognr)
        else:
            statement = message_statement(message)
        message.signature = _sign(self.key, statement)
        return statement


def _names(cert: x509.Certificate) -> list[Identity]:
    try:
        sans = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return []
    uris = sans.get_values_for_type(x509.UniformResourceIdentifier)
    return [who for who in map(Identity.from_uri, uris) if who is not None]


@dataclass(frozen=True)
class Verifier:
    """One part's public key, from its certificate checked against the mission's CA."""

    key: VerifyingKey
    # The serial number of the certificate the key came from (0: none), which a
    # revocation list names (``Keys.revoked``).
    serial: int = 0
    # The grants whose signature held (serialized): a mastership's grant comes with
    # every message of it, and is checked once.
    _grants: set[bytes] = field(default_factory=set, compare=False, repr=False)

    @classmethod
    def from_pem(
        cls, cert_pem: bytes, ca_pem: bytes, now: datetime.datetime, who: Identity = DRONE
    ) -> Verifier:
        """From ``who``'s certificate, once it is signed by the CA, valid at ``now`` and
        names ``who``: another part's certificate would let that part sign as ``who``."""
        cert = x509.load_pem_x509_certificate(cert_pem)
        ca = x509.load_pem_x509_certificate(ca_pem)
        try:
            cert.verify_directly_issued_by(ca)
        except (ValueError, TypeError, InvalidSignature):
            raise AuthenticityError(
                f"the {who.name} certificate is not signed by the mission's CA (ca.crt)"
            ) from None
        if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
            raise AuthenticityError(
                f"the {who.name} certificate is valid from {cert.not_valid_before_utc} to "
                f"{cert.not_valid_after_utc}, not at {now}"
            )
        names = _names(cert)
        if who not in names:
            named = ", ".join(map(str, names)) or "no baton identity"
            raise AuthenticityError(f"the {who.name} certificate names {named}, not {who}")
        key = cert.public_key()
        if not isinstance(key, ec.EllipticCurvePublicKey | ed25519.Ed25519PublicKey):
            raise AuthenticityError(
                f"the {who.name} certificate holds a {type(key).__name__}; baton signs "
                "with an ECDSA or Ed25519 key"
            )
        return cls(key, cert.serial_number)

    def verify(self, entry: ring_pb2.LogEntry, reply_sha256: bytes = b"") -> bool:
        """Whether ``entry`` carries the drone's signature of its reply, and its request
        bytes (shown when a program diverges) are the ones the signed digest names."""
        if entry.request and request_digest(entry.method, entry.request) != entry.request_digest:
            return False
        statement = reply_statement(
            entry.reqnr,
            entry.drone_epoch,
            entry.method,
            entry.request_digest,
            entry.reply,
            reply_sha256,
        )
        return _verify(self.key, entry.drone_signature, statement)

    def verify_grant(self, grant: drone_pb2.Grant) -> bool:
        """Whether ``grant`` carries the drone's signature (``Signer.seal_grant``)."""
        whole = grant.SerializeToString(deterministic=True)
        if whole in self._grants:
            return True
        statement = grant_statement(grant.master, grant.epoch, grant.kind, grant.old_master)
        if not _verify(self.key, grant.signature, statement):
            return False
        self._grants.add(whole)
        return True

    def verify_message(
        self, message: ring_pb2.LogMessage, hashes: list[bytes] | None = None
    ) -> bool:
        """Whether ``message`` carries its creator's signature (``Signer.seal``)."""
        return _verify(self.key, message.signature, message_statement(message, hashes))

    def verify_word(self, word: ring_pb2.MasterWord) -> bool:
        """Whether ``word`` carries its master's signature (``Signer.seal``)."""
        statement = word_statement(word.master, word.epoch, word.lognr)
        return _verify(self.key, word.signature, statement)


@dataclass(frozen=True)
class Keys:
    """What a controller checks log messages against: the drone's key and every
    controller's of the ring, from their certificates; a controller's earlier
    certificates (before a rotation), whose messages may still come round; and the
    serials the revocation list names, whose signatures are not believed."""

    drone: Verifier
    controllers: Mapping[int, Verifier]
    earlier: Mapping[int, tuple[Verifier, ...]] = field(default_factory=dict)
    revoked: frozenset[int] = frozenset()

    def of(self, cid: int) -> list[Verifier]:
        """Controller ``cid``'s keys that are not revoked, the current first."""
        current = self.controllers.get(cid)
        held = ([current] if current is not None else []) + list(self.earlier.get(cid, ()))
        return [verifier for verifier in held if verifier.serial not in self.revoked]


def refusal(
    keys: Keys, message: ring_pb2.LogMessage, receiver: int, hashes: list[bytes] | None = None
) -> str | None:
    """Why ``message``, received by controller ``receiver``, is not what its creator and
    the drone said, or None if it is.

    Its creator's signature first (``LogMessage.sender``, a controller of the ring):
    a relay can pass a message on but not make one in another's name or change it;
    then the drone's grant of the mastership it claims (``unbacked_claim``): its
    creator cannot make itself or another master; then the drone's signature on every
    reply it made: its creator cannot invent one. ``hashes``: the replies' SHA-256
    (``reply_hashes``) if the caller has them."""
    if message.sender not in keys.controllers:
        return f"its creator, controller {message.sender}, is not one of the ring"
    hashes = hashes or reply_hashes(message)
    creators = keys.of(message.sender)
    if not any(creator.verify_message(message, hashes) for creator in creators):
        revoked = [
            f"{v.serial:x}"
            for v in (keys.controllers[message.sender], *keys.earlier.get(message.sender, ()))
            if v.serial in keys.revoked and v.verify_message(message, hashes)
        ]
        if revoked:
            return (
                f"it is signed with controller {message.sender}'s revoked certificate "
                f"(serial {revoked[0]})"
            )
        return f"it has no valid signature of its creator, controller {message.sender}"
    if keys.drone.serial in keys.revoked and (
        message.epoch or message.handover or any(map(needs_drone_signature, message.entries))
    ):
        serial = f"{keys.drone.serial:x}"
        return f"it needs the drone's word; the drone's certificate (serial {serial}) is revoked"
    unbacked = unbacked_claim(keys.drone, message, receiver)
    if unbacked is not None:
        return unbacked
    entry = unsigned_reply(keys.drone, message.entries, hashes)
    if entry is not None:
        return f"request {entry.reqnr} ({entry.method}) has no valid drone signature"
    return None


def unbacked_claim(drone: Verifier, message: ring_pb2.LogMessage, receiver: int) -> str | None:
    """Why the mastership ``message`` claims is not the drone's word, or None if it is.

    A message of epoch E > 0 says its sender was master in E, or, for a handover
    message (also once forwarded without its flag, or sent on by its creator in its
    own name), that its origin is: it must carry the drone's grant of E, and be made
    by the controllers that grant names (``_made_by_the_granted``). The handover flag
    makes its receiver master, so a flagged message needs a handover grant to its
    origin from its sender, and only the origin is its receiver (a relay forwards it
    without the flag). A grant of another epoch backs nothing here: an old grant
    played again cannot raise an epoch. A message of epoch 0 without the flag claims
    no mastership."""
    if message.epoch == 0 and not message.handover:
        return None
    claimed = f"epoch {message.epoch}"
    if not message.HasField("grant"):
        return f"it claims a mastership ({claimed}) without the drone's grant"
    grant = message.grant
    if not drone.verify_grant(grant):
        return f"its grant of epoch {grant.epoch} to controller {grant.master} is not the drone's"
    if grant.epoch != message.epoch:
        return f"it claims {claimed} with the drone's grant of epoch {grant.epoch}"
    if message.handover:
        if grant.kind != drone_pb2.GRANT_KIND_HANDOVER or grant.master != message.origin:
            return (
                f"a handover message to controller {message.origin} with the drone's "
                f"{drone_pb2.GrantKind.Name(grant.kind)} grant to controller {grant.master}"
            )
        if message.origin != receiver:
            return f"a handover message to controller {message.origin} sent to {receiver}"
    if not _made_by_the_granted(grant, message):
        granted = f"to controller {grant.master}"
        if grant.kind == drone_pb2.GRANT_KIND_HANDOVER:
            granted += f" from controller {grant.old_master}"
        return (
            f"it claims {claimed} for controller {message.sender}; the drone granted it {granted}"
        )
    return None


def _made_by_the_granted(grant: drone_pb2.Grant, message: ring_pb2.LogMessage) -> bool:
    """Whether ``message``, of ``grant``'s epoch, was made (``sender``, whose signature
    it carries; a relay may change the origin) by a controller the grant names.

    A first or takeover grant: its master alone makes the messages of its epoch. A
    handover grant also names the old master, whose handover message is of the new
    epoch: sent straight with its flag, forwarded by the new master without it, or
    sent on in the old master's own name when the new master was lost before it
    could (``ControllerProtocol._resend_handed``). Any other station holding the
    grant (every message of the epoch carries it) makes nothing of that epoch.
    """
    if grant.kind == drone_pb2.GRANT_KIND_HANDOVER:
        return message.sender in (grant.master, grant.old_master)
    return message.sender == grant.master


def unbacked_word(keys: Keys, word: ring_pb2.MasterWord | None) -> str | None:
    """Why a sync frame's word on the newest master (``LogFrame.master_word``) is not
    believed, or None if it is: it must be signed by the master it names, with the
    drone's grant of its epoch to that master. A relay says the word on unchanged and
    cannot make one: the grant alone (in every message of the mastership) would let it
    name any log number."""
    if word is None:
        return "it names a master without the master's signed word"
    if not any(verifier.verify_word(word) for verifier in keys.of(word.master)):
        return f"its word of epoch {word.epoch} has no valid signature of controller {word.master}"
    if not word.HasField("grant"):
        return f"controller {word.master}'s word of epoch {word.epoch} has no grant"
    return unbacked_grant(keys, word.grant, word.epoch, word.master)


def unbacked_grant(
    keys: Keys, grant: drone_pb2.Grant | None, epoch: int, master: int | None = None
) -> str | None:
    """Why ``grant`` is not the drone's word that ``epoch`` was granted (to ``master``, if
    given), or None if it is."""
    if grant is None:
        return f"epoch {epoch} without the drone's grant"
    if keys.drone.serial in keys.revoked or not keys.drone.verify_grant(grant):
        return f"its grant of epoch {grant.epoch} to controller {grant.master} is not the drone's"
    if grant.epoch != epoch:
        return f"epoch {epoch} with the drone's grant of epoch {grant.epoch}"
    if master is not None and grant.master != master:
        return f"epoch {epoch} for controller {master}; the drone granted it to {grant.master}"
    return None


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
    signer: Signer | None,
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
    signer: Signer | None, kept: drone_pb2.RetainedReply
) -> drone_pb2.RetainedReply:
    """A retained reply as the drone gives it to a taker: signed if the drone made it."""
    if signer is not None and needs_drone_signature(kept):
        kept.signature = signer.sign(
            kept.reqnr, kept.epoch, kept.method, kept.request_digest, kept.reply
        )
    return kept


def unsigned_reply(
    verifier: Verifier, entries: Sequence[ring_pb2.LogEntry], hashes: Sequence[bytes] = ()
) -> ring_pb2.LogEntry | None:
    """The first entry whose reply needs the drone's signature and lacks a valid one
    (``hashes``: the replies' SHA-256, ``reply_hashes``, if the caller has them)."""
    for k, entry in enumerate(entries):
        reply_sha256 = hashes[k] if hashes else b""
        if needs_drone_signature(entry) and not verifier.verify(entry, reply_sha256):
            return entry
    return None

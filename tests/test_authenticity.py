"""The drone's signature on its replies (baton.authenticity), and the controller core's
check of every log message that arrives: the pure rule's corners, no sockets."""

from __future__ import annotations

import datetime
from pathlib import Path

import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ed25519
from helpers.protocol import started

from baton.authenticity import (
    AuthenticityError,
    Keys,
    Signer,
    Verifier,
    needs_drone_signature,
    refusal,
    signed_reply,
    signed_retained,
    unsigned_reply,
)
from baton.certs.make import init, issue
from baton.controller.core import ControllerCore, Keep, Note, from_retained
from baton.controller.protocol import SendLog
from baton.digest import request_digest
from baton.rpc.tls import DRONE, Identity, Tls
from baton.v1 import drone_pb2, ring_pb2

GET = "/baton.v1.Mobility/GetPosition"
NOW = "/baton.v1.Clock/Now"
REQUEST = b"\x08\x01"


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("certs")
    init(folder, [DRONE, *map(Identity.controller, (0, 1, 2))])
    return folder


def now() -> datetime.datetime:
    return datetime.datetime.now(datetime.UTC)


def pair(certs: Path) -> tuple[Signer, Verifier]:
    drone = Tls.load(certs, DRONE)
    return Signer.from_pem(drone.key), Verifier.from_pem(drone.cert, drone.ca, now())


def signed_entry(signer: Signer, reqnr: int = 3, epoch: int = 1) -> ring_pb2.LogEntry:
    """The log entry a master makes of the drone's signed reply to GetPosition."""
    digest = request_digest(GET, REQUEST)
    reply = signed_reply(signer, reqnr, epoch, GET, digest, b"position")
    return ring_pb2.LogEntry(
        reqnr=reqnr,
        method=GET,
        reply=reply.payload,
        request_digest=digest,
        request=REQUEST,
        drone_epoch=reply.epoch,
        drone_signature=reply.signature,
    )


def test_a_signed_reply_verifies_and_any_change_to_what_it_binds_does_not(certs: Path) -> None:
    signer, verifier = pair(certs)
    good = signed_entry(signer)
    assert verifier.verify(good)
    assert unsigned_reply(verifier, [good]) is None
    changes = {
        "reply": b"elsewhere",
        "reqnr": 4,
        "drone_epoch": 2,
        "method": "/baton.v1.Mobility/GetFlightState",
        "request_digest": request_digest(GET, b"other"),
        "request": b"other",  # the bytes shown on divergence, not the signed digest's
        "drone_signature": b"",
    }
    for field, value in changes.items():
        altered = ring_pb2.LogEntry()
        altered.CopyFrom(good)
        setattr(altered, field, value)
        assert not verifier.verify(altered), field
        assert unsigned_reply(verifier, [good, altered]) is altered, field


def test_another_keys_signature_does_not_verify(certs: Path, tmp_path: Path) -> None:
    _, verifier = pair(certs)
    other = Tls.load(certs, Identity.controller(1))  # a station signing as if it were the drone
    assert not verifier.verify(signed_entry(Signer.from_pem(other.key)))
    ed = ed25519.Ed25519PrivateKey.generate()
    pem = ed.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    assert not verifier.verify(signed_entry(Signer.from_pem(pem)))
    assert Verifier(ed.public_key()).verify(signed_entry(Signer.from_pem(pem)))


def test_only_what_the_drone_answered_needs_its_signature() -> None:
    assert needs_drone_signature(ring_pb2.LogEntry(method=GET))
    assert not needs_drone_signature(ring_pb2.LogEntry(method=NOW))
    assert not needs_drone_signature(ring_pb2.LogEntry(method=GET, given_up=True, status_code=1))
    assert not needs_drone_signature(ring_pb2.LogEntry(method=GET, status_code=14))
    # An unknown method is no Clock call: it needs one.
    assert needs_drone_signature(ring_pb2.LogEntry(method="/x.Y/Z"))


def test_retained_replies_are_signed_as_made_and_a_takers_entry_keeps_the_signature(
    certs: Path,
) -> None:
    signer, verifier = pair(certs)
    digest = request_digest(GET, REQUEST)
    kept = signed_retained(
        signer,
        drone_pb2.RetainedReply(reqnr=5, method=GET, request_digest=digest, reply=b"p", epoch=2),
    )
    clock = signed_retained(signer, drone_pb2.RetainedReply(reqnr=4, method=NOW, epoch=2))
    assert kept.signature and not clock.signature
    assert verifier.verify(from_retained(kept, GET, REQUEST))
    assert signed_retained(None, drone_pb2.RetainedReply(reqnr=5, method=GET)).signature == b""


def test_the_drones_certificate_must_be_the_drones_of_this_ca_and_valid(
    certs: Path, tmp_path: Path
) -> None:
    ca = (certs / "ca.crt").read_bytes()
    station = (certs / "controller-1.crt").read_bytes()
    with pytest.raises(AuthenticityError, match="names spiffe://baton/controller/1, not"):
        Verifier.from_pem(station, ca, now())
    foreign = tmp_path / "foreign"
    init(foreign, [DRONE])
    with pytest.raises(AuthenticityError, match="not signed by the mission's CA"):
        Verifier.from_pem((foreign / "drone.crt").read_bytes(), ca, now())
    expired = tmp_path / "expired"
    init(expired, [])
    issue(expired, DRONE, days=1, not_before=now() - datetime.timedelta(days=2))
    with pytest.raises(AuthenticityError, match="is valid from"):
        Verifier.from_pem(
            (expired / "drone.crt").read_bytes(), (expired / "ca.crt").read_bytes(), now()
        )


def station(certs: Path, cid: int) -> Signer:
    return Signer.from_pem(Tls.load(certs, Identity.controller(cid)).key)


def keys(certs: Path) -> Keys:
    controllers = {
        cid: Verifier.from_pem(
            (certs / f"controller-{cid}.crt").read_bytes(),
            (certs / "ca.crt").read_bytes(),
            now(),
            Identity.controller(cid),
        )
        for cid in (0, 1, 2)
    }
    return Keys(pair(certs)[1], controllers)


def replica(ring_keys: Keys | None) -> ControllerCore:
    """Controller 1 of ring 0 -> 1 -> 2, a replica of master 0 in epoch 1."""
    core = ControllerCore(started(1, [0, 1, 2], 0))
    core.keys = ring_keys
    return core


def sealed(signer: Signer, message: ring_pb2.LogMessage) -> ring_pb2.LogMessage:
    signer.seal(message)
    return message


def test_a_message_with_a_reply_the_drone_did_not_sign_is_refused_whole(certs: Path) -> None:
    signer, _ = pair(certs)
    master = station(certs, 0)
    forged = ring_pb2.LogEntry()
    forged.CopyFrom(signed_entry(signer, reqnr=2))
    forged.reply = b"made up"
    clock = ring_pb2.LogEntry(reqnr=1, method=NOW, reply=b"t", request_digest=b"d")
    message = ring_pb2.LogMessage(
        lognr=1, origin=0, sender=0, epoch=1, entries=[clock, forged, signed_entry(signer)]
    )
    core = replica(keys(certs))
    # Sealed by its creator, who cannot make the drone's word: refused all the same.
    effects = core.log_arrived(sealed(master, message), lambda: True, relayed_by=2)
    # Nothing kept, handled or forwarded: only the refusal, named.
    assert [type(e) for e in effects] == [Note]
    note = effects[0]
    assert isinstance(note, Note) and note.fields == {
        "mlognr": 1,
        "origin": 0,
        "relayed_by": 2,
        "why": f"request 2 ({GET}) has no valid drone signature",
    }
    assert core.protocol.lognr == 0 and not core.protocol.log.entries
    assert core.refused_messages == 1
    assert "relayed by controller 2: request 2" in core.last_refused
    assert core.fresh_self().keys is core.keys  # a rejoin keeps checking
    # The same message as the drone signed it is taken, kept and forwarded.
    message.entries[1].CopyFrom(signed_entry(signer, reqnr=2))
    taken = core.log_arrived(sealed(master, message), lambda: True, relayed_by=2)
    assert any(isinstance(e, Keep) for e in taken)
    assert any(isinstance(e, SendLog) and e.dest == 2 for e in taken)
    assert core.protocol.lognr == 1 and core.refused_messages == 1


def test_a_relay_can_pass_a_message_on_but_not_make_or_change_one(certs: Path) -> None:
    ring_keys = keys(certs)
    master, relay = station(certs, 0), station(certs, 1)
    clock = ring_pb2.LogEntry(reqnr=1, method=NOW, reply=b"t", request_digest=b"d")
    genuine = sealed(
        master,
        ring_pb2.LogMessage(lognr=4, origin=0, sender=0, epoch=1, entries=[clock], after_reqnr=0),
    )
    assert refusal(ring_keys, genuine) is None
    # What it may change on the way: a handover message's origin and flag.
    moved = ring_pb2.LogMessage()
    moved.CopyFrom(genuine)
    moved.origin, moved.handover = 2, True
    assert refusal(ring_keys, moved) is None
    changes: dict[str, object] = {
        "lognr": 9999,
        "epoch": 6,
        "after_reqnr": 3,
        "after_epoch": 1,
        "created_at": 1.0,
        "sender": 2,
    }
    for field, value in changes.items():
        altered = ring_pb2.LogMessage()
        altered.CopyFrom(genuine)
        setattr(altered, field, value)
        assert refusal(ring_keys, altered) is not None, field
    for field, value in {"reply": b"later", "status_code": 2, "given_up": True}.items():
        altered = ring_pb2.LogMessage()
        altered.CopyFrom(genuine)
        setattr(altered.entries[0], field, value)
        assert refusal(ring_keys, altered) is not None, field
    dropped = ring_pb2.LogMessage()
    dropped.CopyFrom(genuine)
    del dropped.entries[:]
    assert "no valid signature of its creator, controller 0" in (refusal(ring_keys, dropped) or "")
    # In another's name, signed with its own key; and from outside the ring.
    forged = ring_pb2.LogMessage()
    forged.CopyFrom(genuine)
    relay.seal(forged)
    assert "controller 0" in (refusal(ring_keys, forged) or "")
    stranger = ring_pb2.LogMessage(lognr=1, sender=7)
    assert "controller 7, is not one of the ring" in (refusal(ring_keys, stranger) or "")


def test_the_protocol_seals_the_messages_it_creates(certs: Path) -> None:
    ring_keys = keys(certs)
    master = ControllerCore(started(0, [0, 1, 2], 0))
    master.protocol.seal = station(certs, 0).seal
    assert master.fresh_self().protocol.seal == master.protocol.seal
    master.protocol.on_reply(ring_pb2.LogEntry(reqnr=1, method=NOW, reply=b"t"))
    handover = master.handover_notice(2, 1, 2)
    sent = [e.message for e in handover if isinstance(e, SendLog)]
    assert sent and all(refusal(ring_keys, m) is None for m in sent)


def test_without_keys_a_stations_word_is_taken() -> None:
    """An insecure ring (no certificates): nothing to check against."""
    unsigned = ring_pb2.LogEntry(reqnr=1, method=GET, reply=b"p", request_digest=b"d")
    message = ring_pb2.LogMessage(lognr=1, origin=0, sender=0, epoch=1, entries=[unsigned])
    effects = replica(None).log_arrived(message, lambda: True)
    assert any(isinstance(e, Keep) for e in effects)

"""The drone's signature on its replies (baton.authenticity), and the controller core's
check of every log message that arrives: the pure rule's corners, no sockets."""

from __future__ import annotations

import datetime
from dataclasses import replace
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
    unbacked_claim,
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
NOW_DIGEST = request_digest(NOW, b"")


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


def grant(
    signer: Signer,
    master: int,
    epoch: int,
    kind: int = drone_pb2.GRANT_KIND_FIRST,
    old_master: int = 0,
) -> drone_pb2.Grant:
    """The drone's grant of ``epoch`` to ``master`` (from ``old_master``), signed."""
    made = drone_pb2.Grant(
        master=master,
        epoch=epoch,
        kind=kind,  # type: ignore[arg-type]
        old_master=old_master,
    )
    signer.seal_grant(made)
    return made


def sealed(certs: Path, signer: Signer, message: ring_pb2.LogMessage) -> ring_pb2.LogMessage:
    """``message`` sealed by its creator, with the drone's first grant of epoch 1 to its
    sender when it claims that mastership and carries no grant."""
    if message.epoch == 1 and not message.HasField("grant"):
        message.grant.CopyFrom(grant(pair(certs)[0], message.sender, 1))
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
    effects = core.log_arrived(sealed(certs, master, message), lambda: True, relayed_by=2)
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
    taken = core.log_arrived(sealed(certs, master, message), lambda: True, relayed_by=2)
    assert any(isinstance(e, Keep) for e in taken)
    assert any(isinstance(e, SendLog) and e.dest == 2 for e in taken)
    assert core.protocol.lognr == 1 and core.refused_messages == 1


def test_a_relay_can_pass_a_message_on_but_not_make_or_change_one(certs: Path) -> None:
    ring_keys = keys(certs)
    master, relay = station(certs, 0), station(certs, 1)
    clock = ring_pb2.LogEntry(reqnr=1, method=NOW, reply=b"t", request_digest=b"d")
    genuine = sealed(
        certs,
        master,
        ring_pb2.LogMessage(lognr=4, origin=0, sender=0, epoch=1, entries=[clock], after_reqnr=0),
    )
    assert refusal(ring_keys, genuine, 1) is None
    # What it may change on the way: the origin (not the flag: that makes its
    # receiver master, and needs the drone's handover grant naming it).
    moved = ring_pb2.LogMessage()
    moved.CopyFrom(genuine)
    moved.origin = 2
    assert refusal(ring_keys, moved, 2) is None
    moved.handover = True
    assert "a handover message to controller 2 with the drone's GRANT_KIND_FIRST" in (
        refusal(ring_keys, moved, 2) or ""
    )
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
        assert refusal(ring_keys, altered, 1) is not None, field
    for field, value in {"reply": b"later", "status_code": 2, "given_up": True}.items():
        altered = ring_pb2.LogMessage()
        altered.CopyFrom(genuine)
        setattr(altered.entries[0], field, value)
        assert refusal(ring_keys, altered, 1) is not None, field
    dropped = ring_pb2.LogMessage()
    dropped.CopyFrom(genuine)
    del dropped.entries[:]
    assert "no valid signature of its creator, controller 0" in (
        refusal(ring_keys, dropped, 1) or ""
    )
    # In another's name, signed with its own key; and from outside the ring.
    forged = ring_pb2.LogMessage()
    forged.CopyFrom(genuine)
    relay.seal(forged)
    assert "controller 0" in (refusal(ring_keys, forged, 1) or "")
    stranger = ring_pb2.LogMessage(lognr=1, sender=7)
    assert "controller 7, is not one of the ring" in (refusal(ring_keys, stranger, 1) or "")


def test_the_protocol_seals_the_messages_it_creates(certs: Path) -> None:
    ring_keys = keys(certs)
    drone = pair(certs)[0]
    master = ControllerCore(started(0, [0, 1, 2], 0))
    master.protocol.seal = station(certs, 0).seal
    master.granted(drone_pb2.Connected(epoch=1, grant=grant(drone, 0, 1)))
    assert master.fresh_self().protocol.seal == master.protocol.seal
    # With a flush limit of 0 every reply is flushed at once.
    now_call = ring_pb2.LogEntry(reqnr=1, method=NOW, reply=b"t", request_digest=NOW_DIGEST)
    replied = master.protocol.on_reply(now_call)
    flushed = [e.message for e in replied if isinstance(e, SendLog)]
    assert flushed and all(refusal(ring_keys, m, 1) is None for m in flushed)
    assert all(m.grant.master == 0 and m.grant.epoch == 1 for m in flushed)
    handed = grant(drone, 2, 2, drone_pb2.GRANT_KIND_HANDOVER)
    handover = master.handover_notice(2, 1, 2, handed)
    sent = [e.message for e in handover if isinstance(e, SendLog)]
    assert sent and all(refusal(ring_keys, m, 2) is None for m in sent)
    # The new master carries the grant the handover message brought in what it flushes.
    target = ControllerCore(started(2, [0, 1, 2], 0))
    target.protocol.seal = station(certs, 2).seal
    target.keys = ring_keys
    for message in (*flushed, sent[-1]):
        target.log_arrived(message, lambda: True, relayed_by=1)
    assert target.refused_messages == 0, target.last_refused
    target.protocol.replay(NOW, b"")  # its program replays request 1, then it takes the role
    assert target.protocol.master and target.protocol.epoch == 2
    replied = target.protocol.on_reply(ring_pb2.LogEntry(reqnr=2, method=NOW, reply=b"t"))
    theirs = [e.message for e in replied if isinstance(e, SendLog)]
    assert theirs and all(refusal(ring_keys, m, 0) is None for m in theirs)


def test_a_takers_own_handover_message_sent_on_to_the_ring_is_believed(certs: Path) -> None:
    """--lose-master --lying seeds 22, 100, 136 and 6 more of 0-299: master 0 handed over to
    1, which died before it sent the handover message on; the drone took the role back to
    0, which sent the message on itself as a normal message of its own (F11). Its replicas
    refused it ("it claims epoch 2 for controller 0; the drone granted it to controller
    1") and waited for ever for log message 1. The drone's handover grant backs it, as it
    backs the same message forwarded by the new master."""
    ring_keys, drone = keys(certs), pair(certs)[0]
    old = ControllerCore(started(0, [0, 1, 2], 1 << 20))
    old.protocol.seal = station(certs, 0).seal
    old.granted(drone_pb2.Connected(epoch=1, grant=grant(drone, 0, 1)))
    old.protocol.on_reply(
        ring_pb2.LogEntry(reqnr=1, method=NOW, reply=b"t", request_digest=NOW_DIGEST)
    )
    old.handover_notice(1, 1, 2, grant(drone, 1, 2, drone_pb2.GRANT_KIND_HANDOVER))
    effects = old.protocol.on_granted(3, takeover=True, grant=grant(drone, 0, 3))
    (sent,) = [e.message for e in effects if isinstance(e, SendLog)]
    assert (sent.lognr, sent.origin, sent.sender, sent.handover) == (1, 0, 0, False)
    assert refusal(ring_keys, sent, 2) is None
    replica = ControllerCore(started(2, [0, 1, 2], 0))
    replica.keys = ring_keys
    replica.log_arrived(sent, lambda: True, relayed_by=0)
    assert replica.refused_messages == 0, replica.last_refused


def test_a_mastership_is_believed_only_where_the_drones_grant_backs_it(certs: Path) -> None:
    """Controller 1, a stolen station, signs messages in its own name claiming masterships
    the drone never gave it: each refused, naming why; the genuine ones taken."""
    drone, liar = pair(certs)[0], station(certs, 1)
    verifier = pair(certs)[1]

    def claim(epoch: int, backing: drone_pb2.Grant | None, **fields: object) -> str | None:
        message = ring_pb2.LogMessage(lognr=9, origin=1, sender=1, epoch=epoch)
        for name, value in fields.items():
            setattr(message, name, value)
        if backing is not None:
            message.grant.CopyFrom(backing)
        liar.seal(message)
        return unbacked_claim(verifier, message, receiver=2)

    handover = drone_pb2.GRANT_KIND_HANDOVER
    assert claim(6, None) == "it claims a mastership (epoch 6) without the drone's grant"
    # A grant made up, or the drone's to another controller, or of another epoch.
    forged = drone_pb2.Grant(master=1, epoch=6, kind=handover)
    liar.seal_grant(forged)
    assert "grant of epoch 6 to controller 1 is not the drone's" in (claim(6, forged) or "")
    takeover = drone_pb2.GRANT_KIND_TAKEOVER
    assert "the drone granted it to controller 0" in (claim(6, grant(drone, 0, 6, takeover)) or "")
    # An old grant of its own played again: it backs its epoch, never a newer one.
    old = grant(drone, 1, 2, handover)
    assert claim(2, old) is None
    assert "epoch 7 with the drone's grant of epoch 2" in (claim(7, old) or "")
    # The handover flag makes its receiver master: a handover grant naming it, only.
    to_two = grant(drone, 2, 3, handover, old_master=1)
    assert claim(3, to_two, origin=2, handover=True) is None
    assert "sent to 2" in (claim(3, grant(drone, 0, 3, handover), origin=0, handover=True) or "")
    assert "GRANT_KIND_TAKEOVER grant" in (
        claim(3, grant(drone, 2, 3, drone_pb2.GRANT_KIND_TAKEOVER), origin=2, handover=True) or ""
    )
    assert "without the drone's grant" in (claim(0, None, origin=2, handover=True) or "")
    # Forwarded without its flag, a handover message is backed by the grant of its epoch;
    # sent on by its creator in its own name (a taker whose new master was lost), too.
    assert claim(3, to_two, origin=2) is None
    assert claim(3, to_two) is None
    # A genuine handover grant of a handover between two others backs nothing the liar
    # makes: every message of the epoch carries it, so any station holds one.
    others = grant(drone, 2, 3, handover, old_master=0)
    for origin in (1, 2, 0):
        assert "the drone granted it to controller 2 from controller 0" in (
            claim(3, others, origin=origin) or ""
        ), origin
    assert "from controller 0" in (claim(3, others, origin=2, handover=True) or "")
    # Nor a takeover's grant, whatever origin a message of its epoch says.
    taken = grant(drone, 2, 4, drone_pb2.GRANT_KIND_TAKEOVER, old_master=1)
    assert "the drone granted it to controller 2" in (claim(4, taken, origin=2) or "")
    # Epoch 0 without the flag claims no mastership.
    assert claim(0, None) is None


def test_a_forged_claim_is_refused_by_the_core_and_leaves_the_log_untouched(
    certs: Path,
) -> None:
    """The receiver's core refuses it like any forged frame, before the protocol sees
    it: counted, named, nothing kept, handled or forwarded."""
    core = replica(keys(certs))
    liar = station(certs, 1)
    claim = ring_pb2.LogMessage(lognr=1, origin=2, sender=1, epoch=6, handover=True)
    liar.seal(claim)
    effects = core.log_arrived(claim, lambda: True, relayed_by=0)
    assert [type(e) for e in effects] == [Note]
    assert core.refused_messages == 1 and core.protocol.lognr == 0
    assert not core.protocol.master and core.protocol.epoch == 0
    assert "without the drone's grant" in core.last_refused


def test_without_keys_a_stations_word_is_taken() -> None:
    """An insecure ring (no certificates): nothing to check against."""
    unsigned = ring_pb2.LogEntry(reqnr=1, method=GET, reply=b"p", request_digest=b"d")
    message = ring_pb2.LogMessage(lognr=1, origin=0, sender=0, epoch=1, entries=[unsigned])
    effects = replica(None).log_arrived(message, lambda: True)
    assert any(isinstance(e, Keep) for e in effects)


def test_a_revoked_certificate_signs_nothing_and_a_rotated_ones_earlier_key_still_holds(
    tmp_path: Path,
) -> None:
    folder = tmp_path / "certs"
    init(folder, [DRONE, *map(Identity.controller, (0, 1))])
    drone = Tls.load(folder, DRONE)
    drone_key = Verifier.from_pem(drone.cert, drone.ca, now())

    def verifier(cid: int) -> Verifier:
        station = Tls.load(folder, Identity.controller(cid))
        return Verifier.from_pem(station.cert, station.ca, now(), Identity.controller(cid))

    old_key, old = station(folder, 1), verifier(1)
    issue(folder, Identity.controller(1))  # rotated: a new key and certificate
    new_key, new = station(folder, 1), verifier(1)
    assert new.serial != old.serial
    rotated = Keys(drone_key, {0: verifier(0), 1: new}, {1: (old,)})

    def by(signer: Signer) -> ring_pb2.LogMessage:
        message = ring_pb2.LogMessage(lognr=3, origin=1, sender=1)
        signer.seal(message)
        return message

    # Rotated, not revoked: what the old key signed still holds, the new key's too.
    assert refusal(rotated, by(old_key), 0) is None
    assert refusal(rotated, by(new_key), 0) is None
    revoked = replace(rotated, revoked=frozenset({old.serial}))
    assert f"controller 1's revoked certificate (serial {old.serial:x})" in (
        refusal(revoked, by(old_key), 0) or ""
    )
    assert refusal(revoked, by(new_key), 0) is None
    # A revoked drone certificate backs no claim and no reply.
    no_drone = replace(rotated, revoked=frozenset({drone_key.serial}))
    claim = by(new_key)
    claim.epoch = 1
    new_key.seal(claim)
    assert "the drone's certificate" in (refusal(no_drone, claim, 0) or "")

"""A sync frame's words on a signed ring: believed on evidence a lying station cannot make
(issue 33; docs/design.md, "A sync frame's words, believed on evidence")."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.protocol import started

from baton.authenticity import holding_proof
from baton.controller.core import ControllerCore, Keep, Note, Persist
from baton.controller.history import LogHistory
from baton.controller.link_core import SyncWord, sync_word
from baton.controller.protocol import ControllerProtocol, Diverged, SendLog, State, Unqueued
from baton.digest import request_digest
from baton.sim.lying import SimKeys, sim_keys
from baton.v1 import drone_pb2, ring_pb2

NOW = "/baton.v1.Clock/Now"
RING = [0, 1, 2]


@pytest.fixture
def keys() -> SimKeys:
    return sim_keys(7, RING)


def clock(reqnr: int) -> ring_pb2.LogEntry:
    """A Clock reading: the master's own word, no drone signature needed."""
    return ring_pb2.LogEntry(
        reqnr=reqnr, method=NOW, reply=f"t{reqnr}".encode(), request_digest=request_digest(NOW, b"")
    )


def grant(keys: SimKeys, master: int, epoch: int) -> drone_pb2.Grant:
    made = drone_pb2.Grant(master=master, epoch=epoch, kind=drone_pb2.GRANT_KIND_TAKEOVER)
    keys.drone.seal_grant(made)
    return made


def signed_core(keys: SimKeys, cid: int, initial_master: int = 0) -> ControllerCore:
    """Controller ``cid`` of ring 0 -> 1 -> 2 with its key, checking the ring's."""
    p = ControllerProtocol(cid, RING, 0)
    p.seal = keys.controllers[cid].seal
    p.start()
    p.on_sync(0)
    core = ControllerCore(p)
    core.keys = keys.keys
    if cid == initial_master:
        core.granted(drone_pb2.Connected(epoch=1, grant=grant(keys, cid, 1)))
    return core


def flushed(core: ControllerCore, reqnr: int) -> ring_pb2.LogMessage:
    """The master answers a Clock call; with a flush limit of 0 it is flushed at once."""
    sent = [e for e in core.protocol.on_reply(clock(reqnr)) if isinstance(e, SendLog)]
    return sent[0].message


def test_the_watermark_moves_only_over_the_masters_own_messages_proved_held(
    keys: SimKeys,
) -> None:
    """Lie 1: "I hold N" from the master's predecessor moved the watermark, and the drone
    let go of replies the taker may lack. On a signed ring only the proof of holding the
    master's own message moves it: a word without it, with another message's, or of a
    number the sender does not hold (it cannot compute that proof) moves nothing."""
    master = signed_core(keys, 0)
    one, two, three = (flushed(master, n) for n in (1, 2, 3))
    p = master.protocol

    def word(holds: int, proof: bytes = b"") -> SyncWord:
        return SyncWord(holds, 1, 0, 0, holds_proof=proof, holds_grant=one.grant)

    master.sync_arrived(2, word(3))  # no proof
    master.sync_arrived(2, word(3, holding_proof(one)))  # another message's proof
    assert master.refused_words == 2 and "holds our message 3 without" in master.last_refused_word
    master.sync_arrived(2, word(9, holding_proof(three)))  # a number it never made
    assert p.watermark_reqnr == 0 and master.refused_words == 2
    assert p.catch_up_to == 9  # the number is still a promise: not a watermark
    master.sync_arrived(2, word(2, holding_proof(two)))
    assert p.watermark_reqnr == 2
    # Proved as its predecessor holds it (forwarded, origin and flag aside).
    forwarded = ring_pb2.LogMessage()
    forwarded.CopyFrom(three)
    forwarded.origin = 1
    master.sync_arrived(2, word(3, holding_proof(forwarded)))
    assert p.watermark_reqnr == 3


def test_a_message_sent_straight_to_a_prepared_target_is_not_proved_by_its_word(
    keys: SimKeys,
) -> None:
    """A prepared handover's target holds the master's messages without the ring: its
    proof says nothing of the controllers between. A later message sent by the ring only
    is proved again, and with it what came before."""
    master = signed_core(keys, 0)
    p = master.protocol
    p.on_prepare(2, 1)
    copied = flushed(master, 1)
    master.sync_arrived(2, SyncWord(1, 0, 0, 0, holds_proof=holding_proof(copied)))
    assert p.watermark_reqnr == 0
    p.end_preparation()
    later = flushed(master, 2)
    master.sync_arrived(2, SyncWord(2, 0, 0, 0, holds_proof=holding_proof(later)))
    assert p.watermark_reqnr == 2


def test_on_an_insecure_ring_the_word_moves_the_watermark_as_before() -> None:
    master = ControllerCore(started(0, RING, 0))
    master.protocol.on_reply(clock(1))
    master.sync_arrived(2, SyncWord(1, 0, 0, 0))
    assert master.protocol.watermark_reqnr == 1 and master.refused_words == 0


def test_a_sync_frame_proves_what_its_history_holds(keys: SimKeys) -> None:
    """The sender's side: ``sync_word`` gives the proof and the grant of its top message
    when it is signed, neither when it is not."""
    master = signed_core(keys, 0)
    message = flushed(master, 1)
    history = LogHistory()
    history.add(message)
    said = sync_word(history, 1, (0, 0))
    assert said.holds_proof == holding_proof(message) and said.holds_grant == message.grant
    plain = LogHistory()
    plain.add(ring_pb2.LogMessage(lognr=1, origin=0, sender=0, epoch=1))
    said = sync_word(plain, 1, (0, 0))
    assert said.holds_proof == b"" and said.holds_grant is None


class NoReadBack(LogHistory):
    """A history whose messages cannot be read back: what a sync word needs is kept."""

    def get(self, lognr: int) -> ring_pb2.LogMessage:
        raise AssertionError(f"log message {lognr} read back for a sync word")


def test_the_proof_is_computed_once_with_the_signature_or_the_check_never_read_back(
    keys: SimKeys,
) -> None:
    """The master's proof comes with its signature (``Persist.proof``), a receiver's with
    its check (``Keep.proof``); the history keeps them beside the message, so a sync word
    (one per message on the successor's stream) neither reads back nor hashes again a
    message that may carry 64 MB of pictures."""
    master = signed_core(keys, 0)
    sent = [e for e in master.protocol.on_reply(clock(1)) if isinstance(e, SendLog)]
    persisted = [e for e in master.ready(sent, True, 0.0) if isinstance(e, Persist)]
    assert [p.proof for p in persisted] == [holding_proof(sent[0].message)]
    replica = signed_core(keys, 1)
    kept = [e for e in replica.log_arrived(sent[0].message, lambda: True) if isinstance(e, Keep)]
    assert [k.proof for k in kept] == [holding_proof(sent[0].message)]
    history = NoReadBack()
    history.add(kept[0].message, kept[0].proof)
    said = sync_word(history, 1, (0, 1))
    assert said.holds_proof == kept[0].proof and said.holds_grant == sent[0].message.grant
    assert history.heading(1).epoch == sent[0].message.epoch


def test_a_history_recovered_from_its_file_proves_what_it_holds(
    keys: SimKeys, tmp_path: Path
) -> None:
    """A restarted controller's history computes a recovered message's heading from the
    file once, when first asked."""
    message = flushed(signed_core(keys, 0), 1)
    first = LogHistory(tmp_path / "log.sqlite")
    first.add(message)
    first.close()
    again = LogHistory(tmp_path / "log.sqlite")
    said = sync_word(again, 1, (0, 1))
    assert said.holds_proof == holding_proof(message) and said.holds_epoch == message.epoch


def queued_behind_a_gap(core: ControllerCore, keys: SimKeys) -> None:
    """A replica holding message 1 (epoch 1) with message 3 (epoch 1) queued above a gap."""
    for lognr in (1, 3):
        m = ring_pb2.LogMessage(lognr=lognr, origin=0, sender=0, epoch=1, after_reqnr=lognr - 1)
        m.entries.append(clock(lognr))
        m.grant.CopyFrom(grant(keys, 0, 1))
        keys.controllers[0].seal(m)
        core.log_arrived(m, lambda: True, relayed_by=0)
    assert core.refused_messages == 0, core.last_refused
    assert 3 in core.protocol.log_queue


def test_a_master_word_is_believed_only_signed_by_its_master_with_the_drones_grant(
    keys: SimKeys,
) -> None:
    """Lie 2: "the newest master is epoch E at log number L" made the receiver drop the
    messages it queued of older masterships above L. Refused: a word without its master's
    signed word, signed by another than the master it names, without the drone's grant
    of E to it, or with its numbers changed by a relay. Counted each time, logged once per
    station. The master's own word, said on by any relay, is believed."""
    replica = signed_core(keys, 1)
    queued_behind_a_gap(replica, keys)
    liar = keys.controllers[2]

    def word(epoch: int, lognr: int, master: int, by: int, backed: bool = True) -> SyncWord:
        signed = ring_pb2.MasterWord(epoch=epoch, lognr=lognr, master=master)
        if backed:
            signed.grant.CopyFrom(grant(keys, master, epoch))
        keys.controllers[by].seal(signed)
        return SyncWord(1, 0, epoch, lognr, master_proof=signed)

    bare = SyncWord(1, 0, 6, 0)
    assert isinstance(replica.sync_arrived(2, bare)[0], Note)
    lies = [
        word(6, 0, master=0, by=2),  # in another's name
        word(6, 0, master=2, by=2, backed=False),  # its own, without the drone's grant
    ]
    ungranted = ring_pb2.MasterWord(epoch=6, lognr=0, master=2)
    ungranted.grant.CopyFrom(grant(keys, 0, 6))  # the drone's grant is to controller 0
    liar.seal(ungranted)
    lies.append(SyncWord(1, 0, 6, 0, master_proof=ungranted))
    genuine = word(2, 2, master=0, by=0)
    assert genuine.master_proof is not None
    lowered = ring_pb2.MasterWord()
    lowered.CopyFrom(genuine.master_proof)
    lowered.lognr = 0  # a relay lowers the number: the master's signature no longer holds
    lies.append(SyncWord(1, 0, 2, 0, master_proof=lowered))
    for lie in lies:
        effects = replica.sync_arrived(2, lie)
        assert not [e for e in effects if isinstance(e, Note | Unqueued)]
    assert 3 in replica.protocol.log_queue and replica.protocol.master_word == (0, 0)
    assert replica.refused_words == 5
    assert "controller 2" in replica.last_refused_word
    # Said on by controller 2, the genuine word drops the older message above its number.
    effects = replica.sync_arrived(2, genuine)
    assert [(type(e), e.lognr) for e in effects if isinstance(e, Unqueued)] == [(Unqueued, 3)]
    assert replica.protocol.master_word == (2, 2)
    assert replica.protocol.master_proof == genuine.master_proof
    assert replica.refused_words == 5


def test_a_master_signs_its_word_once_when_it_goes_active(keys: SimKeys) -> None:
    """The word holds for the whole mastership: every message above the number it held
    when it went ACTIVE is its own or newer."""
    master = signed_core(keys, 0)
    p = master.protocol
    assert p.state is State.ACTIVE
    word = p.master_proof
    assert word is not None and (word.epoch, word.lognr, word.master) == (1, 0, 0)
    flushed(master, 1)
    assert p.master_proof is word and p.master_word == (1, 1)
    replica = signed_core(keys, 2)
    replica.sync_arrived(1, SyncWord(0, 0, *p.master_word, master_proof=p.master_proof))
    assert replica.refused_words == 0 and replica.protocol.master_word == (1, 0)
    assert started(0, RING, 0).master_proof is None  # an insecure ring signs nothing


def test_a_newer_epoch_of_a_held_number_is_believed_only_with_the_drones_grant(
    keys: SimKeys,
) -> None:
    """``holds_epoch``: a sender whose message with one of our numbers is of a newer
    epoch makes us rejoin with nothing. A station that says so of a message it does not
    hold could make any replica drop its log: on a signed ring the word needs the drone's
    grant of that epoch (the message carries it), and an ACTIVE master never rejoins on
    it (only the drone fences it)."""
    replica = signed_core(keys, 1)
    queued_behind_a_gap(replica, keys)
    lie = SyncWord(1, 5, 0, 0)
    assert not [e for e in replica.sync_arrived(2, lie) if isinstance(e, Diverged)]
    assert replica.refused_words == 1 and replica.protocol.lognr == 1
    backed = SyncWord(1, 5, 0, 0, holds_grant=grant(keys, 2, 5))
    assert [e for e in replica.sync_arrived(2, backed) if isinstance(e, Diverged)]
    master = signed_core(keys, 0)
    flushed(master, 1)
    master.protocol.on_granted(2, grant=grant(keys, 0, 2))
    effects = master.sync_arrived(2, SyncWord(1, 2, 0, 0, holds_grant=grant(keys, 2, 2)))
    assert not [e for e in effects if isinstance(e, Diverged)]


def test_a_promise_above_what_we_hold_is_waited_for_only_in_a_granted_epoch(
    keys: SimKeys,
) -> None:
    """A word that the sender holds more than we do holds a master granted the role until
    it handled that much. A station promising what it never sends would hold it for ever:
    on a signed ring the promise counts only in an epoch the drone granted (taken back once
    a newer one is handled), never with no epoch or an ungranted one."""
    replica = signed_core(keys, 1)
    queued_behind_a_gap(replica, keys)
    p = replica.protocol
    for lie in (SyncWord(9, 0, 0, 0), SyncWord(9, 8, 0, 0)):
        replica.sync_arrived(2, lie)
        assert p.catch_up_to == p.lognr == 1
    replica.sync_arrived(2, SyncWord(9, 1, 0, 0, holds_grant=grant(keys, 0, 1)))
    assert p.catch_up_to == 9

"""A lying station (issue 33): keys for every part, and one station's forged frames.

With ``--lying`` the world's parts hold keys and use them as the runtime does,
through the same interface (``baton.authenticity``: ``Signer``, ``Verifier``,
``Keys``): the drone signs its replies and grants, each controller seals the
log messages it creates, and every controller's core checks every message that
arrives (``ControllerCore.log_arrived``). The keys are Ed25519, derived from the
seed (a run replays exactly, and Ed25519 signatures are deterministic): the
runtime's certificates carry ECDSA P-256 keys, which ``authenticity`` takes
alike; no certificate is made, as the simulation has no TLS.

One station (drawn from a random stream of its own) is stolen: at drawn moments
in the fault window it sends a forged frame to another live controller, made
from what it holds, as an attacker with its key could: a newer mastership in
its own name without the drone's grant, a handover making the receiver master,
a genuine old grant played again for a newer epoch, a genuine handover grant of
another station's handover carried by a message of its epoch in the liar's
name or its new master's (every message of the epoch carries the grant),
invented replies, a genuine
message altered, or sent again under another number. Each is delivered to the
receiver's core as a ring stream from the liar delivers it, and the
``lies-refused`` oracle asks that every one was refused (counted in the
receiver's ``refused_messages``), besides every other oracle.

It also lies in sync frames (``SYNC_LIES``, ``forge_sync``), delivered as a sync
frame from it is (``SimController.on_sync``): that it holds the receiver's top
message without the proof of holding it, that it holds more than the receiver
(the truth's shape: its own top's epoch, grant and proof, the number inflated),
a newer master in its own name, a genuine master word with its numbers
changed, a newer epoch of a message the receiver holds, and that it holds less
than it does (``holds-deflated``). Such a frame is refused when it changed
nothing it must not: the receiver's watermark, the master word it believes and
says on, its queue, its log (a rejoin). A word that it holds less may be
believed (the receiver takes itself for caught up): what acting on it can do is
bounded by the drone's word, and every other oracle judges the run.
"""

from __future__ import annotations

import hashlib
import random
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

from cryptography.hazmat.primitives.asymmetric import ed25519

from baton.authenticity import Keys, Signer, Verifier
from baton.controller.link_core import SyncWord, sync_word
from baton.digest import request_digest
from baton.sim.mission import GET_POSITION
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2, ring_pb2

if TYPE_CHECKING:
    from baton.sim.controller import SimController
    from baton.sim.faults import FaultPlan
    from baton.sim.world import World

# What a lying station forges (``forge``).
LIES = (
    "newer-mastership",
    "handover-to-receiver",
    "old-grant-again",
    "borrowed-handover-grant",
    "invented-replies",
    "altered-reply",
    "renumbered",
    # Sync frames (``forge_sync``).
    "holds-unproved",
    "holds-inflated",
    "master-word-forged",
    "master-word-altered",
    "holds-epoch-newer",
    "holds-deflated",
)
SYNC_LIES = frozenset(LIES[7:])
# How far ahead of the newest epoch it knows a forged mastership claims to be.
EPOCHS_AHEAD = (1, 2, 5)


@dataclass(frozen=True)
class SimKeys:
    """Every part's key and what the controllers check against."""

    drone: Signer
    controllers: dict[int, Signer]
    keys: Keys


def _key(seed: int, part: str) -> ed25519.Ed25519PrivateKey:
    return ed25519.Ed25519PrivateKey.from_private_bytes(
        hashlib.sha256(f"baton sim key {seed} {part}".encode()).digest()
    )


def sim_keys(seed: int, ring: list[int]) -> SimKeys:
    """The seed's keys: the drone's and each controller's."""
    drone = _key(seed, "drone")
    controllers = {cid: _key(seed, f"controller {cid}") for cid in ring}
    keys = Keys(
        Verifier(drone.public_key()),
        {cid: Verifier(key.public_key()) for cid, key in controllers.items()},
    )
    return SimKeys(Signer(drone), {cid: Signer(key) for cid, key in controllers.items()}, keys)


@dataclass(frozen=True)
class Lie:
    """One forged frame and what its receiver did with it."""

    at: float
    kind: str
    liar: int
    receiver: int
    lognr: int
    refused: bool


def plan_lying(world: World, plan: FaultPlan) -> None:
    """Draws the stolen station and the moments it lies at (a random stream of its own)."""
    rng = random.Random(f"lying {world.seed}")
    liar = rng.choice(world.ring)
    count = rng.randint(2, 6)
    moments = sorted(rng.uniform(0.0, plan.fault_end) for _ in range(count))
    plan.lying = f"controller {liar} forges {count} frames"
    for at in moments:
        world.loop.at(at, lie, world, rng, liar)


def lie(world: World, rng: random.Random, liar: int) -> None:
    """The liar, if it runs, sends one forged frame to another live controller."""
    forger = world.controller(liar)
    others = [c for c in world.live_controllers() if c.id != liar]
    if not forger.alive or not others or world.keys is None:
        return
    receiver = rng.choice(others)
    kind = rng.choice(LIES)
    if kind in SYNC_LIES:
        lie_in_sync(world, rng, liar, receiver, kind)
        return
    message = forge(world, rng, liar, receiver.id, kind)
    if message is None:  # nothing to forge it from yet: a mastership ahead instead
        kind = "newer-mastership"
        message = forge(world, rng, liar, receiver.id, kind)
    assert message is not None
    before = receiver.core.refused_messages
    receiver.receive_relayed(message, liar)
    refused = receiver.core.refused_messages == before + 1
    world.lies.append(Lie(world.loop.now, kind, liar, receiver.id, message.lognr, refused))
    world.trace(
        f"controller {liar} forges {kind} (log message {message.lognr}) to {receiver.id}: "
        + ("refused" if refused else "BELIEVED")
    )


def lie_in_sync(
    world: World, rng: random.Random, liar: int, receiver: SimController, kind: str
) -> None:
    """The liar sends ``receiver`` a forged sync frame of ``kind``: refused if it changed
    nothing the lie is about (``believed``)."""
    word = forge_sync(world, rng, liar, receiver, kind)
    before = _what_words_move(receiver)
    receiver.on_sync(liar, word)
    after = _what_words_move(receiver)
    refused = not receiver.alive or not believed(kind, before, after)
    world.lies.append(Lie(world.loop.now, kind, liar, receiver.id, word.holds, refused))
    world.trace(
        f"controller {liar} forges a {kind} sync frame (holds {word.holds}, epoch "
        f"{word.holds_epoch}, master {word.master_epoch}/{word.master_lognr}) to "
        f"{receiver.id}: " + ("refused" if refused else f"BELIEVED {before} -> {after}")
    )


@dataclass(frozen=True)
class _Moved:
    """What a sync frame's words can move at a receiver."""

    watermark: int
    heard: tuple[int, int]  # the newest master word the ring gave it
    queued: frozenset[int]
    rejoining: bool
    caught_up: bool


def _what_words_move(receiver: SimController) -> _Moved:
    p = receiver.protocol
    heard = p.heard_master_word
    return _Moved(
        p.watermark_reqnr, heard, frozenset(p.log_queue), receiver.core.rejoining, p.caught_up
    )


def believed(kind: str, before: _Moved, after: _Moved) -> bool:
    """Whether the receiver acted on a forged sync frame of ``kind``: the watermark moved
    on a word of holding, the master word it says on changed or a queued message was
    dropped on a master word, it rejoins on an epoch."""
    if kind in ("holds-unproved", "holds-inflated"):
        return after.watermark != before.watermark
    if kind.startswith("master-word"):
        return after.heard != before.heard or not before.queued <= after.queued
    if kind == "holds-deflated":
        # Believing it is allowed: it can only make a controller take what it holds for
        # all there is (caught up), and acting on that is bounded by the drone's word
        # (a taker's watermark, the handover message a cooperative grant owes, a master
        # that persists what it creates before sending it). The other oracles judge it.
        return False
    return after.rejoining and not before.rejoining


def forge_sync(
    world: World, rng: random.Random, liar: int, receiver: SimController, kind: str
) -> SyncWord:
    """A sync frame of ``kind`` as the liar makes it from what it holds."""
    assert world.keys is not None
    forger = world.controller(liar)
    stolen = world.keys.controllers[liar]
    p, theirs = forger.protocol, receiver.protocol
    top = forger.history.holds_lognr
    held = forger.history.get(top) if top and top in forger.history else None
    # Each lie says one thing: the rest of the frame says nothing that could count.
    own = sync_word(forger.history, top, (0, 0))
    nothing_held = SyncWord(0, 0, 0, 0)
    newest = max(p.epoch, theirs.epoch, held.epoch if held is not None else 0)
    if kind in ("holds-unproved", "holds-inflated"):
        # At least what the receiver waits for already: a word that it holds less
        # would not move the watermark, and is not this lie.
        holds = max(theirs.lognr, theirs.catch_up_to or 0)
        holds += rng.randint(1, 5) if kind == "holds-inflated" else 0
        if holds == top:
            return replace(own, holds_proof=b"")  # the one it holds: without its proof
        return replace(own, holds=holds)  # its own top's epoch, grant and proof
    if kind == "master-word-forged":
        word = ring_pb2.MasterWord(
            epoch=newest + rng.choice(EPOCHS_AHEAD), lognr=rng.randint(0, theirs.lognr), master=liar
        )
        if held is not None and held.HasField("grant"):
            word.grant.CopyFrom(held.grant)  # a genuine grant of another epoch
        stolen.seal(word)
        return replace(
            nothing_held, master_epoch=word.epoch, master_lognr=word.lognr, master_proof=word
        )
    if kind == "master-word-altered":
        genuine = own.master_proof or theirs.master_proof
        word = ring_pb2.MasterWord()
        if genuine is not None:
            word.CopyFrom(genuine)  # its master's signature, no longer over what it says
        if word.lognr > 0 and rng.random() < 0.5:
            word.lognr -= rng.randint(1, word.lognr)
        else:
            word.epoch += rng.choice(EPOCHS_AHEAD)
        return replace(
            nothing_held, master_epoch=word.epoch, master_lognr=word.lognr, master_proof=word
        )
    if kind == "holds-deflated":
        # Less than the liar holds (its own message's epoch, grant and proof, as far
        # as they go), at most what the receiver handled: "you have all I have".
        holds = rng.randint(0, min(top, theirs.lognr))
        return sync_word(forger.history, holds, (0, 0)) if holds else nothing_held
    # holds-epoch-newer: a message the receiver holds, said to be of a newer epoch.
    holds = theirs.lognr
    epoch = theirs.epoch_of(holds) + rng.choice(EPOCHS_AHEAD)
    return replace(nothing_held, holds=holds, holds_epoch=epoch)


def forge(
    world: World, rng: random.Random, liar: int, receiver: int, kind: str
) -> ring_pb2.LogMessage | None:
    """A frame of ``kind`` as the liar makes it from what it holds (None: it holds no
    message to make it from)."""
    assert world.keys is not None
    forger = world.controller(liar)
    p = forger.protocol
    stolen = world.keys.controllers[liar]
    held = [forger.history.get(n) for n in forger.history.above(0)]
    granted = [m for m in held if m.HasField("grant")]
    newest = max([p.epoch, world.controller(receiver).protocol.epoch, *(m.epoch for m in held)])
    lognr = world.controller(receiver).protocol.lognr + 1
    own = ring_pb2.LogMessage(lognr=lognr, origin=liar, sender=liar, after_reqnr=p.reqnr)
    if kind == "newer-mastership":
        own.epoch = newest + rng.choice(EPOCHS_AHEAD)
    elif kind == "handover-to-receiver":
        own.origin, own.handover = receiver, True
        own.epoch = newest + rng.choice(EPOCHS_AHEAD)
    elif kind == "old-grant-again":
        if not granted:
            return None
        old = rng.choice(granted).grant
        own.grant.CopyFrom(old)
        own.epoch = max(newest, old.epoch) + rng.choice(EPOCHS_AHEAD)
    elif kind == "borrowed-handover-grant":
        borrowed = [
            m.grant
            for m in held
            if m.grant.kind == drone_pb2.GRANT_KIND_HANDOVER
            and liar not in (m.grant.master, m.grant.old_master)
        ]
        if not borrowed:
            return None
        grant = rng.choice(borrowed)
        own.grant.CopyFrom(grant)
        own.epoch = grant.epoch
        if rng.random() < 0.5:
            own.origin = grant.master  # as if its new master forwarded it
    elif kind == "invented-replies":
        made_up = api.Position(latitude_deg=1.0, longitude_deg=2.0).SerializeToString()
        own.entries.append(
            ring_pb2.LogEntry(
                reqnr=p.reqnr + 1,
                method=GET_POSITION,
                reply=made_up,
                request_digest=request_digest(GET_POSITION, b""),
            )
        )
    else:
        if not held:
            return None
        genuine = ring_pb2.LogMessage()
        genuine.CopyFrom(rng.choice(held))
        if kind == "altered-reply" and genuine.entries:
            genuine.entries[-1].reply += b"!"
        else:  # renumbered, or a message without entries to alter
            genuine.lognr = lognr + rng.randint(0, 3)
            genuine.after_reqnr += 1
        return genuine  # not sealed again: its creator's signature no longer holds
    stolen.seal(own)
    return own

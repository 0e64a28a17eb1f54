"""What a sync frame's words are believed for, on a signed ring (issue 33).

A sync frame (``link_core.SyncWord``) is its sender's word: what it holds
(``holds``, and the epoch of its message with that number) and the newest
ACTIVE master it knows of (``master_epoch``, ``master_lognr``). One station
with a valid certificate can say anything there, so on a signed ring each word
counts only on evidence it cannot make up (docs/design.md, "A sync frame's
words, believed on evidence"):

- *The master word* only with the master's own signed word
  (``ring_pb2.MasterWord``) and the drone's grant of that epoch to it
  (``authenticity.unbacked_word``); its numbers are then the signed ones. A
  relay says it on unchanged; without it the word is ignored, never a reason
  to drop queued messages.
- *That the sender's message is of an epoch* (``holds_epoch``) only with the
  drone's grant of that epoch, which that message carries (``holds_backed``):
  the protocol rejoins on a newer one only then, and never while ACTIVE
  (``ControllerProtocol._believes_newer``).
- *What it holds* moves the watermark only with the proof that it holds a
  message of the master's own (``authenticity.holding_proof``), which only the
  master can check (``ControllerProtocol._watermark_credit``): nothing here.

Pure: the caller (``ControllerCore.sync_arrived``) counts and logs what is not
believed. On an insecure ring (no keys) every word is taken, as before.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from baton.authenticity import Keys, unbacked_grant, unbacked_word
from baton.controller.link_core import SyncWord


@dataclass(frozen=True)
class Belief:
    """What of a sync frame counts: ``word`` with an unbacked master word taken out;
    whether its ``holds_epoch`` is the drone's word; why anything was not believed."""

    word: SyncWord
    holds_backed: bool
    refused: tuple[str, ...] = ()


def believe(keys: Keys | None, word: SyncWord) -> Belief:
    """What of ``word`` counts against ``keys`` (None: an insecure ring, all of it)."""
    if keys is None:
        return Belief(word, True)
    refused: list[str] = []
    believed = word
    if word.master_epoch > 0 or word.master_proof is not None:
        why = unbacked_word(keys, word.master_proof)
        proof = word.master_proof
        if why is None and proof is not None:
            believed = replace(word, master_epoch=proof.epoch, master_lognr=proof.lognr)
        else:
            refused.append(f"its master word (epoch {word.master_epoch}): {why}")
            believed = replace(word, master_epoch=0, master_lognr=0, master_proof=None)
    holds_backed = True
    if word.holds_epoch > 0:
        why = unbacked_grant(keys, word.holds_grant, word.holds_epoch)
        if why is not None:
            holds_backed = False
            refused.append(f"its message {word.holds} of {why}")
    return Belief(believed, holds_backed, tuple(refused))

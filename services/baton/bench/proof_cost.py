"""A replica's CPU for one signed log message, from its arrival to its sync word: the
signatures' check, the history's write and the word (docs/benchmarks.md, "Sync frames'
words on evidence"). Pure code in one process, timed with ``process_time``:

    python -m baton.bench.proof_cost [--passes 3] [--replies 64] [--reply-bytes 1048576]

Paired against another checkout by running this file with that checkout first on the path
(``PYTHONPATH=OTHER/services python services/baton/bench/proof_cost.py``);
a checkout whose history takes no proof (before the proof was kept beside the message)
is timed the same way and says "before".
"""

from __future__ import annotations

import argparse
import inspect
import os
import time

from baton.controller.core import ControllerCore, Keep
from baton.controller.history import LogHistory
from baton.controller.link_core import sync_word
from baton.controller.protocol import ControllerProtocol
from baton.digest import request_digest
from baton.sim.lying import SimKeys, sim_keys
from baton.v1 import drone_pb2, ring_pb2

NOW = "/baton.v1.Clock/Now"
RING = [0, 1, 2]


def signed_message(keys: SimKeys, replies: int, reply_bytes: int) -> ring_pb2.LogMessage:
    """Master 0's log message 1 of epoch 1, ``replies`` Clock answers of ``reply_bytes``."""
    message = ring_pb2.LogMessage(lognr=1, origin=0, sender=0, epoch=1, after_reqnr=0)
    digest = request_digest(NOW, b"")
    for reqnr in range(1, replies + 1):
        reply = os.urandom(reply_bytes)
        message.entries.append(
            ring_pb2.LogEntry(reqnr=reqnr, method=NOW, reply=reply, request_digest=digest)
        )
    grant = drone_pb2.Grant(master=0, epoch=1, kind=drone_pb2.GRANT_KIND_TAKEOVER)
    keys.drone.seal_grant(grant)
    message.grant.CopyFrom(grant)
    keys.controllers[0].seal(message)
    return message


def replica(keys: SimKeys) -> ControllerCore:
    """Controller 1 of the ring, checking the ring's signatures."""
    protocol = ControllerProtocol(1, RING, 0)
    protocol.seal = keys.controllers[1].seal
    protocol.start()
    protocol.on_sync(0)
    core = ControllerCore(protocol)
    core.keys = keys.keys
    return core


def one_pass(keys: SimKeys, message: ring_pb2.LogMessage, proof_kept: bool) -> float:
    """CPU seconds for a fresh replica to take ``message`` and say it holds it."""
    core, history = replica(keys), LogHistory()
    began = time.process_time()
    for effect in core.log_arrived(message, lambda: True):
        if isinstance(effect, Keep):
            history.add(effect.message, effect.proof) if proof_kept else history.add(effect.message)
    word = sync_word(history, message.lognr, (0, 1))
    took = time.process_time() - began
    if not word.holds_proof or core.refused_messages:
        raise SystemExit(f"the message was not taken: {core.last_refused}")
    history.close()
    return took


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--passes", type=int, default=3)
    parser.add_argument("--replies", type=int, default=64)
    parser.add_argument("--reply-bytes", type=int, default=1 << 20)
    args = parser.parse_args()
    keys = sim_keys(7, RING)
    message = signed_message(keys, args.replies, args.reply_bytes)
    proof_kept = "proof" in inspect.signature(LogHistory.add).parameters
    times = sorted(one_pass(keys, message, proof_kept) for _ in range(args.passes))
    size = message.ByteSize() / (1 << 20)
    print(
        f"{'after ' if proof_kept else 'before'} CPU per {size:.0f} MB message: "
        f"min {times[0] * 1e3:.0f} ms, median {times[len(times) // 2] * 1e3:.0f} ms"
    )


if __name__ == "__main__":
    main()

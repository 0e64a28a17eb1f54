"""What baton.authenticity costs (docs/benchmarks.md, "Signatures"): the drone signing
one reply and a controller checking it, and a log message of 64 pictures of 1 MiB and
one of 1000 small replies sealed by its creator and checked whole by a receiver, and
the drone's grant of a mastership signed and checked (``unbacked_claim``).

    .venv/bin/python tools/signing_cost.py
"""

from __future__ import annotations

import datetime
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

from baton.authenticity import Keys, Signer, Verifier, refusal, signed_reply, unbacked_claim
from baton.certs.make import init
from baton.digest import request_digest
from baton.rpc.tls import DRONE, Identity, Tls
from baton.v1 import drone_pb2, ring_pb2

PICTURE = "/baton.v1.Camera/TakePicture"
DIGEST = request_digest(PICTURE, b"")
STATION = Identity.controller(0)


def p50_ms(work: Callable[[], object], times: int) -> float:
    """The median wall time of ``work``, in milliseconds."""
    samples = []
    for _ in range(times):
        start = time.perf_counter()
        work()
        samples.append(time.perf_counter() - start)
    return sorted(samples)[len(samples) // 2] * 1e3


def main() -> None:
    folder = Path(tempfile.mkdtemp()) / "certs"
    init(folder, [DRONE, STATION])
    now = datetime.datetime.now(datetime.UTC)
    drone, station = Tls.load(folder, DRONE), Tls.load(folder, STATION)
    signer, master = Signer.from_pem(drone.key), Signer.from_pem(station.key)
    keys = Keys(
        Verifier.from_pem(drone.cert, drone.ca, now),
        {0: Verifier.from_pem(station.cert, station.ca, now, STATION)},
    )

    def entry(reqnr: int, size: int) -> ring_pb2.LogEntry:
        reply = signed_reply(signer, reqnr, 1, PICTURE, DIGEST, bytes(size))
        return ring_pb2.LogEntry(
            reqnr=reqnr,
            method=PICTURE,
            reply=reply.payload,
            request_digest=DIGEST,
            drone_epoch=1,
            drone_signature=reply.signature,
        )

    for size in (64, 1 << 20):
        one = entry(1, size)
        sign = p50_ms(partial(signer.sign, 1, 1, PICTURE, DIGEST, one.reply), 101)
        check = p50_ms(partial(keys.drone.verify, one), 101)
        print(
            f"reply of {size} B: the drone signs {sign:.3f} ms, a controller checks {check:.3f} ms"
        )
    cases = {
        "64 replies of 1 MiB": [entry(n, 1 << 20) for n in range(1, 65)],
        "1000 replies of 64 B": [entry(n, 64) for n in range(1, 1001)],
    }
    for name, entries in cases.items():
        message = ring_pb2.LogMessage(lognr=1, sender=0, epoch=1, entries=entries)
        message.grant.CopyFrom(drone_pb2.Grant(master=0, epoch=1, kind=drone_pb2.GRANT_KIND_FIRST))
        signer.seal_grant(message.grant)
        seal = p50_ms(partial(master.seal, message), 7)
        assert refusal(keys, message, 1) is None
        check = p50_ms(partial(refusal, keys, message, 1), 7)
        print(
            f"log message of {name}: its creator seals {seal:.1f} ms, "
            f"a receiver checks {check:.1f} ms"
        )
    claim = ring_pb2.LogMessage(lognr=1, sender=0, origin=0, epoch=1)
    claim.grant.CopyFrom(drone_pb2.Grant(master=0, epoch=1, kind=drone_pb2.GRANT_KIND_FIRST))
    sign = p50_ms(partial(signer.seal_grant, claim.grant), 1001)

    def first_check() -> None:  # a grant the receiver has not seen yet
        assert unbacked_claim(Verifier(keys.drone.key), claim, 1) is None

    first = p50_ms(first_check, 1001)
    again = p50_ms(partial(unbacked_claim, keys.drone, claim, 1), 1001)
    print(
        f"a mastership grant: the drone signs {sign:.3f} ms, a receiver checks it "
        f"{first:.3f} ms the first time, {again:.3f} ms on every message after"
    )


if __name__ == "__main__":
    main()

"""Issue 33 across real processes under mutual TLS: a station holding a valid certificate
lies in the sync frames it sends (what it holds, the newest master, the epoch of a
message). The receivers believe none of it (docs/design.md, "A sync frame's words,
believed on evidence"): the master's watermark does not move, no queued message is
dropped, nobody rejoins or waits for what never comes, and the mission completes exactly
once with every replica's program seeing the same replies."""

from __future__ import annotations

import asyncio
from pathlib import Path

from helpers.forgery import operator_hands_over, say, signed_message
from helpers.missions import assert_mission_promises, three_on_fast_links
from waiting import eventually

from baton.authenticity import Signer
from baton.config import LinkSpec
from baton.rpc.channels import aio_channel
from baton.rpc.tls import Identity, Tls
from baton.testbed.local import LocalTestbed
from baton.v1 import ring_pb2, ring_pb2_grpc

# The ring behind the master slowed, so its own messages wait this long for the proof
# that its predecessor holds them: a lie about holding one comes first. Long enough that
# the honest proof cannot arrive between the lie and the check of the watermark on a
# loaded machine (2 s, then 6 s, were not: two pytest workers' testbeds beside it made
# the lie and its refusal take longer); the frames it delays reach the victim later.
SLOW_RING_S = 20.0
# How many messages more than it holds the liar tells the victim it holds.
PROMISED = 500


async def test_lying_sync_words_are_not_believed_and_the_mission_flies_once(
    tmp_path: Path,
) -> None:
    plan = three_on_fast_links()
    master, liar, victim = 0, 1, 2  # ring 0 -> 1 -> 2: 2 is the master's predecessor
    async with LocalTestbed(plan, tmp_path) as testbed:
        config = testbed.config
        assert config is not None and testbed.tls is not None

        async def signed_in_log() -> ring_pb2.LogMessage | None:
            return await asyncio.to_thread(signed_message, testbed.controller_log(victim))

        genuine = await eventually(signed_in_log, "a drone-signed reply in the log", 120)
        station = Tls.load(config.tls.certs, Identity.controller(liar))  # stolen from a mast
        stolen_key = Signer.from_pem(station.key)
        epoch, grant = genuine.epoch, genuine.grant  # the master's, in every message of it

        async def status(cid: int) -> ring_pb2.ControllerStatus:
            address = config.controller(cid).address
            async with aio_channel(address, station, Identity.controller(cid)) as channel:
                ring = ring_pb2_grpc.ControllerRingStub(channel)
                return await ring.GetStatus(ring_pb2.GetControllerStatusRequest())

        async def refused(cid: int, count: int, why: str) -> None:
            async def counted() -> ring_pb2.ControllerStatus | None:
                s = await status(cid)
                return s if s.refused_words >= count else None

            s = await eventually(counted, f"controller {cid} refusing {count} words", 30)
            assert s.refused_words == count, s.last_refused_word
            assert f"from controller {liar}" in s.last_refused_word, s.last_refused_word
            assert why in s.last_refused_word, s.last_refused_word

        # Lie 1, to the master: "I hold your newest message" (its hello's top), with the
        # mastership's genuine grant but without the proof of holding it. Believed, it
        # moved the watermark over messages its successors did not hold yet.
        testbed.reshape_link("link-ring-1", LinkSpec(latency=SLOW_RING_S))
        # The emulator takes its new shape on a signal: what the master logged until
        # about now may still cross at the old speed, and its proof move the watermark
        # honestly (CI saw it reach the request the test had taken as lagging: 2 < 2).
        # Three requests later, the lie's "your newest" lies beyond that.
        shaped = (await status(master)).reqnr

        async def lagging() -> ring_pb2.ControllerStatus | None:
            s = await status(master)
            return s if s.reqnr >= max(s.watermark_reqnr, shaped) + 3 else None

        before = await eventually(lagging, "the master's watermark lagging", 60)
        await say(
            config.controller(master).address,
            station,
            master,
            lambda hello: [
                ring_pb2.LogFrame(holds_lognr=hello.lognr, holds_epoch=epoch, holds_grant=grant)
            ],
        )
        await refused(master, 1, "without the proof")
        after = await status(master)
        assert after.watermark_reqnr < before.reqnr, (after.watermark_reqnr, before.reqnr)
        testbed.reshape_link("link-ring-1", config.controller_link)

        # To the victim, on one stream: a promise of many more messages of no epoch (a new
        # master would wait for them for ever); a newer master in its own name with the
        # master's grant; the master's word with its number changed, signed by the liar;
        # its top message said to be of an epoch 5 on, without the drone's grant (it would
        # rejoin with nothing).
        forged = ring_pb2.MasterWord(epoch=epoch + 5, lognr=0, master=liar, grant=grant)
        stolen_key.seal(forged)
        altered = ring_pb2.MasterWord(epoch=epoch, lognr=0, master=master, grant=grant)
        stolen_key.seal(altered)

        told: list[int] = []  # the victim's top when it was lied to

        def lies(hello: ring_pb2.LogAck) -> list[ring_pb2.LogFrame]:
            told.append(hello.lognr)
            return [
                ring_pb2.LogFrame(holds_lognr=hello.lognr + PROMISED),
                ring_pb2.LogFrame(
                    holds_lognr=hello.lognr,
                    holds_epoch=hello.epoch,
                    holds_grant=grant,
                    master_epoch=forged.epoch,
                    master_lognr=0,
                    master_word=forged,
                ),
                ring_pb2.LogFrame(
                    holds_lognr=hello.lognr,
                    holds_epoch=hello.epoch,
                    holds_grant=grant,
                    master_epoch=epoch,
                    master_lognr=0,
                    master_word=altered,
                ),
                ring_pb2.LogFrame(holds_lognr=hello.lognr, holds_epoch=epoch + 5),
            ]

        await say(config.controller(victim).address, station, victim, lies)
        await refused(victim, 3, f"epoch {epoch + 5} without the drone's grant")
        s = await status(victim)
        assert s.catching_up_to < told[0] + PROMISED and s.program_restarts == 0, s

        # An operator hands over to the victim: it goes ACTIVE on the ring's log, not
        # waiting for the promised messages.
        await operator_hands_over(config.drone.address, testbed.tls, victim)
        snapshot = await testbed.run_mission(240)
    assert_mission_promises(snapshot, plan)
    assert snapshot.drone.master == victim
    words = {cid: c.refused_words for cid, c in snapshot.controllers.items()}
    assert words == {master: 1, liar: 0, victim: 3}, words
    assert all(c.program_restarts == 0 for c in snapshot.controllers.values())

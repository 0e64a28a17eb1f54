"""Issue 33 across real processes under mutual TLS: a station holding a valid certificate
cannot invent or alter what the drone answered, nor claim a mastership the drone did not
grant (baton.authenticity). Its forged log messages are refused and named by the
receiver, and the mission completes exactly once (counted where the effects happen) with
every replica's program seeing the same replies."""

from __future__ import annotations

import asyncio
from pathlib import Path

from helpers.forgery import copy, operator_hands_over, send, signed_message
from helpers.missions import assert_mission_promises, three_on_fast_links
from waiting import eventually

from baton.authenticity import Signer
from baton.digest import request_digest
from baton.rpc.channels import aio_channel
from baton.rpc.methods import path
from baton.rpc.tls import Identity, Tls
from baton.testbed.local import LocalTestbed
from baton.v1 import drone_api_pb2 as api
from baton.v1 import ring_pb2, ring_pb2_grpc

GET_POSITION = path("Mobility.GetPosition")


async def test_forged_replies_and_masterships_on_the_ring_are_refused_and_the_mission_flies_once(
    tmp_path: Path,
) -> None:
    plan = three_on_fast_links()
    async with LocalTestbed(plan, tmp_path) as testbed:
        config = testbed.config
        assert config is not None and testbed.tls is not None
        victim = 2  # controller 1's successor: a LogRing stream from 1 is its to take

        async def signed_in_log() -> ring_pb2.LogMessage | None:
            return await asyncio.to_thread(signed_message, testbed.controller_log(victim))

        genuine = await eventually(signed_in_log, "a drone-signed reply in the log", 120)
        station = Tls.load(config.tls.certs, Identity.controller(1))  # stolen from a mast
        stolen_key = Signer.from_pem(station.key)

        # Invented replies in its own name, signed with its own key, claiming no
        # mastership: GetPosition answered with a place the drone never was.
        made_up = api.Position(latitude_deg=1.0, longitude_deg=2.0).SerializeToString()
        digest = request_digest(GET_POSITION, b"")
        last = max(e.reqnr for e in genuine.entries)
        invented = ring_pb2.LogMessage(
            origin=1,
            sender=1,
            after_reqnr=last,
            entries=[
                ring_pb2.LogEntry(
                    reqnr=last + n, method=GET_POSITION, reply=made_up, request_digest=digest
                )
                for n in (1, 2)
            ],
        )
        # A real message of the master with a reply changed.
        altered = copy(genuine)
        next(e for e in altered.entries if e.drone_signature).reply = made_up
        # The master's message again under the next log number, and one claiming a newer
        # mastership in its name (log number 9999, a handover, 5 epochs on).
        newer = copy(genuine)
        newer.lognr, newer.handover, newer.epoch, newer.origin = 9999, True, genuine.epoch + 5, 2
        # Masterships claimed in its own name, signed with its own key: master 5 epochs
        # on; a handover making the victim master then; the same with the master's
        # genuine grant of an older epoch played again; and the master's grant of this
        # epoch for a mastership of its own.
        ahead = genuine.epoch + 5

        def claim(
            origin: int, epoch: int, handover: bool = False, granted: bool = False
        ) -> ring_pb2.LogMessage:
            made = ring_pb2.LogMessage(
                origin=origin, sender=1, epoch=epoch, handover=handover, after_reqnr=last
            )
            if granted:  # the master's grant, as every message of its mastership carries
                made.grant.CopyFrom(genuine.grant)
            return made

        claims = [
            claim(1, ahead),
            claim(victim, ahead, handover=True),
            claim(1, ahead, granted=True),
            claim(1, genuine.epoch, granted=True),
        ]
        no_grant = f"it claims a mastership (epoch {ahead}) without the drone's grant"
        address = config.controller(victim).address
        cases = [
            (invented, True, f"request {last + 1} (/baton.v1.Mobility/GetPosition) has no valid"),
            (altered, True, "no valid signature of its creator, controller 0"),
            (copy(genuine), True, "no valid signature of its creator, controller 0"),
            (newer, False, "no valid signature of its creator, controller 0"),
            (claims[0], True, no_grant),
            (claims[1], True, no_grant),
            (
                claims[2],
                True,
                f"claims epoch {ahead} with the drone's grant of epoch {genuine.epoch}",
            ),
            (claims[3], True, "for controller 1; the drone granted it to controller 0"),
        ]
        sealed = [invented, *claims]
        async with aio_channel(address, station, Identity.controller(victim)) as channel:
            ring = ring_pb2_grpc.ControllerRingStub(channel)
            for count, (message, renumber, why) in enumerate(cases, 1):
                seal = stolen_key.seal if any(message is m for m in sealed) else None
                await send(address, station, victim, message, renumber, seal)
                status = await ring.GetStatus(ring_pb2.GetControllerStatusRequest())
                assert status.refused_messages == count, status
                assert "relayed by controller 1" in status.last_refused, status.last_refused
                assert why in status.last_refused, status.last_refused
            # A replayed old frame, numbered as it was: held already, and genuine.
            await send(address, station, victim, copy(genuine), renumber=False)
            status = await ring.GetStatus(ring_pb2.GetControllerStatusRequest())
            assert status.refused_messages == len(cases), status

        # An operator hands over to the victim, whose log the forgeries did not touch.
        await operator_hands_over(config.drone.address, testbed.tls, victim)
        snapshot = await testbed.run_mission(240)
    assert_mission_promises(snapshot, plan)
    assert snapshot.drone.master == victim
    # Every genuine message, handovers included, passed every controller's check.
    refused = {cid: c.refused_messages for cid, c in snapshot.controllers.items()}
    assert refused == {0: 0, 1: 0, victim: len(cases)}, refused

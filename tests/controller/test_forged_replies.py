"""Issue 33 across real processes under mutual TLS: a station holding a valid certificate
cannot invent or alter what the drone answered (baton.authenticity). Its forged log
messages are refused and named by the receiver, and the mission completes exactly once
(counted where the effects happen) with every replica's program seeing the same replies."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path

from helpers.missions import assert_mission_promises, three_on_fast_links
from waiting import eventually

from baton.authenticity import Signer, needs_drone_signature
from baton.controller.history import read_log
from baton.controller.ring import frames
from baton.digest import request_digest
from baton.rpc.channels import aio_channel
from baton.rpc.methods import path
from baton.rpc.tls import DRONE, Identity, Tls
from baton.testbed.local import LocalTestbed
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2, drone_pb2_grpc, ring_pb2, ring_pb2_grpc

GET_POSITION = path("Mobility.GetPosition")


def signed_message(log: Path) -> ring_pb2.LogMessage | None:
    """The newest message of a controller's log file with a reply the drone signed."""
    for message in reversed(read_log(log)):
        if any(needs_drone_signature(e) and e.drone_signature for e in message.entries):
            return message
    return None


async def send(
    address: str,
    station: Tls,
    receiver: int,
    message: ring_pb2.LogMessage,
    renumber: bool,
    seal: Callable[[ring_pb2.LogMessage], None] | None = None,
) -> None:
    """Sends ``message`` on a LogRing stream from ``station``'s certificate (numbered
    after what the receiver's hello says it holds if ``renumber``, then ``seal``ed) and
    waits for its acknowledgement: a refused message is acknowledged too (dropped, not
    asked again)."""
    async with aio_channel(address, station, Identity.controller(receiver)) as channel:
        call = ring_pb2_grpc.ControllerRingStub(channel).LogRing()
        hello = await call.read()
        assert isinstance(hello, ring_pb2.LogAck) and hello.hello
        if renumber:
            message.lognr = hello.lognr + 1
        if seal is not None:
            seal(message)
        for frame in frames(message, station.identity.number or 0):
            await call.write(frame)
        while True:
            ack = await call.read()
            assert isinstance(ack, ring_pb2.LogAck), ack
            if ack.lognr == message.lognr:
                break
        await call.done_writing()


async def test_forged_and_altered_replies_on_the_ring_are_refused_and_the_mission_flies_once(
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

        def copy(message: ring_pb2.LogMessage) -> ring_pb2.LogMessage:
            copied = ring_pb2.LogMessage()
            copied.CopyFrom(message)
            return copied

        # Invented replies in its own name, signed with its own key: GetPosition
        # answered with a place the drone never was.
        made_up = api.Position(latitude_deg=1.0, longitude_deg=2.0).SerializeToString()
        digest = request_digest(GET_POSITION, b"")
        last = max(e.reqnr for e in genuine.entries)
        invented = ring_pb2.LogMessage(
            origin=1,
            sender=1,
            epoch=genuine.epoch,
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
        address = config.controller(victim).address
        cases = [
            (invented, True, f"request {last + 1} (/baton.v1.Mobility/GetPosition) has no valid"),
            (altered, True, "no valid signature of its creator, controller 0"),
            (copy(genuine), True, "no valid signature of its creator, controller 0"),
            (newer, False, "no valid signature of its creator, controller 0"),
        ]
        async with aio_channel(address, station, Identity.controller(victim)) as channel:
            ring = ring_pb2_grpc.ControllerRingStub(channel)
            for count, (message, renumber, why) in enumerate(cases, 1):
                seal = stolen_key.seal if message is invented else None
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
        async with aio_channel(config.drone.address, testbed.tls, DRONE) as channel:
            moved = await drone_pb2_grpc.DroneStub(channel).Handover(
                drone_pb2.HandoverRequest(new_master=victim)
            )
            assert moved.new_master == victim
        snapshot = await testbed.run_mission(240)
    assert_mission_promises(snapshot, plan)
    assert snapshot.drone.master == victim
    # Every genuine message, handovers included, passed every controller's check.
    refused = {cid: c.refused_messages for cid, c in snapshot.controllers.items()}
    assert refused == {0: 0, 1: 0, victim: 4}, refused

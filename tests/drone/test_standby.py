"""The drone's standby streams over a real gRPC channel: who is reachable, and a
TakeOver that is owed to a taker whose stream was not there to carry it (issue 10)."""

from __future__ import annotations

import asyncio
import logging

import grpc
import pytest
from drone_harness import connect_as_master, start_drone
from waiting import eventually

from baton.config import controllers_only, merge
from baton.controller.drone_link import DroneStandby
from baton.digest import request_digest
from baton.drone.policy import LinkBounds
from baton.logs import get_logger
from baton.rpc.streams import next_message
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2


async def test_a_standby_stream_says_who_is_master_and_counts_as_reachable() -> None:
    drone, server = await start_drone()
    try:
        call = drone.stub.Standby(drone_pb2.StandbyRequest(controller_id=2))
        first = await next_message(call)
        assert first.held.master == 0 and first.held.epoch == 1
        status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert list(status.reachable) == [2]
        call.cancel()
        with pytest.raises(grpc.aio.AioRpcError) as unknown:
            await drone.stub.Standby(drone_pb2.StandbyRequest(controller_id=7)).read()
        assert unknown.value.code() is grpc.StatusCode.INVALID_ARGUMENT
    finally:
        await server.stop()


async def test_a_takeover_is_told_again_to_a_taker_that_was_not_listening() -> None:
    drone, server = await start_drone()
    try:
        reply = await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=1, takeover=True))
        assert reply.epoch == 2
        record = (await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())).handovers[0]
        assert (record.kind, record.trigger) == (
            drone_pb2.HANDOVER_KIND_TAKEOVER,
            drone_pb2.HANDOVER_TRIGGER_RPC,
        )
        # Controller 1 held no standby stream when the drone decided: it is told when
        # it opens one, for as long as it has not sent a request as master.
        call = drone.stub.Standby(drone_pb2.StandbyRequest(controller_id=1))
        assert (await next_message(call)).held.master == 1
        owed = (await next_message(call)).take_over
        assert (owed.old_master, owed.epoch) == (0, 2)
        call.cancel()
        other = drone.stub.Standby(drone_pb2.StandbyRequest(controller_id=2))
        assert (await next_message(other)).held.master == 1  # nothing owed to 2
        other.cancel()
    finally:
        await server.stop()


async def test_the_drone_measures_each_standby_links_round_trip_and_says_when_it_goes_silent(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Controller 1 answers the drone's pings (the controller's own DroneStandby);
    controller 2 holds a stream and never answers: its link goes silent, is logged
    unhealthy, and healthy again once it answers."""
    caplog.set_level(logging.INFO, logger="baton.drone")
    bounds = [
        ("max_rtt", "handover_policy.max_rtt", 0.5),
        ("rtt_stale", "handover_policy.rtt_stale", 1.5),
    ]
    drone, server = await start_drone(config=merge(controllers_only((0, 1, 2)), bounds))
    pings = asyncio.create_task(drone.service.watch_links())

    async def take_over(_: drone_pb2.TakeOver) -> None:
        raise AssertionError("no takeover here")

    answering = DroneStandby(1, drone.address, take_over, get_logger("controller"))
    answering.start()
    silent = drone.stub.Standby(drone_pb2.StandbyRequest(controller_id=2))
    try:
        assert (await next_message(silent)).HasField("held")

        async def links() -> dict[int, drone_pb2.ControllerLink]:
            status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
            return {link.controller_id: link for link in status.links}

        async def measured() -> drone_pb2.ControllerLink | None:
            one = (await links())[1]
            return one if one.answers >= 2 else None

        one = await eventually(measured, "two of controller 1's answers measured")
        assert one.standby and not one.connect and one.healthy and not one.problem
        assert 0 < one.rtt_s < 0.5 and 0 <= one.rtt_age_s < 1.5, one
        assert (one.max_rtt_s, one.rtt_stale_s) == (0.5, 1.5) and one.pings >= one.answers
        assert answering.pings_answered >= 2
        # Controller 2 was pinged on its stream and never answered.
        ping = (await next_message(silent)).ping
        assert ping.seq > 0

        async def silent_for_long() -> drone_pb2.ControllerLink | None:
            two = (await links())[2]
            return two if not two.healthy else None

        two = await eventually(silent_for_long, "controller 2's link to go silent")
        assert two.standby and two.rtt_s == -1 and two.rtt_age_s > 1.5
        assert two.problem.startswith("link silent (no answer to a ping of"), two.problem
        # Controller 0 holds no stream: down, nothing measured.
        zero = (await links())[0]
        assert not zero.standby and not zero.healthy and zero.rtt_s == zero.rtt_age_s == -1

        def logged() -> list[tuple[str, dict[str, object]]]:
            """Controller 2's link health lines, in order."""
            return [
                (r.getMessage(), r.fields)  # type: ignore[attr-defined]
                for r in caplog.records
                if r.getMessage().startswith("controller link") and r.fields.get("controller") == 2  # type: ignore[attr-defined]
            ]

        def went(message: str) -> dict[str, object] | None:
            lines = logged()
            return lines[-1][1] if lines and lines[-1][0] == message else None

        unhealthy = await eventually(
            lambda: went("controller link unhealthy"), "the silent link logged unhealthy"
        )
        assert str(unhealthy["problem"]).startswith("link silent")
        # It answers at last, each ping as it reads it: the ones queued while it did not
        # read are measured slow; once it keeps up, the link is healthy again.
        for _ in range(30):
            latest = (await next_message(silent)).ping.seq
            answer = drone_pb2.PingAnswer(controller_id=2, seq=latest)
            assert (await drone.stub.AnswerPing(answer)).measured
            if (await links())[2].healthy:
                break
        else:
            raise AssertionError(f"controller 2's link never healthy: {(await links())[2]}")
        # Neither a ping never sent to it nor one answered already is measured.
        for seq in (latest, 10**9):
            reply = await drone.stub.AnswerPing(drone_pb2.PingAnswer(controller_id=2, seq=seq))
            assert not reply.measured
        healthy = await eventually(
            lambda: went("controller link healthy"), "the link logged healthy again"
        )
        assert 0 <= float(healthy["rtt_ms"]) <= 500  # type: ignore[arg-type]
    finally:
        pings.cancel()
        silent.cancel()
        await answering.stop()
        await server.stop(0)


NOW = "/baton.v1.Clock/Now"
POSITION = "/baton.v1.Mobility/GetPosition"


def clock_reply(reqnr: int, method: str = NOW, seconds: float = 1.0) -> drone_pb2.RetainedReply:
    reply = api.NowReply(unix_time_s=1_700_000_000 + seconds).SerializeToString()
    return drone_pb2.RetainedReply(
        reqnr=reqnr, method=method, request_digest=request_digest(method, b""), reply=reply
    )


async def test_a_taker_connects_and_gets_the_retained_replies_with_their_epochs() -> None:
    """F12: a lost master's Clock.Now, sent along with its next Invoke, reaches the taker
    with the drone's own replies above the watermark, so it reads the same time; those
    the taker holds (its Connect says) too, each with the epoch that brought it, for the
    taker to compare with its framing (--policy nearest seed 132)."""
    drone, server = await start_drone()
    try:
        first = drone_pb2.InvokeRequest(controller_id=0, reqnr=1, method=POSITION, epoch=1)
        await drone.stub.Invoke(first)
        read = clock_reply(2, seconds=12.5)
        second = drone_pb2.InvokeRequest(
            controller_id=0, reqnr=3, method=POSITION, epoch=1, master_answers=[read]
        )
        position = await drone.stub.Invoke(second)
        standby = drone.stub.Standby(drone_pb2.StandbyRequest(controller_id=1))
        await standby.read()
        await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=1, takeover=True))
        take_over = (await next_message(standby)).take_over
        standby.cancel()
        assert (take_over.old_master, take_over.epoch, take_over.after_reqnr) == (0, 2, 3)
        connected, retained = await connect_as_master(drone.stub, 1, holds_reqnr=1)
        assert connected.epoch == 2
        assert [(r.reqnr, r.epoch) for r in retained] == [(1, 1), (2, 1), (3, 1)]
        read.epoch = 1
        assert retained[1] == read
        assert retained[2].reply == position.payload
        assert retained[2].request_digest == request_digest(POSITION, b"")
    finally:
        await server.stop()


async def test_every_connected_of_a_taker_says_takeover_and_the_watermark() -> None:
    """--lose-master seed 1092: a taker that sent a request, then rejoined with nothing,
    is told no TakeOver again; its Connected says the mastership is a takeover (no
    handover message will come) and the watermark it must hold before it goes ACTIVE
    (the retained replies start above it)."""
    drone, server = await start_drone()
    try:
        await drone.stub.Invoke(
            drone_pb2.InvokeRequest(controller_id=0, reqnr=1, method=POSITION, epoch=1)
        )
        await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=1, takeover=True))
        await drone.stub.Invoke(
            drone_pb2.InvokeRequest(
                controller_id=1, reqnr=2, method=POSITION, epoch=2, watermark_reqnr=1
            )
        )
        connected, retained = await connect_as_master(drone.stub, 1, holds_reqnr=0)
        assert (connected.epoch, connected.takeover, connected.watermark_reqnr) == (2, True, 1)
        assert [r.reqnr for r in retained] == [2]
        await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=2))
        connected, _ = await connect_as_master(drone.stub, 2)
        assert (connected.epoch, connected.takeover) == (3, False)
    finally:
        await server.stop()


async def test_a_masters_fresh_self_that_gave_its_mastership_up_is_granted_a_new_epoch() -> None:
    """--policy nearest seed 48: taker 1 (epoch 2) flushed a message on a framing it then
    gave up, and rejoined with nothing. Its fresh self's Connect says so: the drone grants
    it epoch 3 by a takeover of its earlier self. A second Connect that says the same (the
    first Connected not heard yet) is granted epoch 3 as it is."""
    drone, server = await start_drone()
    try:
        await drone.stub.Invoke(
            drone_pb2.InvokeRequest(controller_id=0, reqnr=1, method=POSITION, epoch=1)
        )
        await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=1, takeover=True))
        connected, _ = await connect_as_master(drone.stub, 1, given_up_epoch=2)
        assert (connected.epoch, connected.takeover, connected.takeover_epoch) == (3, True, 3)
        connected, _ = await connect_as_master(drone.stub, 1, given_up_epoch=2)
        assert connected.epoch == 3
        status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert (status.handovers[-1].old_master, status.handovers[-1].new_master) == (1, 1)
    finally:
        await server.stop()


async def test_two_switches_at_once_whose_first_old_master_is_lost_are_taken_over() -> None:
    """--lose-master seeds 2407, 2535, 5120, 6027 (F1's pattern), over real gRPC: the
    script hands 0 -> 1 after request 1, an operator's Handover 1 -> 2 comes right after,
    and 0 is gone before its log left. 1 never goes ACTIVE (it waits for 0's handover
    message), so it never hands over to 2, and the last switch's old master (1) holds
    its stream: before, nothing was taken over. Now 2 is granted again by takeover of 0,
    told on its standby stream, and 0's log is fenced."""
    drone, server = await start_drone("1 1")
    drone.service.takeover_after_s = 0.3
    watch = asyncio.create_task(drone.service.watch_master())
    standbys = [drone.stub.Standby(drone_pb2.StandbyRequest(controller_id=c)) for c in (1, 2)]
    try:
        for standby in standbys:
            await next_message(standby)
        await drone.stub.Invoke(
            drone_pb2.InvokeRequest(controller_id=0, reqnr=1, method=POSITION, epoch=1)
        )
        reply = await drone.stub.Handover(drone_pb2.HandoverRequest(new_master=2))
        assert (reply.old_master, reply.epoch) == (1, 3)
        # Before, nothing came: no takeover was ever due.
        take_over = (await asyncio.wait_for(next_message(standbys[1]), 5)).take_over
        assert (take_over.old_master, take_over.epoch) == (0, 4)
        record = (await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())).handovers[-1]
        assert (record.kind, record.old_master, record.new_master) == (
            drone_pb2.HANDOVER_KIND_TAKEOVER,
            0,
            2,
        )
        refusal = drone.stub.Connect(drone_pb2.ConnectRequest(controller_id=0, mastership_epoch=1))
        with pytest.raises(grpc.aio.AioRpcError) as fenced:
            await next_message(refusal)
        assert dict(fenced.value.trailing_metadata() or ())["baton-takeover"] == "1"
    finally:
        watch.cancel()
        for standby in standbys:
            standby.cancel()
        await server.stop()


@pytest.mark.parametrize(
    ("kept", "why"),
    [
        (clock_reply(2, method=POSITION), "neither a Clock method nor a call given up"),
        (clock_reply(1), "must increase, above the last request served (1)"),
        (clock_reply(3), "below this one (3)"),
    ],
)
async def test_a_clock_reply_sent_along_out_of_place_is_refused_and_nothing_runs(
    kept: drone_pb2.RetainedReply, why: str
) -> None:
    drone, server = await start_drone()
    try:
        await drone.stub.Invoke(
            drone_pb2.InvokeRequest(controller_id=0, reqnr=1, method=POSITION, epoch=1)
        )
        bad = drone_pb2.InvokeRequest(
            controller_id=0, reqnr=3, method=POSITION, epoch=1, master_answers=[kept]
        )
        with pytest.raises(grpc.aio.AioRpcError) as refused:
            await drone.stub.Invoke(bad)
        assert refused.value.code() is grpc.StatusCode.INVALID_ARGUMENT
        assert why in (refused.value.details() or "")
        status = await drone.stub.GetStatus(drone_pb2.GetDroneStatusRequest())
        assert (status.last_reqnr, status.executed, status.retained_replies) == (1, 1, 1)
    finally:
        await server.stop()


def test_one_late_answer_does_not_make_a_link_slow_two_in_a_row_do() -> None:
    """CI: on a loaded machine one answer came after max_rtt and the policy moved the
    master away and back. The round trip judged is the smaller of the last two answers."""
    from baton.drone.link_probe import LinkProbes
    from baton.logs import get_logger

    probes = LinkProbes((0,), LinkBounds(max_rtt_s=0.5, rtt_stale_s=5.0), get_logger("test"))

    def answer(sent: float, took: float) -> None:
        seq = probes.ping(0, sent).ping.seq
        assert probes.answered(0, seq, sent + took)

    answer(0.0, 0.01)
    answer(1.0, 0.9)  # one late answer
    assert probes.problem(probes.state(0, True, 0.0, 2.0)) == ""
    answer(2.0, 0.9)  # and another: slow now
    assert probes.problem(probes.state(0, True, 0.0, 3.0)).startswith("link too slow")
    answer(3.0, 0.01)  # one fast answer: the smaller of the two is fast again
    assert probes.problem(probes.state(0, True, 0.0, 3.1)) == ""

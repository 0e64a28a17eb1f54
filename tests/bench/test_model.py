"""The paper's model and the offline flush-point computation."""

from __future__ import annotations

import math

import pytest

from baton.bench.model import (
    MB,
    Call,
    LogPoint,
    entry_size_of,
    master_log_sizes,
    pick_in_stretch,
    preparation_limit,
    t_log,
    t_max,
)
from baton.bench.script import (
    GET_POSITION,
    RACE_SLACK,
    TAKE_PICTURE,
    entry_bytes,
    picture_reply_bytes,
    worst_case_script,
)
from baton.bench.timeline import TimelineSettings, place_handovers
from baton.controller.protocol import ControllerProtocol, entry_size
from baton.v1 import ring_pb2


def test_t_log_is_latency_plus_bits_over_bandwidth() -> None:
    assert t_log(0, 0.020, 25e6) == pytest.approx(0.020)
    # 1 MB = 2**20 bytes = 8,388,608 bits: 0.3355 s at 25 Mbit/s.
    assert t_log(MB, 0.020, 25e6) == pytest.approx(0.020 + 8 * 2**20 / 25e6)


def test_a_preparations_limit_is_its_bytes_over_one_ring_link_and_the_drone_link_both_ways() -> (
    None
):
    ring_l, ring_b, drone_l, drone_b = 0.020, 25e6, 0.002, 20e6
    # Nothing taken meanwhile: the log over the ring link, the ack back, the drone's
    # request and the master's word.
    alone = preparation_limit(MB, [], ring_l, ring_b, drone_l, drone_b)
    assert alone == pytest.approx(drone_l + 8 * MB / ring_b + 2 * ring_l + drone_l)
    # A picture requested at once crosses the drone link while a 2 MB log crosses the
    # ring link, then queues behind it (FIFO): it adds its ring transfer only.
    two = preparation_limit(2 * MB, [], ring_l, ring_b, drone_l, drone_b)
    early = preparation_limit(2 * MB, [(0.0, MB)], ring_l, ring_b, drone_l, drone_b)
    assert early == pytest.approx(two + 8 * MB / ring_b)
    # One requested late cannot leave the master before it exists there.
    late = preparation_limit(MB, [(1.0, MB)], ring_l, ring_b, drone_l, drone_b)
    picture_at_master = 1.0 + drone_l + 8 * MB / drone_b
    assert late == pytest.approx(picture_at_master + 8 * MB / ring_b + 2 * ring_l + drone_l)
    # Unlimited links: the latencies alone.
    assert preparation_limit(MB, [(0.0, MB)], ring_l, None, drone_l, None) == pytest.approx(
        2 * ring_l + 2 * drone_l
    )


def test_t_max_adds_one_handover_message_h_log_messages_and_t_conn() -> None:
    expected = 0.020 + 3 * (0.020 + 8 * (2 * MB + MB) / 25e6) + 0.05
    assert t_max(2 * MB, MB, 3, 0.05) == pytest.approx(expected)
    assert t_max(0, 0, 1, 0.0) == pytest.approx(0.040)


def test_synthetic_entries_have_the_real_entries_size() -> None:
    call = Call(7, TAKE_PICTURE, 1000, 12)
    real = ring_pb2.LogEntry(
        reqnr=7, method=TAKE_PICTURE, reply=bytes(1000), request_digest=bytes(32), request=bytes(12)
    )
    assert entry_size_of(call) == entry_size(real)


def test_log_flushes_when_it_reaches_the_limit_and_can_exceed_it_by_one_entry() -> None:
    calls = [Call(1, GET_POSITION, 40), Call(2, TAKE_PICTURE, 600), Call(3, TAKE_PICTURE, 600)]
    small, big = entry_size_of(calls[0]), entry_size_of(calls[1])
    points = master_log_sizes(calls, flush_limit=small + big + 1)
    assert points[0] == LogPoint(1, small, 0)
    assert points[1] == LogPoint(2, small + big, 0)
    # The third entry crosses the limit: the log flushed holds f + e, about.
    assert points[2] == LogPoint(3, 0, small + 2 * big)


def test_flush_limit_zero_flushes_every_entry() -> None:
    calls = [Call(k, GET_POSITION, 40) for k in range(1, 4)]
    assert all(p.size == 0 and p.flushed > 0 for p in master_log_sizes(calls, 0))


def test_handover_empties_the_log() -> None:
    calls = [Call(k, TAKE_PICTURE, 100) for k in range(1, 5)]
    points = master_log_sizes(calls, flush_limit=10**6, handovers=[2])
    assert [p.size for p in points] == [
        entry_size_of(calls[0]),
        2 * entry_size_of(calls[0]),
        entry_size_of(calls[0]),
        2 * entry_size_of(calls[0]),
    ]


def test_offline_log_matches_the_protocol_state_machine() -> None:
    calls = [Call(k, TAKE_PICTURE if k % 3 == 0 else GET_POSITION, 300 * k) for k in range(1, 30)]
    protocol = ControllerProtocol(0, [0, 1], flush_limit=2000)
    protocol.on_sync(0)
    protocol.on_granted(1)  # the drone's word: master in epoch 1, ACTIVE
    from baton.bench.model import log_entry

    for call, point in zip(calls, master_log_sizes(calls, 2000), strict=True):
        effects = protocol.on_reply(log_entry(call))
        assert protocol.log.size == point.size
        assert bool(effects) == bool(point.flushed)


def test_pick_in_stretch_picks_late_in_the_first_stretch_near_the_target() -> None:
    sizes = [0, 0, 900, 1000, 1010, 1020, 1030, 1040, 2000, 1000]
    points = [LogPoint(k + 1, s, 0) for k, s in enumerate(sizes)]
    # Stretch near 1000 is reqnr 3..8; two before its end is reqnr 6.
    assert pick_in_stretch(points, 1000, 100) == 6
    assert pick_in_stretch(points, 1000, 100, lambda p: p.reqnr <= 4) == 3
    assert pick_in_stretch(points, 5000, 100) is None


@pytest.mark.parametrize("flush_limit", [0, MB, 2 * MB, 3 * MB, 4 * MB])
def test_worst_case_script_flushes_about_f_plus_e_right_before_each_handover(
    flush_limit: int,
) -> None:
    script = worst_case_script(flush_limit, [1, 3, 5], controllers=6, settle_s=2.0)
    e = entry_bytes(Call(1000, TAKE_PICTURE, picture_reply_bytes(640, 546)))
    log = {p.reqnr: p for p in script.predicted_log()}
    for point in script.points:
        assert point.after_reqnr == point.picture_reqnr + 1
        flushed = log[point.picture_reqnr].flushed
        assert flushed == point.predicted_flush_bytes
        # Just under f before the picture, so the flush is between f and f + e.
        # (Entry sizes differ by a byte or two with the reqnr's varint.)
        assert flushed >= flush_limit
        assert flush_limit + e - 64 * 1024 < flushed < flush_limit + e + 16
        # Nothing flushed between the big flush and the handover (f > 0), and
        # room below f for the handover request's entry should the drone's
        # notice overtake its reply (footnote 2) and put it in the next log.
        if flush_limit:
            assert log[point.picture_reqnr - 1].size + RACE_SLACK < flush_limit
            assert log[point.after_reqnr].flushed == 0
    assert [p.hops for p in script.points] == [1, 3, 5]
    assert [(p.old_master, p.new_master) for p in script.points] == [(0, 1), (1, 4), (4, 3)]
    assert script.script.count(",s2") == 3
    assert len(script.calls) == script.points[-1].after_reqnr + 1


def test_timeline_places_handovers_on_polls_near_0_1_and_2_mb() -> None:
    # A synthetic grid run: ten polls between pictures of 0.99 MB, 2 MB flush limit.
    calls: list[Call] = []
    for _leg in range(12):
        for _ in range(10):
            calls.append(Call(len(calls) + 1, GET_POSITION, 38))
        calls.append(Call(len(calls) + 1, TAKE_PICTURE, 1_036_900))
    settings = TimelineSettings()
    handovers = place_handovers(calls, settings)
    sizes = {
        p.reqnr: p.size
        for p in master_log_sizes(calls, settings.flush_limit, [r for r, _ in handovers])
    }
    methods = {c.reqnr: c.method for c in calls}
    assert [m for _, m in handovers] == [1, 0, 1]
    for (reqnr, _), target in zip(handovers, settings.targets, strict=True):
        assert methods[reqnr] == GET_POSITION
        assert math.isclose(sizes[reqnr], target, abs_tol=settings.tolerance)


def test_timeline_looks_past_the_first_third_when_its_legs_were_long() -> None:
    # A loaded dry run (CI): the first legs took 20 polls, the rest 3, so the
    # first third of the core holds no log near 0 MB (the third picture
    # flushes after it); the handover goes to the first such poll after it.
    calls: list[Call] = []
    for leg in range(9):
        for _ in range(20 if leg < 3 else 3):
            calls.append(Call(len(calls) + 1, GET_POSITION, 38))
        calls.append(Call(len(calls) + 1, TAKE_PICTURE, 1_036_900))
    settings = TimelineSettings()
    handovers = place_handovers(calls, settings)
    sizes = {
        p.reqnr: p.size
        for p in master_log_sizes(calls, settings.flush_limit, [r for r, _ in handovers])
    }
    assert handovers[0][0] > 63  # after the third picture's flush
    for (reqnr, _), target in zip(handovers, settings.targets, strict=True):
        assert math.isclose(sizes[reqnr], target, abs_tol=settings.tolerance)


def test_audit_gaps_are_the_controllers_own_clock_calls() -> None:
    from baton.bench.runner import audit_calls
    from baton.testbed.local import Snapshot
    from baton.v1 import drone_pb2

    drone = drone_pb2.DroneStatus(
        audit=[
            drone_pb2.AuditEntry(reqnr=1, method=GET_POSITION, reply_bytes=38),
            drone_pb2.AuditEntry(reqnr=3, method=TAKE_PICTURE, reply_bytes=1000),
        ]
    )
    calls = audit_calls(Snapshot(drone), {3: 0, 2: 11}, {2: "/baton.v1.Clock/Now"})
    assert calls == [
        Call(1, GET_POSITION, 38, 0),
        Call(2, "/baton.v1.Clock/Now", 0, 11),
        Call(3, TAKE_PICTURE, 1000, 0),
    ]


def test_a_handovers_ready_time_is_the_new_masters_next_connection_in_its_status() -> None:
    from baton.bench.timeline import drone_connected_after
    from baton.testbed.local import Snapshot
    from baton.v1 import drone_pb2, ring_pb2

    status = ring_pb2.ControllerStatus(id=1, drone_connected_at=[10.0, 25.5, 40.0])
    run = Snapshot(drone_pb2.DroneStatus(), {1: status})
    assert drone_connected_after(run, 1, 20.0) == 25.5
    assert math.isnan(drone_connected_after(run, 1, 41.0))
    assert math.isnan(drone_connected_after(run, 2, 0.0))  # no such controller

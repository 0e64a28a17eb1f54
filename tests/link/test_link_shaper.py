"""The serial-line timing model, fed chunks at chosen times (no sockets)."""

from __future__ import annotations

import itertools

import pytest

from baton.config import LinkSpec
from baton.link.shaper import QUEUE_BYTES, SEGMENT_BYTES, SerialLine

PAPER = LinkSpec(latency=0.020, bandwidth=25e6)


@pytest.mark.parametrize("chunk", [1, 1000, 65536, 10**6])
def test_transfer_arrives_after_latency_plus_serialization_however_chunked(chunk: int) -> None:
    line = SerialLine(PAPER)
    size = 10**6
    arrival = 0.0
    for offset in range(0, size, chunk):
        arrival = line.transmit(5.0, min(chunk, size - offset))
    assert arrival == pytest.approx(5.0 + 0.020 + 8e6 / 25e6)


def test_latency_overlaps_transmission_instead_of_adding_per_chunk() -> None:
    line = SerialLine(PAPER)
    first = line.transmit(0.0, 1000)
    second = line.transmit(0.0, 1000)
    assert second - first == pytest.approx(8000 / 25e6)


def test_idle_line_starts_fresh_at_the_next_read() -> None:
    line = SerialLine(PAPER)
    line.transmit(0.0, 1000)
    assert line.transmit(10.0, 1000) == pytest.approx(10.0 + 0.020 + 8000 / 25e6)


def test_end_of_stream_arrives_behind_queued_data() -> None:
    line = SerialLine(PAPER)
    last = line.transmit(0.0, 10**6)
    assert line.close_time(0.001) == pytest.approx(last)
    assert line.close_time(100.0) == pytest.approx(100.020)


def test_unlimited_line_only_delays() -> None:
    line = SerialLine(LinkSpec(latency=0.005))
    assert line.segments(1.0, 10**6) == [(pytest.approx(1.005), 10**6)]
    assert LinkSpec().emulated is False


def test_segments_arrive_at_line_rate() -> None:
    line = SerialLine(PAPER)
    segments = line.segments(0.0, 3 * SEGMENT_BYTES + 1)
    assert [n for _, n in segments] == [SEGMENT_BYTES] * 3 + [1]
    gaps = [b[0] - a[0] for a, b in itertools.pairwise(segments)]
    assert gaps[:2] == [pytest.approx(SEGMENT_BYTES * 8 / 25e6)] * 2


def test_buffering_bound_is_bandwidth_delay_product_plus_queue() -> None:
    assert SerialLine(PAPER).max_in_flight == 62_500 + QUEUE_BYTES

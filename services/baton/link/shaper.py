"""The timing model of one direction of an emulated link, with no sockets in it.

A byte stream through a link behaves like a serial line of rate ``b``
followed by a propagation delay ``l``: a chunk departs when the line is free,
takes ``8 * len / b`` seconds to serialize and arrives ``l`` seconds after its
serialization ends. Latency therefore overlaps with transmission, and a
transfer of ``S`` bytes that starts at ``t0`` is fully delivered at
``t0 + l + 8 * S / b``, however it is cut into chunks.
"""

from __future__ import annotations

from baton.config import LinkSpec

# Read ahead of the line by this much beyond the bandwidth-delay product, so
# the line never idles while the proxy waits for the scheduler, yet memory
# stays bounded whatever the transfer size.
QUEUE_BYTES = 1 << 20
# An unlimited line has no bandwidth-delay product; this bounds its buffering.
UNLIMITED_IN_FLIGHT = 8 << 20
# Chunks are cut into segments of at most this size, each with its own arrival
# time, so a receiver sees data arrive at the line rate rather than in bursts.
SEGMENT_BYTES = 16 << 10


class SerialLine:
    """One direction of a link: when each chunk written to it arrives.

    ``transmit(now, size)`` is called as chunks are read from the source, with
    the current time; it returns the arrival time of the chunk's last byte.
    """

    def __init__(self, spec: LinkSpec) -> None:
        self.latency = spec.latency
        self.bandwidth = spec.bandwidth
        self._free_at = float("-inf")  # when the line finishes serializing its queue

    def retune(self, spec: LinkSpec) -> None:
        """From now on, ``spec``'s latency and bandwidth (a radio link fading with
        distance); what is queued keeps the times it was given."""
        self.latency = spec.latency
        self.bandwidth = spec.bandwidth

    @property
    def max_in_flight(self) -> int:
        """Bytes to hold between reading from the source and writing to the sink."""
        if self.bandwidth is None:
            return UNLIMITED_IN_FLIGHT
        return int(self.bandwidth * self.latency / 8) + QUEUE_BYTES

    def serialization(self, size: int) -> float:
        """Seconds the line takes to put ``size`` bytes on the wire."""
        return 0.0 if self.bandwidth is None else size * 8 / self.bandwidth

    def transmit(self, now: float, size: int) -> float:
        """Queues ``size`` bytes read at ``now``; returns when their last byte arrives."""
        start = max(now, self._free_at)
        self._free_at = start + self.serialization(size)
        return self._free_at + self.latency

    def segments(self, now: float, size: int) -> list[tuple[float, int]]:
        """Like ``transmit`` for a chunk cut into segments: ``(arrival, length)`` each."""
        if self.bandwidth is None:
            return [(self.transmit(now, size), size)]
        out = []
        for offset in range(0, size, SEGMENT_BYTES):
            length = min(SEGMENT_BYTES, size - offset)
            out.append((self.transmit(now, length), length))
        return out

    def close_time(self, now: float) -> float:
        """When an end of stream sent at ``now`` arrives: after everything queued before it."""
        return max(now, self._free_at) + self.latency

"""The drone's reply cache: duplicate request numbers are answered, not re-executed.

How long a reply is kept, and why that is enough: only the master may
invoke, and the master's request numbers strictly increase (a new request
must be above ``last_reqnr``; numbers may be skipped, because the controller
answers Clock calls itself and logs ``Clock.Now`` under a request number of
its own). So the only duplicates the drone can ever see are

- a retry of the last request by the master (its reply was lost), and
- the request the old master had in flight at a handover (footnote 2 of the
  paper): the drone executed request k and switched masters before the old
  master had the reply; the new master replays the log it received, reaches
  k without a logged reply, and re-sends k.

Both are within the last one or two request numbers served. The cache keeps
the last ``window`` replies (16 by default) — several times the worst case,
so that a new master that re-sends a short tail of requests still gets
cached answers — and evicts the oldest beyond that, which bounds memory to
``window`` replies (16 pictures of ~1 MB at the default resolution).

A third kind comes with takeovers (docs/design.md, "Takeover"): a master
lost with its unflushed log, whose successor re-sends every request above
what the ring holds. So the cache also *retains* every reply above the
*watermark*, the highest request number every reachable controller is known
to hold (the master says it on each Invoke): those are the replies only the
drone may still have. The watermark trails the master by its unflushed log
and the messages in flight, so this is bounded by the flush limit plus what
is in flight, not by the mission.

The retained replies also include the Clock calls the master answered itself
and sent along with its next Invoke (``InvokeRequest.master_answers``): a
drone call after a ``Clock.Now`` may depend on the time it read, so a taker
must read the same time. At a takeover the drone gives the taker all of them
on its Connect stream, in batches (``retained_batches``), and the taker
answers its program from each batch while the next crosses the link,
instead of re-sending each request.

A request that failed after it was accepted (unknown method, bad payload,
autopilot refusal, no acknowledgement in time) is served too: its status is
cached like a reply, so a duplicate sees the same failure and every
replica's mission program sees it (ring.proto logs failed calls). The
protocol's own rejections (not the master, wrong reqnr) and UNAVAILABLE
(the vehicle not connected: nothing reached it) leave the request number
unused, so the master sends the same request again once the vehicle is back.

A duplicate must be the same request: the cache keeps a digest of the method
and the serialized request, and a re-sent reqnr with another digest is a
mission program that diverged, which the drone refuses rather than answer
with a reply to a different question.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, replace

from baton.rpc.errors import StatusError, status_of
from baton.v1 import drone_pb2

DEFAULT_WINDOW = 16
# The retained replies go to a master in batches of about this many reply bytes:
# 64 KiB crosses a 20 Mbit/s link in 26 ms, so the program is answered from the
# first batch while the rest crosses (docs/design.md, "Takeover").
RETAINED_BATCH_BYTES = 64 * 1024
# The metadata of a cached failure that is the mission program's give-up, not
# the drone's outcome (a master sent it along: InvokeRequest.master_answers).
GIVEN_UP = ("baton-given-up", "true")


@dataclass(frozen=True)
class CachedReply:
    """One served request, as the cache remembers it."""

    reqnr: int
    method: str
    digest: bytes
    reply: bytes
    # The failure, if the request failed; None for a reply.
    error: StatusError | None = None
    # The epoch of the mastership that brought it (its request, or master_answers).
    epoch: int = 0

    def duplicate_error(self) -> StatusError | None:
        """The failure a duplicate of this request gets again, marked as a duplicate's
        (``baton-duplicate``); None for a reply."""
        error = self.error
        if error is None:
            return None
        return StatusError(
            error.code, error.message, metadata=(*error.metadata, ("baton-duplicate", "true"))
        )

    def to_proto(self) -> drone_pb2.RetainedReply:
        """As the drone gives it to a taker."""
        error = self.error
        return drone_pb2.RetainedReply(
            reqnr=self.reqnr,
            method=self.method,
            request_digest=self.digest,
            reply=self.reply,
            status_code=0 if error is None else error.code.value[0],
            status_message="" if error is None else error.message,
            given_up=error is not None and GIVEN_UP in error.metadata,
            epoch=self.epoch,
        )

    @classmethod
    def from_proto(cls, kept: drone_pb2.RetainedReply) -> CachedReply:
        """A reply a master sent along (a Clock call it answered itself)."""
        error = None
        if kept.status_code:
            given_up = (GIVEN_UP,) if kept.given_up else ()
            error = StatusError(status_of(kept.status_code), kept.status_message, given_up)
        return cls(kept.reqnr, kept.method, kept.request_digest, kept.reply, error, kept.epoch)


class ReplyCache:
    """The last ``window`` replies by request number, and every one above the watermark."""

    def __init__(self, window: int = DEFAULT_WINDOW) -> None:
        if window < 1:
            raise ValueError(f"the reply cache window must be >= 1, got {window}")
        self.window = window
        self.watermark = 0
        self._entries: OrderedDict[int, CachedReply] = OrderedDict()

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, reqnr: object) -> bool:
        return reqnr in self._entries

    def get(self, reqnr: int) -> CachedReply | None:
        """The cached reply of ``reqnr``, or None if it was never served or was evicted."""
        return self._entries.get(reqnr)

    def store(
        self,
        reqnr: int,
        method: str,
        digest: bytes,
        reply: bytes,
        error: StatusError | None = None,
        epoch: int = 0,
    ) -> None:
        """Remembers a served request (reply or failure), brought by the master of
        ``epoch``; evicts the oldest beyond the window."""
        self._entries[reqnr] = CachedReply(reqnr, method, digest, reply, error, epoch)
        self._entries.move_to_end(reqnr)
        self._evict()

    def restamp(self, first: int, below: int, epoch: int) -> list[CachedReply]:
        """The retained replies from ``first`` up to ``below`` (excluded) brought before
        ``epoch``, now counted as brought in it (in place: eviction's order is unchanged);
        returns them."""
        changed = [
            replace(entry, epoch=epoch)
            for entry in self.retained_replies(above=first - 1)
            if entry.reqnr < below and entry.epoch < epoch
        ]
        for entry in changed:
            self._entries[entry.reqnr] = entry
        return changed

    def raise_watermark(self, reqnr: int) -> None:
        """Every controller holds the replies up to ``reqnr``: they need not be retained."""
        if reqnr > self.watermark:
            self.watermark = reqnr
            self._evict()

    def _evict(self) -> None:
        while len(self._entries) > self.window:
            oldest = next(iter(self._entries))
            if oldest > self.watermark:
                return  # retained: only the drone may have it
            del self._entries[oldest]

    def retained_replies(self, above: int = 0) -> list[CachedReply]:
        """The replies above the watermark (and ``above``), oldest first: what a master
        that holds up to ``above`` is given on Connect."""
        floor = max(self.watermark, above)
        return [entry for entry in self._entries.values() if entry.reqnr > floor]

    @property
    def retained(self) -> tuple[int, int]:
        """Replies above the watermark, kept whatever the window: (count, bytes)."""
        kept = self.retained_replies()
        return len(kept), sum(len(entry.reply) for entry in kept)

    @property
    def reqnrs(self) -> list[int]:
        """The cached request numbers, oldest first."""
        return list(self._entries)


def retained_batches(
    replies: list[CachedReply], max_bytes: int = RETAINED_BATCH_BYTES
) -> list[list[CachedReply]]:
    """``replies`` in order, cut into batches of at most ``max_bytes`` of replies each
    (a larger reply goes alone): the RetainedBatch events after a Connected."""
    batches: list[list[CachedReply]] = []
    size = 0
    for reply in replies:
        if not batches or size + len(reply.reply) > max_bytes:
            batches.append([])
            size = 0
        batches[-1].append(reply)
        size += len(reply.reply)
    return batches

"""The drone's decisions as a pure object: who may invoke, which requests, what was served.

No sockets, no tasks, no clock of its own (times are passed in): the drone
service (``service.py``) asks it whether to execute a request, answer it from
the reply cache or refuse it, executes what it is told to, and books the
outcome here; the deterministic simulation (``baton.sim``) drives the same
object. Everything the drone must not forget lives here, so the durable
store (``store.py``) saves and restores exactly this.

The rules (docs/design.md, "Epochs" and "Exactly once..."):

- Only the master may invoke, and only in the *epoch* of its mastership:
  epoch 1 is the initial master's, and every switch grants the new master
  the next one. A request from an earlier mastership of the same controller
  (still on the wire when the drone handed the role away and back) is
  *stale*: refused, never executed, and never mistaken for a program that
  diverged.
- Request numbers increase (skipping only the controller's own Clock calls,
  by less than ``MAX_REQNR_GAP``); a re-sent number is answered from the
  reply cache if it is the same request, refused if it is another.
- Every outcome of an accepted request is booked: a reply, or a failure
  after the request reached the vehicle; UNAVAILABLE (nothing reached the
  vehicle) is not booked and leaves the number unused.
- The handover script's line due after a served request switches masters,
  or, marked ``prepared``, starts a prepared handover: the master catches
  the target up while the mission goes on, and the master moves after the
  first request served once the target lacks at most
  ``PREPARED_BOUND_BYTES`` (with that request's reply), or at the timeout
  as a forced handover (docs/design.md, "Prepared handover").
- A master lost (no stream and no request for the takeover time) is taken
  over by the first reachable controller after it in ring order, in a new
  epoch, without its log (``takeover_due``); the drone answers the new
  master's re-sent requests from the replies it retains above the
  watermark (dedupe.py).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace

import grpc

from baton.config import PREPARE_TIMEOUT_S
from baton.drone.dedupe import DEFAULT_WINDOW, GIVEN_UP, CachedReply, ReplyCache
from baton.rpc.errors import StatusError
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2

# How far a new request number may be above the last one served. Numbers skip
# the Clock calls a controller answers itself, never this many; a larger jump
# is a bug or an attack, and accepting it (2**64 - 1, say) would make every
# later request look old, so the drone would refuse the mission for good.
MAX_REQNR_GAP = 1_000_000
# Audit entries kept in memory, the newest (the durable store keeps them all).
AUDIT_IN_MEMORY = 1_000
# A prepared handover moves the master once its target lacks at most this much
# of the log, the reply served last included: 5 ms on a 25 Mbit/s link.
PREPARED_BOUND_BYTES = 16 << 10
# ... and has acknowledged every message it was sent more than this long ago, and
# at least one since the preparation began: a target that lacks little but hears
# nothing (its link froze) has not caught up.
PREPARED_BEHIND_S = 0.25


@dataclass(frozen=True)
class ScriptedHandover:
    """One line of the handover script: hand over to ``new_master`` after ``after_reqnr``."""

    after_reqnr: int
    new_master: int
    line: int
    prepared: bool = False  # a prepared handover (the line's third word)


@dataclass(frozen=True)
class Served:
    """What booking a request's outcome led to."""

    audit: drone_pb2.AuditEntry
    cached: CachedReply
    # The handover the script fired after it, if any.
    handover: drone_pb2.HandoverRecord | None = None
    # A script line that named the master itself (skipped, kept for the log).
    skipped: ScriptedHandover | None = None
    # A prepared handover the script began after it (owed to the master).
    prepare: drone_pb2.PrepareHandover | None = None


@dataclass
class Preparation:
    """A prepared handover under way (``Sequencer.prepare``)."""

    target: int
    trigger: drone_pb2.HandoverTrigger.ValueType
    started_at: float
    deadline: float
    notice: drone_pb2.PrepareHandover
    reason: str = ""  # the handover policy's why and where, for the record
    position: api.Position | None = None
    # The master's last word on what the target lacks (None: not heard yet), and
    # how long its oldest unacknowledged message has waited.
    lacks_bytes: int | None = None
    behind_s: float = 0.0
    acked: int = 0
    # The script line that began it (its reqnr; 0: not the script's).
    line: int = 0


@dataclass(frozen=True)
class TakeoverDue:
    """``takeover_due``'s verdict: make ``new_master`` master without ``lost``'s log."""

    new_master: int
    lost: int  # the controller whose log is given up: the master, or a handover's old master
    lost_at: float  # when the drone last saw it


class Sequencer:
    """The drone's master, epoch, request order, reply cache, audit and handover script."""

    def __init__(
        self,
        controllers: Iterable[int],
        initial_master: int,
        script: Mapping[int, ScriptedHandover] | None = None,
        cache_window: int = DEFAULT_WINDOW,
        prepare_timeout_s: float = PREPARE_TIMEOUT_S,
    ) -> None:
        # In the order given: the ring's, which a takeover follows.
        self.ring = list(dict.fromkeys(controllers))
        self.controllers = sorted(self.ring)
        if not self.controllers:
            raise ValueError("the drone needs at least one controller id")
        if initial_master not in self.controllers:
            raise ValueError(
                f"initial master {initial_master} is not a controller id; use one of "
                f"{self.controllers}"
            )
        self.master = initial_master
        self.handovers: list[drone_pb2.HandoverRecord] = []
        self.cache = ReplyCache(cache_window)
        self.last_reqnr = 0
        self.executed = 0
        self.duplicates = 0
        self.rejected = 0
        # The newest served requests; older ones are in the store, if any.
        self.audit: deque[drone_pb2.AuditEntry] = deque(maxlen=AUDIT_IN_MEMORY)
        self.script = dict(script or {})  # pending scripted handovers, by reqnr
        self.fired_script: list[int] = []
        # Notices owed to old masters, by controller id.
        self.pending: dict[int, drone_pb2.HandoverNotice] = {}
        # The epoch in which the master last opened a Connect stream (0: not
        # since this drone started): ``handover_must_take_over``.
        self.connected_epoch = 0
        # The prepared handover under way, if any; any switch ends it.
        self.preparing: Preparation | None = None
        self.prepare_timeout_s = prepare_timeout_s
        # The last epoch whose master spoke as ACTIVE between requests (its word on a
        # preparation: it prepares only when ACTIVE): ``takeover_due``. 0 after a
        # restart, as the store does not keep it; a request says as much.
        self.active_epoch = 0
        # Signs a grant with the drone's key (``sign_grants_with``); None: insecure,
        # grants go unsigned. The grants made, by epoch.
        self._seal_grant: Callable[[drone_pb2.Grant], None] | None = None
        self._grants: dict[int, drone_pb2.Grant] = {}

    @property
    def epoch(self) -> int:
        """The current master's epoch: 1, and one more at every switch."""
        return len(self.handovers) + 1

    def sign_grants_with(self, seal: Callable[[drone_pb2.Grant], None]) -> None:
        """Grants are signed by ``seal`` from now on (``authenticity.Signer.seal_grant``)."""
        self._seal_grant = seal
        self._grants.clear()

    def signed_grant(self, epoch: int) -> drone_pb2.Grant | None:
        """The drone's grant of ``epoch``, signed; None on an insecure drone (nobody checks
        grants there, and its events and refusals say none)."""
        return self.grant_of(epoch) if self._seal_grant is not None else None

    def grant_of(self, epoch: int) -> drone_pb2.Grant:
        """The drone's grant of ``epoch`` (one it made), signed if it has a key: who it
        made master and how. The handover records say it for every epoch, also after a
        restart, and the key is the drone's certificate's, so a grant signed again
        verifies like the first."""
        grant = self._grants.get(epoch)
        if grant is None:
            if epoch == 1:
                first = self.handovers[0].old_master if self.handovers else self.master
                grant = drone_pb2.Grant(
                    master=first, epoch=1, kind=drone_pb2.GRANT_KIND_FIRST, old_master=first
                )
            else:
                record = self.handovers[epoch - 2]
                takeover = record.kind == drone_pb2.HANDOVER_KIND_TAKEOVER
                grant = drone_pb2.Grant(
                    master=record.new_master,
                    old_master=record.old_master,
                    epoch=epoch,
                    kind=drone_pb2.GRANT_KIND_TAKEOVER
                    if takeover
                    else drone_pb2.GRANT_KIND_HANDOVER,
                )
            if self._seal_grant is not None:
                self._seal_grant(grant)
            self._grants[epoch] = grant
        copied = drone_pb2.Grant()
        copied.CopyFrom(grant)
        return copied

    # -- refusals -------------------------------------------------------------------

    def check_known(self, controller_id: int) -> None:
        """INVALID_ARGUMENT unless ``controller_id`` is a known controller."""
        if controller_id not in self.controllers:
            raise StatusError(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"unknown controller id {controller_id}; known ids: {self.controllers}",
            )

    def where_we_are(
        self, controller_id: int | None = None, mastership_epoch: int = 0
    ) -> tuple[tuple[str, str], ...]:
        """The trailing metadata of a refusal: master, epoch, last request served.

        ``baton-takeover`` tells a controller that the mastership whose log
        it holds (``mastership_epoch``: the epoch its request or Connect
        carries) was taken over: its log is not wanted; it rejoins as a
        replica with nothing (``taken_over_since``).
        ``baton-takeover-watermark`` goes with it: the drone's watermark at that
        takeover (``HandoverRecord.watermark_reqnr``), below which no later master
        frames a request anew, so the controller keeps its log up to it
        (``ControllerProtocol.kept_when_fenced``).
        ``baton-takeover-holds`` goes with it once the taker has connected: the log
        message its own follow (``taker_connected``), as ``lognr/epoch``; the
        controller keeps its messages up to it if it holds that one.
        ``baton-takeover-epoch`` is the epoch the newest takeover granted
        (absent: none yet). A controller still ACTIVE in an older epoch holds a log
        that never left it, and that takeover framed the same replies from
        the ones the drone retains, whoever the master it replaced was (the
        new master of a cooperative handover that waited for that very log,
        say): the controller's log is not wanted either
        (``ControllerProtocol.log_given_up``). Only the controller knows
        whether it is ACTIVE, so the drone says the epoch and it decides.
        """
        where: tuple[tuple[str, str], ...] = (
            ("baton-master", str(self.master)),
            ("baton-epoch", str(self.epoch)),
            ("baton-after-reqnr", str(self.last_reqnr)),
        )
        grant = self.signed_grant(self.epoch)
        if grant is not None:
            # The master's grant: a refused old master hands its log over with it.
            where += (("baton-grant", grant.SerializeToString().hex()),)
        if self.takeover_epoch:
            where += (("baton-takeover-epoch", str(self.takeover_epoch)),)
        taken = None
        if controller_id is not None:
            taken = self.taken_over_since(controller_id, mastership_epoch)
        if taken is not None:
            where += (("baton-takeover", "1"),)
            if taken.watermark_reqnr:
                where += (("baton-takeover-watermark", str(taken.watermark_reqnr)),)
            if taken.taker_lognr_epoch:
                holds = f"{taken.taker_lognr}/{taken.taker_lognr_epoch}"
                where += (("baton-takeover-holds", holds),)
        return where

    def taker_connected(self, request: drone_pb2.ConnectRequest) -> None:
        """The master's Connect, granted: a taker's first in its epoch records the log
        message it holds (``HandoverRecord.taker_lognr``), on which its own follow."""
        last = self.handovers[-1] if self.handovers else None
        if (
            last is not None
            and last.kind == drone_pb2.HANDOVER_KIND_TAKEOVER
            and last.new_master == request.controller_id == self.master
            and last.epoch == self.epoch
            and not last.taker_lognr_epoch
        ):
            last.taker_lognr = request.holds_lognr
            last.taker_lognr_epoch = request.holds_lognr_epoch

    @property
    def takeover_epoch(self) -> int:
        """The epoch the newest takeover granted (0: no takeover yet)."""
        for record in reversed(self.handovers):
            if record.kind == drone_pb2.HANDOVER_KIND_TAKEOVER:
                return record.epoch
        return 0

    def taken_over_since(
        self, controller_id: int, mastership_epoch: int
    ) -> drone_pb2.HandoverRecord | None:
        """The takeover that gave up ``controller_id``'s log after its mastership in
        ``mastership_epoch``, if any (0: it holds the log of no mastership).

        The taker framed the replies that log holds in log messages of its
        own, so a controller still holding it must not act on it, as master
        or as a replica, even if the role has come back to it since (a
        takeover, then a handover back): it rejoins as a replica with
        nothing first (fenced; docs/design.md, "Takeover"). Decided from the
        handover records, which the store keeps, and the controller's word,
        so neither a drone restart (the notices owed are not kept) nor a
        controller restart (its history file keeps the epoch) loses it.
        """
        if mastership_epoch <= 0:
            return None
        for record in self.handovers[max(0, mastership_epoch - 1) :]:
            # handovers[i] granted epoch i + 2: these ended ``mastership_epoch`` or later.
            if (
                record.kind == drone_pb2.HANDOVER_KIND_TAKEOVER
                and record.old_master == controller_id
            ):
                return record
        return None

    def not_master_error(
        self, controller_id: int, what: str, mastership_epoch: int = 0
    ) -> StatusError:
        """The FAILED_PRECONDITION a non-master gets, naming the master."""
        return StatusError(
            grpc.StatusCode.FAILED_PRECONDITION,
            f"{what} refused: controller {controller_id} is not the master; the master is "
            f"controller {self.master} (epoch {self.epoch}, last reqnr served {self.last_reqnr})",
            metadata=self.where_we_are(controller_id, mastership_epoch),
        )

    # -- a request arrives ---------------------------------------------------------

    def admit(
        self,
        controller_id: int,
        epoch: int,
        reqnr: int,
        method: str,
        digest: bytes,
        watermark: int = 0,
        clock: Sequence[CachedReply] = (),
    ) -> CachedReply | None:
        """Decides a request: None to execute it now, a CachedReply to answer it again.

        Raises StatusError when it is refused; nothing is executed then and
        the request number stays unused. The master's ``watermark`` (every
        reachable controller holds the replies up to it) lets the cache stop
        retaining them. ``clock`` are the calls the master answered
        since its last request, numbered between the last request served and
        this one (INVALID_ARGUMENT otherwise); ``served`` keeps them.
        """
        what = f"Invoke reqnr {reqnr} epoch {epoch}"
        if controller_id != self.master:
            raise self.not_master_error(controller_id, what, epoch)
        if epoch == 0 or epoch > self.epoch:
            raise StatusError(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"{what}: epoch {epoch} was never granted (the current one is {self.epoch}); "
                "send the epoch of the Connected event of your Connect stream",
            )
        if epoch < self.epoch:
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"{what} is stale: controller {controller_id} is master in epoch "
                f"{self.epoch}; a request of an earlier epoch (sent before a switch and "
                "still on the wire) is never executed",
                metadata=self.where_we_are(),
            )
        self.cache.raise_watermark(min(watermark, self.last_reqnr))
        cached = self.cache.get(reqnr)
        if cached is not None:
            if cached.digest != digest:
                raise StatusError(
                    grpc.StatusCode.FAILED_PRECONDITION,
                    f"reqnr {reqnr} was served as {cached.method} (request digest "
                    f"{cached.digest.hex()[:16]}) but is re-sent as {method} (digest "
                    f"{digest.hex()[:16]}): the mission program diverged",
                    metadata=self.where_we_are(),
                )
            self.duplicates += 1
            return cached
        if reqnr == 0:
            # reqnr 0 can never be right, so it is INVALID_ARGUMENT; a number
            # that is wrong for the drone's state is FAILED_PRECONDITION, fixed
            # by resynchronising from the metadata.
            raise StatusError(
                grpc.StatusCode.INVALID_ARGUMENT, "reqnr 0 is not a request number; they start at 1"
            )
        if reqnr <= self.last_reqnr:
            oldest = self.cache.reqnrs[0] if len(self.cache) else None
            cached_range = (
                f"; replies cached for reqnr {oldest}..{self.last_reqnr}" if oldest else ""
            )
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"expected a reqnr above {self.last_reqnr} (or a cached duplicate), "
                f"got {reqnr}{cached_range}",
                metadata=self.where_we_are(),
            )
        if reqnr > self.last_reqnr + MAX_REQNR_GAP:
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"reqnr {reqnr} is more than {MAX_REQNR_GAP} above the last one served "
                f"({self.last_reqnr}): request numbers skip only the controller's own Clock "
                "calls, and a number this far ahead would make every later request look "
                "old; refused, nothing executed",
                metadata=self.where_we_are(),
            )
        after = self.last_reqnr
        for kept in clock:
            if kept.reqnr <= self.last_reqnr and after == self.last_reqnr and self._known(kept):
                continue  # sent again: a give-up of a request served (its outcome is
                # what the program saw: served again so), or what we keep already
            if not after < kept.reqnr < reqnr:
                raise StatusError(
                    grpc.StatusCode.INVALID_ARGUMENT,
                    f"{what}: a call the master answered (master_answers) is numbered "
                    f"{kept.reqnr}; they must increase, above the last request served "
                    f"({self.last_reqnr}) and below this one ({reqnr}), or be the last one "
                    "served, given up by the program; refused, nothing executed",
                )
            after = kept.reqnr
        return None

    def _known(self, kept: CachedReply) -> bool:
        """A call at or below the last request served that the master sends along again:
        a give-up of a request we served, as the master's program saw it, or a call it
        answered itself that we keep already (the same request, by digest), or let go at
        the watermark (every controller holds it).

        A master keeps sending what it answered since its last drone call whose
        outcome it knows, and a drone call the program gave up on leaves it not
        knowing: so what it answered comes along again with the next request,
        which must not be refused for it.
        """
        ours = self.cache.get(kept.reqnr)
        if ours is None:
            return kept.reqnr <= self.cache.watermark
        if ours.digest != kept.digest:
            return False
        return _given_up(kept) or (ours.reply == kept.reply and ours.error is kept.error is None)

    def keep(self, answers: Sequence[CachedReply]) -> tuple[CachedReply, ...]:
        """Keeps the calls the master answered itself that ``admit`` accepted with a
        request about to be executed (before it is: a drone that dies executing it
        must still give them to a taker); returns those not held already."""
        fresh = tuple(replace(kept, epoch=self.epoch) for kept in answers if self._fresh(kept))
        for kept in fresh:
            self.cache.store(
                kept.reqnr, kept.method, kept.digest, kept.reply, kept.error, kept.epoch
            )
        return fresh

    def adopt(
        self, controller_id: int, epoch: int, adopted_from: int, reqnr: int
    ) -> list[CachedReply]:
        """A taker's request says it answered its program from the retained replies from
        ``adopted_from`` on (``InvokeRequest.adopted_from_reqnr``): those up to ``reqnr``
        count from now on as brought in its epoch; returns them, for the store.

        It held none of them, and frames them in its own messages. Kept with the
        epoch of the master that first brought them, they would look older than
        a framing they had replaced (a lost master's give-up of a request the
        drone executed, handed on before the takeover), and a later taker
        holding that framing would take it for the ring's and build on it,
        showing programs different replies. The taker says what it adopted
        itself: its Connect's ``holds_reqnr`` may be stale by the time the
        replies come, and counted from it a taker could refuse its own framing
        for ever.
        """
        if not adopted_from or not self.granted_by_takeover:
            return []
        if controller_id != self.master or epoch != self.epoch:
            return []
        return self.cache.restamp(adopted_from, reqnr, epoch)

    def note_framing(self, controller_id: int, epoch: int, framed_after: tuple[int, int]) -> None:
        """A taker's request says the log message, (lognr, epoch), its own messages follow
        (``InvokeRequest.framed_after_lognr``, ``framed_after_epoch``): kept on its
        takeover's record, the first time (``replaced_framing`` reads it)."""
        if not self.granted_by_takeover:
            return
        record = self.handovers[-1]
        if controller_id != self.master or epoch != self.epoch or record.epoch != epoch:
            return
        if not record.HasField("framed_after_lognr"):
            record.framed_after_lognr, record.framed_after_epoch = framed_after

    def replaced_framing(self, holds_lognr: int, holds_epoch: int) -> tuple[int, int] | None:
        """Whether log message ``holds_lognr`` of ``holds_epoch`` (a taker's top, its
        Connect's) is of a framing a takeover replaced: the log number that framing is
        replaced from and the epoch that replaced it, or None.

        A taker's messages follow what it held when it went ACTIVE
        (``framed_after_lognr``), so from the next number on the ring's log is of
        its epoch or newer, until a later taker frames from a lower number (each
        taker holds a prefix of the ring's log and builds on it). The message a
        later taker built on is the ring's: an earlier start at or below its
        number whose epoch is newer than that message's did not last (its
        taker's messages never left it), and no longer counts. Along a lineage
        epochs never go down, so a top message numbered at or above such a start
        and older than its epoch is another framing of those numbers: the same
        replies numbered otherwise by a master the takeover replaced. A taker
        that built on it would lead the ring into a lineage whose messages the
        others cannot follow, and the others would rejoin on the ring's newer
        numbering, dropping what the drone let go of on its word.
        """
        starts: list[tuple[int, int]] = []  # (first log number, epoch), ascending numbers
        for record in self.handovers:
            if record.kind != drone_pb2.HANDOVER_KIND_TAKEOVER:
                continue
            if not record.HasField("framed_after_lognr"):
                continue
            base, base_epoch = record.framed_after_lognr, record.framed_after_epoch
            while starts and (starts[-1][0] > base or starts[-1][1] > base_epoch):
                starts.pop()
            starts.append((base + 1, record.epoch))
        for first, epoch in reversed(starts):
            if first <= holds_lognr:
                return (first, epoch) if 0 < holds_epoch < epoch else None
        return None

    def _fresh(self, kept: CachedReply) -> bool:
        """Whether ``served`` keeps a call the master answered (``admit`` accepted it):
        above the last request served, or a give-up of one served that we still hold as
        the drone's outcome (the program saw the give-up)."""
        if kept.reqnr > self.last_reqnr:
            return True
        ours = self.cache.get(kept.reqnr)
        return ours is not None and _given_up(kept) and not _given_up(ours)

    def note_request(
        self, controller_id: int, received_at: float
    ) -> drone_pb2.HandoverRecord | None:
        """Completes the last handover's record with the new master's first request."""
        if not self.handovers:
            return None
        record = self.handovers[-1]
        if record.new_master != controller_id or record.first_request_at != 0:
            return None
        record.first_request_at = received_at
        record.delay_s = received_at - record.decided_at
        return record

    def served(
        self,
        controller_id: int,
        reqnr: int,
        method: str,
        digest: bytes,
        reply: bytes,
        received_at: float,
        now: float,
        error: StatusError | None = None,
    ) -> Served:
        """Books an accepted request's outcome, then fires the script's line due after it.

        ``received_at`` is when the request arrived (the audit's), ``now``
        when it was done (a scripted handover is decided then).
        """
        self.cache.store(reqnr, method, digest, reply, error, self.epoch)
        self.last_reqnr = reqnr
        # ``executed`` counts replies; a failed request counts as rejected
        # (by the service, which refuses it) but is audited, so the audit's
        # reqnrs have no gaps.
        if error is None:
            self.executed += 1
        entry = drone_pb2.AuditEntry(
            reqnr=reqnr,
            method=method,
            controller_id=controller_id,
            received_at=received_at,
            reply_bytes=len(reply),
        )
        self.audit.append(entry)
        cached = self.cache.get(reqnr)
        assert cached is not None
        if self.preparing is not None and controller_id == self.master:
            handover = self._finish_preparation(len(reply), now)
            if handover is not None:
                return Served(entry, cached, handover=handover)
        # A scripted handover fires after the first request served at or past
        # its reqnr: request numbers the controllers answer themselves (Clock)
        # never reach the drone. The script's lines go in order: one due while
        # the preparation an earlier line began is under way waits for its
        # handover (replacing it dropped that line's handover).
        due = [n for n in self.script if n <= reqnr]
        if not due or (self.preparing is not None and self.preparing.line):
            return Served(entry, cached)
        line = min(due)
        scripted = self.script.pop(line)
        if scripted.prepared and scripted.new_master != self.master:
            prepare = self.prepare(scripted.new_master, drone_pb2.HANDOVER_TRIGGER_SCRIPT, now)
            # Fired once the preparation ends (``_preparation_ended``): the preparation
            # is not in the store, so a restart before then begins it again.
            assert self.preparing is not None
            self.preparing.line = line
            return Served(entry, cached, prepare=prepare)
        self.fired_script.append(line)
        if scripted.new_master == self.master:
            return Served(entry, cached, skipped=scripted)
        handover = self.switch(scripted.new_master, drone_pb2.HANDOVER_TRIGGER_SCRIPT, now)
        return Served(entry, cached, handover=handover)

    # -- a restart ------------------------------------------------------------------

    def resume(
        self,
        master: int,
        handovers: Iterable[drone_pb2.HandoverRecord],
        counts: tuple[int, int, int, int],
        replies: Iterable[CachedReply],
        audit: Iterable[drone_pb2.AuditEntry],
        fired_script: Iterable[int],
        watermark: int = 0,
    ) -> None:
        """Takes back what the durable store kept: master and handovers (so the epoch),
        ``counts`` (last reqnr, executed, duplicates, rejected), the reply cache, the
        newest audit entries, the script lines already fired, and the watermark.

        The watermark too: the cache let the replies at or below it go, and a
        taker is told it (``Connected.watermark_reqnr``) to know what it must
        hold before it goes ACTIVE. Read as 0 after a restart, it would let a
        taker restarted with nothing go ACTIVE at once and wait for ever for the
        retained reply of request 1, long gone.
        """
        self.master = master
        self.handovers[:] = handovers
        self._grants.clear()
        self.last_reqnr, self.executed, self.duplicates, self.rejected = counts
        for reply in replies:
            self.cache.store(
                reply.reqnr, reply.method, reply.digest, reply.reply, reply.error, reply.epoch
            )
        self.cache.raise_watermark(watermark)
        self.audit.extend(audit)
        self.fired_script[:] = fired_script
        for reqnr in self.fired_script:
            self.script.pop(reqnr, None)

    # -- masters ----------------------------------------------------------------------

    def switch(
        self,
        new_master: int,
        trigger: drone_pb2.HandoverTrigger.ValueType,
        now: float,
        takeover: bool = False,
        lost_at: float = 0.0,
        reason: str = "",
        position: api.Position | None = None,
        lost: int | None = None,
    ) -> drone_pb2.HandoverRecord:
        """Makes ``new_master`` the master in the next epoch; owes the old one a notice.

        ``reason`` and ``position`` (the handover policy's why and where) are kept
        in the record for the report.

        Called between two requests (the service holds its execution lock).
        FAILED_PRECONDITION if ``new_master`` already is the master: a
        handover to oneself would grant an epoch that fences nothing. A
        takeover may re-grant the master itself: a new master still waiting
        for a lost old master's log is told to stop waiting, and the new
        epoch fences that log if it comes late.
        """
        self.check_known(new_master)
        old = self.master
        if new_master == old and not (takeover and self.handovers):
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"controller {new_master} already is the master (epoch {self.epoch}, after "
                f"reqnr {self.last_reqnr})",
            )
        if lost is not None:
            old = lost  # the one whose log a takeover gives up, as the caller says
        elif new_master == old:
            old = self.handovers[-1].old_master  # the lost one whose log is given up
        ended = self.epoch
        record = drone_pb2.HandoverRecord(
            old_master=old,
            new_master=new_master,
            after_reqnr=self.last_reqnr,
            decided_at=now,
            trigger=trigger,
            epoch=ended + 1,
            kind=drone_pb2.HANDOVER_KIND_TAKEOVER
            if takeover
            else drone_pb2.HANDOVER_KIND_COOPERATIVE,
            lost_at=lost_at,
            reason=reason,
            position=position,
            watermark_reqnr=self.cache.watermark if takeover else 0,
        )
        self.handovers.append(record)
        self.master = new_master
        self._preparation_ended()  # a preparation ends with any switch
        # A master that got the role back no longer needs the notice of losing it:
        # after a cooperative switch its log never left it, so nobody acted without
        # it. One whose mastership was taken over meanwhile must still rejoin with
        # nothing: its Connect says which mastership's log it holds, and is refused
        # with ``baton-takeover`` (``admit_connect``).
        self.pending.pop(new_master, None)
        if old == new_master:
            return record  # its earlier self's log is given up: nobody to tell
        self.pending[old] = drone_pb2.HandoverNotice(
            old_master=old,
            new_master=new_master,
            after_reqnr=self.last_reqnr,
            ended_epoch=ended,
            epoch=ended + 1,
            takeover=takeover,
            grant=self.signed_grant(ended + 1),
            takeover_epoch=self.takeover_epoch,
            takeover_watermark_reqnr=record.watermark_reqnr,
        )
        return record

    def takeover_due(
        self,
        now: float,
        reachable: Iterable[int],
        last_seen: Mapping[int, float],
        after_s: float,
        unseen_from: float | None = None,
        serving: Mapping[int, float] | None = None,
        serve_within_s: float = 0.0,
    ) -> TakeoverDue | None:
        """Whether the master is lost, and who takes over (None: nobody, or not yet).

        ``reachable`` are the controllers holding a stream now, ``last_seen``
        when each last held one or sent a request (absent: not seen since the
        drone started). ``unseen_from`` is when a master not seen since the
        drone started counts as seen: the end of the start-up grace (the
        controllers come up one by one), or the switch that made it master
        if that came later; None: such a master is never lost (no controller
        was seen yet). Lost: the master, seen
        ``after_s`` ago or longer; the first reachable controller after it
        in ring order takes over (it received every log message that left
        the master). Also lost: the old master of a cooperative handover
        whose new master has sent nothing since (no request, and no word on
        a preparation, which only an ACTIVE master gives: after the
        mission's last request an ACTIVE new master sends no request,
        and a takeover then would fence it and lose its log), when the
        old master has
        not been seen for ``after_s`` since the switch (it died before
        sending its log): the new master is granted again, by takeover.
        The same for any old master of the cooperative switches since the
        last takeover or request: a new master that waits for a handover
        message is not ACTIVE, so it never sends one on, and the lost log
        holds up every switch after it (two switches at one instant, the
        first old master lost right after). ``lost`` is that old
        master, whose log the takeover gives up (``switch``'s ``lost``: its
        Connect is fenced); the middle masters never went ACTIVE, or hold a
        log the takeover's epoch replaces as it does a late handover
        message's.

        Lost too, whatever streams it holds: a master that has not served
        (``serving``: when each controller last held its Connect stream or
        sent a request) for ``serve_within_s`` since it last did, or since the
        switch that made it master. A master that keeps its standby stream but
        never connects (its handover message stuck on a frozen ring link, its
        program stopped) would otherwise be waited on for ever. The first
        reachable controller after it takes over, giving up its mastership.
        """
        live = set(reachable)
        if after_s <= 0:
            return None
        master_seen = last_seen.get(self.master)
        if master_seen is None:
            # Never seen since the drone started: the mission's start (the
            # controllers come up one by one), or the drone restarted before
            # the mission went anywhere. It gets the start-up grace; one that
            # never comes up is then lost like one that died (the mission
            # would wait for it for ever).
            if unseen_from is None:
                return None
            master_seen = unseen_from
            if self.handovers:
                master_seen = max(master_seen, self.handovers[-1].decided_at)
        if self.master not in live and now - master_seen >= after_s:
            taker = self._first_after(self.master, live)
            return None if taker is None else TakeoverDue(taker, self.master, master_seen)
        due = self._old_master_lost(now, live, last_seen, after_s)
        if due is None and serving is not None and serve_within_s > 0:
            due = self._not_serving(now, live, serving, serve_within_s, unseen_from)
        return due

    def _first_after(self, controller_id: int, live: set[int]) -> int | None:
        """The first controller after ``controller_id`` in ring order that is in ``live``."""
        position = self.ring.index(controller_id)
        for step in range(1, len(self.ring)):
            candidate = self.ring[(position + step) % len(self.ring)]
            if candidate in live:
                return candidate
        return None

    def _not_serving(
        self,
        now: float,
        live: set[int],
        serving: Mapping[int, float],
        serve_within_s: float,
        unseen_from: float | None,
    ) -> TakeoverDue | None:
        """``takeover_due``'s master that holds a stream but has not served for
        ``serve_within_s`` (since its last Connect stream or request, or the switch)."""
        since = serving.get(self.master, unseen_from)
        if since is None:
            return None
        if self.handovers:
            since = max(since, self.handovers[-1].decided_at)
        if now - since < serve_within_s:
            return None
        taker = self._first_after(self.master, live)
        return None if taker is None else TakeoverDue(taker, self.master, since)

    def _old_master_lost(
        self, now: float, live: set[int], last_seen: Mapping[int, float], after_s: float
    ) -> TakeoverDue | None:
        """``takeover_due``'s old master of the trailing cooperative switches, lost."""
        if not self.handovers or self.master not in live:
            return None
        if self.handovers[-1].new_master != self.master:
            return None
        # The trailing cooperative switches whose new masters sent nothing: each new
        # master waits for its old master's handover message, which an old master
        # sends only once ACTIVE, so one lost before its log left holds up every
        # switch after it (two at one instant, the script's and an RPC's).
        for record in reversed(self.handovers):
            if record.kind == drone_pb2.HANDOVER_KIND_TAKEOVER or record.first_request_at:
                return None
            if record.epoch <= self.active_epoch:
                return None  # its new master went ACTIVE: the log before it arrived
            old_seen = max(last_seen.get(record.old_master, 0.0), record.decided_at)
            if record.old_master not in live and now - old_seen >= after_s:
                return TakeoverDue(self.master, record.old_master, old_seen)
        return None

    def admit_connect(self, controller_id: int, mastership_epoch: int = 0) -> None:
        """Raises unless ``controller_id`` may hold a Connect stream (master, or owed a notice).

        ``mastership_epoch`` is the epoch of the mastership whose log the
        controller holds (ConnectRequest; 0: none). If a takeover gave that
        log up, the Connect is refused with ``baton-takeover`` (it rejoins
        as a replica with nothing, then connects again), whoever is master
        now (``taken_over_since``). A takeover notice owed to a controller
        that holds no such log is moot (it restarted or rejoined with
        nothing since): it is dropped, not delivered, so it does not make
        the controller rejoin twice.
        """
        self.check_known(controller_id)
        lost = self.taken_over_since(controller_id, mastership_epoch)
        if lost is not None:
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"Connect refused: controller {controller_id} holds the log of its mastership "
                f"in epoch {mastership_epoch}, which controller {lost.new_master} took over in "
                f"epoch {lost.epoch}; it rejoins as a replica with nothing, then connects again "
                f"(the master is controller {self.master}, epoch {self.epoch})",
                metadata=self.where_we_are(controller_id, mastership_epoch),
            )
        notice = self.pending.get(controller_id)
        if notice is not None and notice.takeover:
            del self.pending[controller_id]
        if controller_id != self.master and controller_id not in self.pending:
            raise self.not_master_error(controller_id, "Connect", mastership_epoch)
        if controller_id == self.master:
            self.connected_epoch = self.epoch

    def fresh_self_due(
        self, controller_id: int, mastership_epoch: int, given_up_epoch: int
    ) -> bool:
        """Whether the master's Connect comes from a fresh self of it that must be granted a
        new epoch (``take_over_from_earlier_self``): it holds the log of no mastership
        (``mastership_epoch`` 0) and says an earlier self gave up the log of the current
        one (``ConnectRequest.given_up_epoch``).

        That earlier self flushed log messages in this epoch on a framing it then
        gave up (it rejoined with nothing: ``ControllerProtocol.
        mastership_given_up``). Granted this epoch again, the fresh self's
        messages could not be told apart from those, and nothing newer would
        replace them where they are queued. A
        second Connect of the same fresh self before its first Connected says
        the same word, and is granted the new epoch as it is: the epoch has
        moved on.
        """
        return (
            controller_id == self.master
            and mastership_epoch == 0
            and 0 < given_up_epoch == self.epoch
            and bool(self.handovers)
        )

    def take_over_from_earlier_self(
        self, controller_id: int, now: float
    ) -> drone_pb2.HandoverRecord:
        """The master takes over from its earlier self (``fresh_self_due``): a new epoch, by
        takeover (its Connected says so, and it goes ACTIVE on what it holds and the
        replies the drone retains), giving up the earlier self's log
        (``taken_over_since`` fences a Connect that names it). No notice is owed."""
        return self.switch(
            controller_id, drone_pb2.HANDOVER_TRIGGER_LOST, now, takeover=True, lost=controller_id
        )

    @property
    def granted_by_takeover(self) -> bool:
        """Whether the current mastership was granted by a takeover (Connected.takeover).

        Its master is owed no handover message, and it must hold every
        request up to the watermark before it goes ACTIVE. Said on every
        Connected, because the master may not know: a taker that restarted or
        rejoined with nothing after its first request is not told the TakeOver
        again (``take_over_owed``), and would wait for ever for a handover
        message.
        """
        return bool(self.handovers) and self.handovers[-1].kind == drone_pb2.HANDOVER_KIND_TAKEOVER

    def replies_for_master(self, holds_reqnr: int) -> list[CachedReply]:
        """The retained replies the master's Connected is followed by: those above what
        it holds (``ConnectRequest.holds_reqnr``), and in a mastership granted by
        takeover every one above the watermark.

        A taker's held tail need not be the one the drone keeps: the policy's
        taker is the nearest station, not the first after the lost master, and
        may hold a master's framing that an earlier takeover replaced (a cut-off
        master's Clock readings, framed again by the taker that did not hold
        them). The replies it holds come too, with
        the epoch that brought each, for it to compare
        (``ControllerProtocol.replaced_framing``); they are bounded like the
        rest, by the flush limit and what is in flight.
        """
        above = 0 if self.granted_by_takeover else holds_reqnr
        return self.cache.retained_replies(above=above)

    def handover_must_take_over(self, new_master: int) -> bool:
        """Whether a handover to ``new_master`` decided now must be a takeover: the master
        was made master by a takeover and has not connected since, or it is the initial
        master, which has not connected and had nothing served.

        A cooperative handover needs the old master to hear the notice and send
        its log as a handover message, which only an ACTIVE master does. A
        taker that has not connected yet is not ACTIVE: it would never send
        it, and the new master would wait for ever. A takeover needs nobody's
        log: the new master gets the replies above what it holds from the
        drone, and the old master, told ``takeover``, rejoins as a replica.
        After a drone restart a taker that had connected counts as not
        connected until it connects again: the handover is then a takeover
        too, which costs its program a restart.
        """
        last = self.handovers[-1] if self.handovers else None
        if new_master == self.master or self.connected_epoch == self.epoch:
            return False
        if last is None:
            # The initial master, not connected and nothing served: it was never
            # ACTIVE (it goes ACTIVE on its Connected event) and holds no log, so it
            # would ignore the notice and the new master would wait for ever for its
            # handover message. A takeover loses nothing.
            return self.last_reqnr == 0
        return last.kind == drone_pb2.HANDOVER_KIND_TAKEOVER and last.new_master == self.master

    # -- prepared handovers (docs/design.md, "Prepared handover") -------------------

    def prepare(
        self,
        target: int,
        trigger: drone_pb2.HandoverTrigger.ValueType,
        now: float,
        timeout_s: float | None = None,
        reason: str = "",
        position: api.Position | None = None,
    ) -> drone_pb2.PrepareHandover:
        """Begins a prepared handover to ``target``; returns the notice the master is owed.

        INVALID_ARGUMENT for an unknown id, FAILED_PRECONDITION for the master
        itself (as ``switch``). A preparation under way is replaced.
        """
        self.check_known(target)
        if target == self.master:
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"controller {target} already is the master (epoch {self.epoch}, after "
                f"reqnr {self.last_reqnr})",
            )
        timeout = self.prepare_timeout_s if timeout_s is None else timeout_s
        notice = drone_pb2.PrepareHandover(
            target=target, epoch=self.epoch, timeout_s=timeout, bound_bytes=PREPARED_BOUND_BYTES
        )
        self._preparation_ended()
        self.preparing = Preparation(target, trigger, now, now + timeout, notice, reason, position)
        return notice

    def _preparation_ended(self) -> None:
        """The preparation under way, if any, ends (a switch, or a new one replaces it):
        the script line that began it has fired."""
        if self.preparing is not None and self.preparing.line:
            self.fired_script.append(self.preparing.line)
        self.preparing = None

    def note_progress(
        self, controller_id: int, epoch: int, progress: drone_pb2.PreparationProgress | None
    ) -> None:
        """The master's word on the preparation, from an Invoke it sent (admitted)."""
        p = self.preparing
        if p is None or progress is None or progress.target != p.target:
            return
        if controller_id == self.master and epoch == self.epoch:
            p.lacks_bytes, p.behind_s = progress.lacks_bytes, progress.behind_s
            p.acked = progress.acked

    def progress_between(
        self,
        controller_id: int,
        epoch: int,
        progress: drone_pb2.PreparationProgress,
        now: float,
    ) -> drone_pb2.HandoverRecord | None:
        """The master's word between requests (``ReportPreparation``, no request in
        service): moves the master now if the target has caught up. A word written
        before the last request was served (``after_reqnr`` below it) misses that
        reply and is ignored; so is one not of the master in its epoch."""
        if controller_id == self.master and epoch == self.epoch:
            self.active_epoch = epoch
        p = self.preparing
        if p is None or controller_id != self.master or epoch != self.epoch:
            return None
        if progress.target != p.target or progress.after_reqnr < self.last_reqnr:
            return None
        self.note_progress(controller_id, epoch, progress)
        return self._finish_preparation(0, now, force=False)

    def preparation_expired(self, now: float) -> drone_pb2.HandoverRecord | None:
        """At the deadline with no request served meanwhile: the handover is forced."""
        p = self.preparing
        if p is None or now < p.deadline:
            return None
        return self._finish_preparation(0, now)

    def _finish_preparation(
        self, reply_bytes: int, now: float, force: bool = True
    ) -> drone_pb2.HandoverRecord | None:
        """After a master's request: moves the master if its target has caught up (the
        master's last word and this reply within the bound) or (``force``) the time is up."""
        p = self.preparing
        assert p is not None
        lacked = None if p.lacks_bytes is None else p.lacks_bytes + reply_bytes
        # A word speaks of the request it came with: the next must bring its own
        # (this reply may be a picture the target now lacks too).
        p.lacks_bytes = None
        caught_up = (
            lacked is not None
            and lacked <= PREPARED_BOUND_BYTES
            and p.behind_s <= PREPARED_BEHIND_S
            and p.acked > 0
        )
        if not caught_up and (now < p.deadline or not force):
            return None
        record = self.switch(p.target, p.trigger, now, reason=p.reason, position=p.position)
        record.kind = (
            drone_pb2.HANDOVER_KIND_PREPARED if caught_up else drone_pb2.HANDOVER_KIND_COOPERATIVE
        )
        record.prepare_started_at = p.started_at
        record.prepare_timed_out = not caught_up
        record.prepare_lacked_bytes = lacked or 0
        return record

    def delivered(self, controller_id: int, notice: drone_pb2.HandoverNotice) -> None:
        """The notice reached its old master; it is no longer owed."""
        if self.pending.get(controller_id) is notice:
            del self.pending[controller_id]


def cut_off_outcome(method: str, reqnr: int, is_read: bool) -> StatusError | None:
    """What a request the drone was executing when it restarted becomes.

    None for a read: it changed nothing, and the re-sent request executes it
    again. UNKNOWN for anything else: the vehicle may have acted on it, so
    it is booked with that failure and never executed a second time.
    """
    if is_read:
        return None
    return StatusError(
        grpc.StatusCode.UNKNOWN,
        f"{method} (request {reqnr}) was being executed when the drone service "
        "restarted: the vehicle may have acted on it, so it is not executed again",
    )


def _given_up(reply: CachedReply) -> bool:
    """A call the mission program gave up on, as its master sent it along."""
    return reply.error is not None and GIVEN_UP in reply.error.metadata

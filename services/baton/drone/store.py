"""The drone's durable state: what a restarted drone service must not forget.

The drone service runs on the drone's companion computer, which can crash or
be restarted mid-mission. What it knows decides what the vehicle does next:
who the master is, the last request number it served, the replies it must
give again to a re-sent request (the reply cache), the audit, how far the
handover script has got, and the request it was executing when it died. All
of it is kept in one SQLite file (the standard library's), written in the
same transaction as the request it belongs to, so a kill -9 at any point
loses nothing that a caller was told.

The request being executed is written first (an *intent*) and cleared with
its outcome. An intent found at start means the drone died while the vehicle
may have been acting on it: a read is executed again when it is re-sent (it
changes nothing), a command is answered with UNKNOWN and never executed a
second time (at most once, counted at the vehicle).

The handover policy's runner keeps what the vehicle outlives the drone with
(``PolicyMemory``): the leg it flies (the master's last Goto) and whether the
policy holds it. An autopilot told to hold keeps holding whatever happens to
the companion computer, so a restarted drone must know to resume it.

Durability: WAL with ``synchronous=NORMAL``, which survives the process
being killed (the operating system keeps what was written); a power cut may
lose the last transactions. ``synchronous=FULL`` would cost an fsync per
request. Checkpoints run on a thread of their own (``baton.wal``), not in a
request's commit.

A write that fails (the disk full, an I/O error, a read-only file system) is
kept, and tried again, in order, before the next write (``baton.durability``):
every write replaces rows whole, so the first that succeeds makes the file
whole again. Until one does, ``begin`` refuses the request UNAVAILABLE: a
request executed with no intent on disk could be executed again by a drone
restarted from the file. A failed ``served`` does not take back what was
executed: its intent is on disk (a restart answers the request UNKNOWN, never
executes it again), and the reply cache in memory answers a re-sent request.
"""

from __future__ import annotations

import json
import sqlite3
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from baton.drone.dedupe import CachedReply
from baton.drone.safety import Failsafe
from baton.drone.sequencer import AUDIT_IN_MEMORY
from baton.durability import (
    FileHealth,
    Report,
    drone_refusal,
    write_failed,
    write_succeeded,
)
from baton.logs import get_logger
from baton.rpc.errors import StatusError, status_of
from baton.v1 import drone_pb2
from baton.wal import describe_write_error, open_wal, roll_back

if TYPE_CHECKING:
    from baton.drone.sequencer import Sequencer

SCHEMA = """
CREATE TABLE IF NOT EXISTS state (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    master INTEGER NOT NULL,
    last_reqnr INTEGER NOT NULL,
    executed INTEGER NOT NULL,
    duplicates INTEGER NOT NULL,
    rejected INTEGER NOT NULL,
    handovers BLOB NOT NULL,
    fired_script TEXT NOT NULL,
    watermark INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS replies (
    reqnr INTEGER PRIMARY KEY,
    method TEXT NOT NULL,
    digest BLOB NOT NULL,
    reply BLOB NOT NULL,
    code INTEGER,
    message TEXT,
    metadata TEXT,
    epoch INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS audit (reqnr INTEGER PRIMARY KEY, entry BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS executing (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    reqnr INTEGER NOT NULL,
    method TEXT NOT NULL,
    digest BLOB NOT NULL,
    controller_id INTEGER NOT NULL,
    received_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS commanded (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS policy (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    leg BLOB,
    held INTEGER NOT NULL,
    resumes INTEGER NOT NULL DEFAULT 0
);
"""


@dataclass
class Counters:
    """The drone's counters and position in the mission, as GetStatus shows them."""

    master: int
    last_reqnr: int = 0
    executed: int = 0
    duplicates: int = 0
    rejected: int = 0
    handovers: list[drone_pb2.HandoverRecord] = field(default_factory=list)
    fired_script: list[int] = field(default_factory=list)  # script reqnrs already fired
    # The reply cache's watermark: the replies at or below it are let go (dedupe.py).
    watermark: int = 0


def counters_of(seq: Sequencer) -> Counters:
    """What the store keeps of ``seq``: its counters and position in the mission."""
    return Counters(
        master=seq.master,
        last_reqnr=seq.last_reqnr,
        executed=seq.executed,
        duplicates=seq.duplicates,
        rejected=seq.rejected,
        handovers=list(seq.handovers),
        fired_script=list(seq.fired_script),
        watermark=seq.cache.watermark,
    )


@dataclass(frozen=True)
class Intent:
    """A request the drone had started to execute."""

    reqnr: int
    method: str
    digest: bytes
    controller_id: int
    received_at: float


@dataclass(frozen=True)
class PolicyMemory:
    """What the handover policy's runner must not forget (``policy_runner.py``): the leg
    the vehicle flies (the master's last Goto, a serialized ``GotoRequest``; None: none
    known), whether the policy holds the vehicle in the air, and how many resumes it
    sent (``DroneStatus.policy_resumes``)."""

    leg: bytes | None = None
    held: bool = False
    resumes: int = 0


@dataclass
class DroneState:
    """Everything the store holds, as loaded at start."""

    counters: Counters
    replies: list[CachedReply]
    audit: list[drone_pb2.AuditEntry]
    executing: Intent | None


class DroneStore:
    """One SQLite file; every write is one transaction."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._db, self._checkpointer = open_wal(self.path)
            self._db.executescript(SCHEMA)
            columns = {row[1] for row in self._db.execute("PRAGMA table_info(state)")}
            if "watermark" not in columns:  # a file written before the watermark was kept
                self._db.execute(
                    "ALTER TABLE state ADD COLUMN watermark INTEGER NOT NULL DEFAULT 0"
                )
            columns = {row[1] for row in self._db.execute("PRAGMA table_info(policy)")}
            if "resumes" not in columns:  # a file written before the resumes were kept
                self._db.execute("ALTER TABLE policy ADD COLUMN resumes INTEGER NOT NULL DEFAULT 0")
            columns = {row[1] for row in self._db.execute("PRAGMA table_info(replies)")}
            if "epoch" not in columns:  # a file written before the replies' epochs were kept
                self._db.execute("ALTER TABLE replies ADD COLUMN epoch INTEGER NOT NULL DEFAULT 0")
        except (OSError, sqlite3.Error) as exc:
            raise OSError(
                f"drone state file {self.path} (--state): {exc}; give a writable path"
            ) from exc
        self.health = FileHealth(str(self.path))
        # Writes that failed, each with what it was, to be tried again first, in order.
        self._unsaved: list[tuple[str, Callable[[], object]]] = []
        self._log = get_logger("store", file=str(self.path))
        # Whether failing checkpoints were said (once, until one succeeds again).
        self._checkpoints_failing = False

    @property
    def problem(self) -> str:
        """What GetStatus says while the file takes no writes ("" while it does)."""
        refusal = drone_refusal(self.health)
        return "" if refusal is None else refusal.message

    def _write(self, what: str, write: Callable[[], object], keep: bool = True) -> bool:
        """``write`` (one transaction) after the failed ones; False if any still fails.
        ``keep``: a write that fails is tried again before the next (not an intent: its
        request is refused, and no record of it may appear later)."""
        self._watch_checkpoints()
        entry = (what, write)
        self._unsaved.append(entry)
        written = self._write_through()
        if not written and not keep:
            self._unsaved.remove(entry)
        return written

    def _watch_checkpoints(self) -> None:
        """Failing checkpoints, said once: the file's disk is filling, though commits
        still reach its write-ahead log (and a drone restarted reads them from there)."""
        failed = self._checkpointer.failed
        if failed and not self._checkpoints_failing:
            self._log.error(
                f"checkpoints of {self.path} fail: {failed}; requests are still written to "
                f"{self.path.name}-wal while its disk has room, then refused",
                file=str(self.path),
                error=failed,
            )
        elif not failed and self._checkpoints_failing:
            self._log.info(f"checkpoints of {self.path} succeed again", file=str(self.path))
        self._checkpoints_failing = bool(failed)

    def _write_through(self) -> bool:
        while self._unsaved:
            what, write = self._unsaved[0]
            try:
                write()
            except sqlite3.Error as exc:
                roll_back(self._db)
                self.health, reports = write_failed(
                    self.health,
                    what,
                    describe_write_error(self.path, exc),
                    time.time(),
                    "the drone refuses new requests until a write succeeds (it tries again at "
                    "each request), so that none can be executed twice after a restart",
                )
                self._report(reports)
                return False
            del self._unsaved[0]
        self.health, reports = write_succeeded(self.health, time.time())
        self._report(reports)
        return True

    def _report(self, reports: Sequence[Report]) -> None:
        for report in reports:
            getattr(self._log, report.level)(report.text, **report.fields)

    def close(self) -> None:
        """Closes the file."""
        self._checkpointer.close()
        self._db.close()

    def load(self) -> DroneState | None:
        """What was stored; None for a new file."""
        row = self._db.execute(
            "SELECT master, last_reqnr, executed, duplicates, rejected, handovers, fired_script, "
            "watermark FROM state WHERE id = 1"
        ).fetchone()
        if row is None:
            return None
        master, last_reqnr, executed, duplicates, rejected, handovers, fired, watermark = row
        counters = Counters(
            master,
            last_reqnr,
            executed,
            duplicates,
            rejected,
            list(drone_pb2.DroneStatus.FromString(handovers).handovers),
            list(json.loads(fired)),
            watermark,
        )
        replies = [
            CachedReply(
                reqnr, method, bytes(digest), bytes(reply), _error(code, message, meta), epoch
            )
            for reqnr, method, digest, reply, code, message, meta, epoch in self._db.execute(
                "SELECT reqnr, method, digest, reply, code, message, metadata, epoch FROM replies "
                "ORDER BY reqnr"
            )
        ]
        newest = self._db.execute(
            "SELECT entry FROM audit ORDER BY reqnr DESC LIMIT ?", (AUDIT_IN_MEMORY,)
        )
        audit = [drone_pb2.AuditEntry.FromString(entry) for (entry,) in newest][::-1]
        intent = self._db.execute(
            "SELECT reqnr, method, digest, controller_id, received_at FROM executing WHERE id = 1"
        ).fetchone()
        executing = None
        if intent is not None:
            reqnr, method, digest, controller_id, received_at = intent
            executing = Intent(reqnr, method, bytes(digest), controller_id, received_at)
        return DroneState(counters, replies, audit, executing)

    def load_policy(self) -> PolicyMemory:
        """The policy runner's memory; empty for a new file (or a drone without a policy)."""
        row = self._db.execute("SELECT leg, held, resumes FROM policy WHERE id = 1").fetchone()
        if row is None:
            return PolicyMemory()
        leg, held, resumes = row
        return PolicyMemory(None if leg is None else bytes(leg), bool(held), int(resumes))

    def save_policy(self, memory: PolicyMemory) -> None:
        """The policy runner's memory, replacing what was kept (one statement: atomic)."""

        def write() -> None:
            self._db.execute(
                "INSERT OR REPLACE INTO policy (id, leg, held, resumes) VALUES (1, ?, ?, ?)",
                (memory.leg, int(memory.held), memory.resumes),
            )

        self._write("the policy's memory", write)

    def save_failsafe(self, failsafe: Failsafe | None) -> None:
        """The failsafe the vehicle is in (None: cleared): a restarted drone keeps refusing
        the mission's calls until an operator resumes."""
        self.save_commanded("failsafe", None if failsafe is None else asdict(failsafe))

    def load_failsafe(self) -> Failsafe | None:
        """The failsafe kept by ``save_failsafe``; None if none."""
        kept = self.load_commanded().get("failsafe")
        return None if kept is None else Failsafe(**kept)

    def save_commanded(self, key: str, value: Any) -> None:
        """Commanded state the vehicle must get again after a restart of the drone or the
        autopilot (the mission's cruise speed, the failsafe), as JSON; None forgets it."""

        def write() -> None:
            with self._transaction():
                if value is None:
                    self._db.execute("DELETE FROM commanded WHERE key = ?", (key,))
                else:
                    self._db.execute(
                        "INSERT OR REPLACE INTO commanded VALUES (?, ?)", (key, json.dumps(value))
                    )

        self._write(f"the commanded {key}", write)

    def load_commanded(self) -> dict[str, Any]:
        """Everything ``save_commanded`` kept, by key."""
        rows = self._db.execute("SELECT key, value FROM commanded").fetchall()
        return {key: json.loads(value) for key, value in rows}

    def audit_page(self, after_reqnr: int, limit: int) -> list[drone_pb2.AuditEntry]:
        """At most ``limit`` audit entries with a reqnr above ``after_reqnr``, in order."""
        rows = self._db.execute(
            "SELECT entry FROM audit WHERE reqnr > ? ORDER BY reqnr LIMIT ?",
            (after_reqnr, limit),
        )
        return [drone_pb2.AuditEntry.FromString(entry) for (entry,) in rows]

    def oldest_audit_reqnr(self) -> int:
        """The oldest reqnr in the audit; 0 if it is empty."""
        (oldest,) = self._db.execute("SELECT COALESCE(MIN(reqnr), 0) FROM audit").fetchone()
        return int(oldest)

    def begin(self, intent: Intent, answers: Sequence[CachedReply] = ()) -> None:
        """Notes the request about to be executed, with the calls its master answered
        itself that came with it (kept for a taker whatever happens next). Raises
        StatusError UNAVAILABLE if the file takes no writes: the request must not be
        executed."""

        def write() -> None:
            with self._transaction():
                self._put(answers)
                self._db.execute(
                    "INSERT OR REPLACE INTO executing (id, reqnr, method, digest, "
                    "controller_id, received_at) VALUES (1, ?, ?, ?, ?, ?)",
                    (
                        intent.reqnr,
                        intent.method,
                        intent.digest,
                        intent.controller_id,
                        intent.received_at,
                    ),
                )

        if not self._write(f"the intent of request {intent.reqnr}", write, keep=False):
            refusal = drone_refusal(self.health)
            assert refusal is not None
            raise refusal

    def abandon(self) -> None:
        """The request noted by ``begin`` executed nothing (its reqnr stays unused)."""
        self._write("an abandoned intent", lambda: self._db.execute("DELETE FROM executing"))

    def served(
        self,
        counters: Counters,
        reply: CachedReply,
        audit: drone_pb2.AuditEntry,
        oldest_cached: int,
    ) -> None:
        """A request's outcome, its audit entry and the counters, in one transaction."""

        def write() -> None:
            with self._transaction():
                self._put([reply])
                self._db.execute("DELETE FROM replies WHERE reqnr < ?", (oldest_cached,))
                self._db.execute(
                    "INSERT OR REPLACE INTO audit VALUES (?, ?)",
                    (audit.reqnr, audit.SerializeToString()),
                )
                self._db.execute("DELETE FROM executing")
                self._write_counters(counters)

        self._write(f"the outcome of request {reply.reqnr}", write)

    def _put(self, replies: Sequence[CachedReply]) -> None:
        self._db.executemany(
            "INSERT OR REPLACE INTO replies VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
            [
                (
                    reply.reqnr,
                    reply.method,
                    reply.digest,
                    reply.reply,
                    None if reply.error is None else reply.error.code.value[0],
                    None if reply.error is None else reply.error.message,
                    None if reply.error is None else json.dumps(list(reply.error.metadata)),
                    reply.epoch,
                )
                for reply in replies
            ],
        )

    def save(self, counters: Counters) -> None:
        """The counters alone (a handover between requests)."""

        def write() -> None:
            with self._transaction():
                self._write_counters(counters)

        self._write("the counters", write)

    def _write_counters(self, c: Counters) -> None:
        handovers = drone_pb2.DroneStatus(handovers=c.handovers).SerializeToString()
        self._db.execute(
            "INSERT OR REPLACE INTO state (id, master, last_reqnr, executed, duplicates, "
            "rejected, handovers, fired_script, watermark) VALUES (1, ?, ?, ?, ?, ?, ?, ?, ?)",
            (
                c.master,
                c.last_reqnr,
                c.executed,
                c.duplicates,
                c.rejected,
                handovers,
                json.dumps(sorted(c.fired_script)),
                c.watermark,
            ),
        )

    def _transaction(self) -> _Transaction:
        return _Transaction(self._db)


class _Transaction:
    """BEGIN ... COMMIT, or ROLLBACK on an exception."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db

    def __enter__(self) -> None:
        self._db.execute("BEGIN")

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self._db.execute("COMMIT" if exc_type is None else "ROLLBACK")


def _error(code: int | None, message: str | None, metadata: str | None) -> StatusError | None:
    if code is None:
        return None
    pairs = [(str(k), str(v)) for k, v in json.loads(metadata or "[]")]
    return StatusError(status_of(code), message or "", metadata=pairs)

"""Every log message a controller holds, on disk: what it recovers, and gives a successor.

Every controller sees every log number (it received the message, or created
it), so each one can give its successor the whole log again when the
successor comes back with nothing (docs/design.md, "Restarts and catch-up").
The messages are written once, as they arrive, to a SQLite file; memory
holds none of them (a mission's pictures are 100 MB and more).

With a file of its own (``baton controller --log-file``, which the testbed
gives every controller), the history outlives the process: a controller
restarted after a crash recovers what it had from it (``recover``) before
its predecessor gives it the rest. Without one, the file is a temporary one
that is unlinked as soon as it is open: it goes with the process.

The format (for ``baton replay`` and the mission report): a table
``messages(lognr INTEGER PRIMARY KEY, message BLOB)``, each row a serialized
``baton.v1.LogMessage`` (ring.proto) as the ring carried it, with its
``handover`` flag cleared: history re-sent to a restarted controller never
makes it master; only the drone's grant or a handover message still owed to
it does; and a table ``meta(key, value)`` with ``mastership_epoch``, the
epoch of the mastership whose log the file holds (what the controller tells
the drone on Connect, to be fenced if a takeover gave that log up). WAL
journal, ``synchronous=NORMAL``: a kill -9 loses nothing
written; a power cut may lose the last messages, which the ring gives again.
Its checkpoints run on a thread of their own (``baton.wal``), not in the
commit of a message on the event loop.

A write that fails (the disk full, an I/O error, a read-only file system), or
a checkpoint that fails, ends the file's durability (``baton.durability``):
the controller says so once (an ERROR naming the file, the write and the
error, and ``ControllerStatus.log_file``), writes nothing more to the file,
and keeps every later message in memory, still replicating. The file stays
whole up to the log number stated then, which it records, if it still can,
as ``meta.whole_up_to_lognr``; ``baton replay`` stops there and names what
is missing. A controller opened on a file it cannot write says so at start
(a probe write).
"""

from __future__ import annotations

import os
import sqlite3
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from google.protobuf.message import DecodeError

from baton.authenticity import holding_proof
from baton.controller.protocol import SeenNumbers
from baton.durability import FileHealth, held_whole, write_failed
from baton.logs import get_logger
from baton.v1 import drone_pb2, ring_pb2
from baton.wal import Checkpointer, describe_write_error, open_wal, roll_back

SCHEMA = "CREATE TABLE IF NOT EXISTS messages (lognr INTEGER PRIMARY KEY, message BLOB NOT NULL)"
# What the controller must know about its log beyond the messages, by name:
# ``mastership_epoch``, the epoch of the mastership whose log it holds;
# ``whole_up_to_lognr``, once a write failed, the log number up to which the file is
# whole (``baton replay`` reads no further).
META_SCHEMA = "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value INTEGER NOT NULL)"


# What the start's probe writes (and deletes): a disk that cannot take this much more
# is said to be full at start. One picture's log message is larger.
PROBE_BYTES = 64 << 10


@dataclass(frozen=True)
class Heading:
    """What a ring stream's greeting and sync words say of a held message, kept in
    memory beside it so that it is never read back for them (a message may carry
    64 MB of pictures): the epoch it was framed in, the drone's grant it carries, and
    its proof of holding (``authenticity.holding_proof``; b"" unsigned)."""

    epoch: int
    grant: drone_pb2.Grant | None
    proof: bytes

    @classmethod
    def of(cls, message: ring_pb2.LogMessage, proof: bytes = b"") -> Heading:
        """``message``'s heading; ``proof``: its holding proof if the caller computed it
        (with its signature or its check), else computed here if it is signed."""
        if message.signature and not proof:
            proof = holding_proof(message)
        grant = None
        if message.HasField("grant"):
            # A copy: a sub-message keeps its whole message alive (upb's arena), and a
            # heading outlives the message it heads, pictures and all.
            grant = drone_pb2.Grant()
            grant.CopyFrom(message.grant)
        return cls(message.epoch, grant, proof if message.signature else b"")


class LogHistory:
    """Log messages by log number, in SQLite; ``holds_lognr`` is the contiguous top."""

    def __init__(self, path: str | Path | None = None) -> None:
        self.path = Path(path) if path is not None else None
        self._checkpointer: Checkpointer | None = None
        try:
            if self.path is None:
                fd, temporary = tempfile.mkstemp(prefix="baton-history-", suffix=".sqlite")
                os.close(fd)
                self._db = sqlite3.connect(temporary, isolation_level=None)
                # No journal file to find by name: the database can be unlinked now.
                self._db.execute("PRAGMA journal_mode=MEMORY")
                self._db.execute("PRAGMA synchronous=OFF")
                self._db.execute(SCHEMA)
                self._db.execute(META_SCHEMA)
                os.unlink(temporary)
            else:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self._db, self._checkpointer = open_wal(self.path)
                self._db.execute(SCHEMA)
                self._db.execute(META_SCHEMA)
            self._lognrs = {n for (n,) in self._db.execute("SELECT lognr FROM messages")}
            row = self._db.execute(
                "SELECT value FROM meta WHERE key = 'mastership_epoch'"
            ).fetchone()
            self._mastership_epoch = int(row[0]) if row else 0
        except (OSError, sqlite3.Error) as exc:
            raise OSError(
                f"controller log file {self.path} (--log-file): {exc}; give a writable path"
            ) from exc
        self._held = SeenNumbers()
        for lognr in sorted(self._lognrs):
            self._held.add(lognr)
        # Messages the file could not take, by log number, serialized (memory only).
        self._memory: dict[int, bytes] = {}
        # The headings of the messages held (``heading``); one recovered from the file
        # is read once, when first asked for.
        self._headings: dict[int, Heading] = {}
        self.health = FileHealth(str(self.path) if self.path else "(a temporary file)")
        self._log = get_logger("history", file=self.health.path)
        if self.path is not None:  # a temporary file claims nothing to probe for
            self._probe()

    def _probe(self) -> None:
        """A write of ``PROBE_BYTES`` at start, deleted (``meta.starts`` counted): a file
        whose disk cannot take that much more is said so now, not at its first message
        (a checkpoint that fails later is said by ``poll``). A file that takes writes
        again drops its mark: the ring gives a restarted controller what its file lacks,
        and the file is written whole again."""
        writes: list[tuple[str, tuple[object, ...]]] = [
            (
                "INSERT INTO meta (key, value) VALUES ('starts', 1) "
                "ON CONFLICT (key) DO UPDATE SET value = value + 1",
                (),
            ),
            (
                "INSERT OR REPLACE INTO meta (key, value) VALUES ('probe', zeroblob(?))",
                (PROBE_BYTES,),
            ),
            ("DELETE FROM meta WHERE key IN ('probe', 'whole_up_to_lognr')", ()),
        ]
        for sql, params in writes:
            if not self._write("the start's probe write", sql, params):
                return

    def poll(self) -> None:
        """Takes a failed checkpoint (reported by its thread) as the file's failure."""
        if self._checkpointer is not None and self._checkpointer.failed and self.health.durable:
            self._fail("a checkpoint", self._checkpointer.failed, self._checkpointer.failed_at)

    def status(self) -> ring_pb2.LogFileStatus:
        """The file's health, for GetStatus."""
        self.poll()
        h = self.health
        return ring_pb2.LogFileStatus(
            path=h.path,
            durable=h.durable,
            failed_write=h.failed_write,
            error=h.error,
            failed_at=h.failed_at,
            failures=h.failures,
            whole_up_to_lognr=h.whole_up_to,
        )

    def _write(self, what: str, sql: str, params: tuple[object, ...] = ()) -> bool:
        """One write to the file while it takes writes; False once it does not."""
        self.poll()
        if not self.health.durable:
            return False
        try:
            self._db.execute(sql, params)
        except sqlite3.Error as exc:
            self._failed(what, exc)
            return False
        return True

    def _failed(self, what: str, exc: sqlite3.Error) -> None:
        roll_back(self._db)
        self._fail(what, describe_write_error(self.path, exc))

    def _fail(self, what: str, error: str, began: float | None = None) -> None:
        whole = 0
        while whole + 1 in self._lognrs and whole + 1 not in self._memory:
            whole += 1
        self.health, reports = write_failed(
            self.health,
            what,
            error,
            time.time(),
            f"the log is no longer durable: the file holds {held_whole(whole)} whole; "
            "this controller keeps later ones in memory only and still replicates (a restart "
            "recovers only what the file holds; the ring gives it the rest)",
            whole,
            began,
        )
        for report in reports:
            getattr(self._log, report.level)(report.text, **report.fields)
        try:  # the mark, if the file still takes one small write
            self._db.execute(
                "INSERT OR REPLACE INTO meta (key, value) VALUES ('whole_up_to_lognr', ?)",
                (whole,),
            )
        except sqlite3.Error:
            roll_back(self._db)

    def close(self) -> None:
        """Closes the file (a temporary one is gone with it)."""
        if self._checkpointer is not None:
            self._checkpointer.close()
        self._db.close()

    def clear(self) -> None:
        """Forgets every message (a controller fenced by a takeover rejoins with nothing).
        A file that no longer takes writes keeps what it held, with its mark."""
        if self._write("clearing the log", "DELETE FROM messages"):
            self._write("clearing the log", "DELETE FROM meta")
        self._memory.clear()
        self._headings.clear()
        self._lognrs.clear()
        self._held = SeenNumbers()
        self._mastership_epoch = 0

    @property
    def mastership_epoch(self) -> int:
        """The epoch of the mastership whose log this history holds (0: none).

        Kept with the messages and cleared with them, so that a controller
        restarted from its file still tells the drone (ConnectRequest) that
        it holds the log of a mastership the drone may have given up by
        takeover meanwhile, and is made to rejoin with nothing.
        """
        return self._mastership_epoch

    def keep_mastership_epoch(self, epoch: int) -> None:
        """Records ``epoch`` as the mastership whose log this history holds."""
        if epoch == self._mastership_epoch:
            return
        self._write(
            f"the mastership epoch {epoch}",
            "INSERT OR REPLACE INTO meta (key, value) VALUES ('mastership_epoch', ?)",
            (epoch,),
        )
        self._mastership_epoch = epoch

    def __contains__(self, lognr: object) -> bool:
        return lognr in self._lognrs

    def __len__(self) -> int:
        return len(self._lognrs)

    @property
    def holds_lognr(self) -> int:
        """Every log number up to this one is held."""
        return self._held.upto

    def add(self, message: ring_pb2.LogMessage, proof: bytes = b"") -> None:
        """Keeps ``message`` unless a message with its log number is held already,
        from the same or a newer epoch (one from an older epoch is replaced: a
        takeover numbered the log again, and a controller keeps the ring's framing
        of a message it has not handled yet, ``ControllerProtocol.on_log``).
        ``proof``: its holding proof, if the caller computed it (``Heading.of``)."""
        if message.lognr in self._lognrs and self.heading(message.lognr).epoch >= message.epoch:
            return
        if message.handover:
            kept = ring_pb2.LogMessage()
            kept.CopyFrom(message)
            kept.handover = False
            message = kept
        blob = message.SerializeToString()
        if self._write(
            f"log message {message.lognr}",
            "INSERT OR REPLACE INTO messages (lognr, message) VALUES (?, ?)",
            (message.lognr, blob),
        ):
            self._memory.pop(message.lognr, None)
        else:
            self._memory[message.lognr] = blob
        self._lognrs.add(message.lognr)
        self._held.add(message.lognr)
        self._headings[message.lognr] = Heading.of(message, proof)

    def discard(self, lognr: int, epoch: int) -> None:
        """Forgets the message ``lognr`` if it is of ``epoch``: one received and dropped
        unhandled, of a framing a takeover replaced (protocol.py ``Unqueued``)."""
        if lognr not in self._lognrs or self.heading(lognr).epoch != epoch:
            return
        if self._memory.pop(lognr, None) is None:
            self._write(
                f"dropping log message {lognr}", "DELETE FROM messages WHERE lognr = ?", (lognr,)
            )
        self._lognrs.discard(lognr)
        self._held.discard(lognr)
        self._headings.pop(lognr, None)

    def get(self, lognr: int) -> ring_pb2.LogMessage:
        """The message with ``lognr``; KeyError if it is not held."""
        kept = self._memory.get(lognr)
        if kept is not None:
            return ring_pb2.LogMessage.FromString(kept)
        row = self._db.execute("SELECT message FROM messages WHERE lognr = ?", (lognr,)).fetchone()
        if row is None:
            raise KeyError(lognr)
        return ring_pb2.LogMessage.FromString(row[0])

    def heading(self, lognr: int) -> Heading:
        """What the ring's greetings and sync words say of message ``lognr`` (``Heading``);
        KeyError if it is not held."""
        heading = self._headings.get(lognr)
        if heading is None:
            heading = self._headings[lognr] = Heading.of(self.get(lognr))
        return heading

    def above(self, lognr: int) -> Iterator[int]:
        """The held log numbers above ``lognr``, in order."""
        return iter(sorted(n for n in self._lognrs if n > lognr))


class NotALogFile(ValueError):
    """A file that is not a controller's log (``read_log``), and why."""


class OtherDatabase(NotALogFile):
    """A SQLite database, but without a log's ``messages`` table (the drone's state, say)."""


@dataclass(frozen=True)
class SavedLog:
    """A saved log file as ``baton replay`` reads it."""

    messages: list[ring_pb2.LogMessage]
    # Set when its controller could not write to it: the log number up to which the
    # file is whole (``messages`` stops there); None: a file whose writes never failed.
    whole_up_to: int | None = None


def read_log(path: str | Path) -> list[ring_pb2.LogMessage]:
    """The messages of a saved log file, by log number (``read_saved_log``)."""
    return read_saved_log(path).messages


def read_saved_log(path: str | Path) -> SavedLog:
    """A saved log file, read without changing it: its messages by log number, up to
    the log number its mark says the file is whole to, if its controller marked it.

    For ``baton replay``: the file may be a copy, read-only, or still open in
    a controller (WAL lets it read what was committed). Raises ``NotALogFile``
    naming the file and what is wrong with it.
    """
    file = Path(path)
    if not file.is_file():
        raise NotALogFile(f"{file}: no such file")
    try:
        db = sqlite3.connect(f"{file.resolve().as_uri()}?mode=ro", uri=True)
    except sqlite3.Error as exc:
        raise NotALogFile(f"{file}: cannot open it: {exc}") from exc
    try:
        rows = db.execute("SELECT lognr, message FROM messages ORDER BY lognr").fetchall()
        mark = (
            db.execute("SELECT value FROM meta WHERE key = 'whole_up_to_lognr'").fetchone()
            if _has_meta(db)
            else None
        )
    except sqlite3.OperationalError as exc:
        raise OtherDatabase(
            f"{file}: not a controller log file ({exc}): a SQLite database of another kind"
        ) from exc
    except sqlite3.DatabaseError as exc:
        if _sqlite_header(file):
            raise NotALogFile(
                f"{file}: a damaged file ({exc}): it was cut or overwritten, and what it "
                "held cannot be read; replay another controller's log file"
            ) from exc
        raise NotALogFile(
            f"{file}: not a controller log file ({exc}); give a controller's --log-file "
            "(the testbed keeps them as controller-N-log.sqlite in its workdir)"
        ) from exc
    finally:
        db.close()
    whole_up_to = None if mark is None else int(mark[0])
    messages = []
    for lognr, blob in rows:
        if whole_up_to is not None and lognr > whole_up_to:
            break
        try:
            message = ring_pb2.LogMessage.FromString(blob)
        except DecodeError as exc:
            raise NotALogFile(f"{file}: log message {lognr} does not decode: {exc}") from exc
        if message.lognr != lognr:
            raise NotALogFile(f"{file}: row {lognr} holds log message {message.lognr}")
        messages.append(message)
    return SavedLog(messages, whole_up_to)


def _sqlite_header(file: Path) -> bool:
    """Whether ``file`` begins as a SQLite database does (one that then fails to read is
    damaged: cut or overwritten)."""
    with file.open("rb") as opened:
        return opened.read(16) == b"SQLite format 3\x00"


def _has_meta(db: sqlite3.Connection) -> bool:
    """Whether the file has the ``meta`` table (files written before it was kept do not)."""
    row = db.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'meta'")
    return row.fetchone() is not None

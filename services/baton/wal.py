"""SQLite files in WAL mode whose checkpoints never stall the event loop.

The controller's history and the drone's state are SQLite files in WAL mode
with ``synchronous=NORMAL``: a commit appends to the write-ahead log without
an fsync, so a kill -9 loses nothing committed. SQLite's automatic
checkpoint, though, runs *inside* the commit that takes the log past 1,000
pages (4 MB): that commit copies the log into the database file and fsyncs
it, on the caller's thread, which for baton is the event loop. Measured here
(2 cores, the CI machine's disk): a 1 MB insert takes 1.5 ms, and every
fourth one 16-19 ms; a 4 MB insert 12.5 ms, or 25 ms with the checkpoint it
always triggers. On a handover's path that is the old master storing its
flush before the first frame goes out and the new master storing it before
it acknowledges (docs/design.md, "Storage off the event loop").

``open_wal`` turns the automatic checkpoint off and runs checkpoints from a
thread of the file's own (``Checkpointer``), with its own connection, every
``CHECKPOINT_EVERY_S`` when something was committed: a PASSIVE checkpoint
never blocks the writer, SQLite releases the GIL while it copies and
fsyncs, and once a checkpoint has caught up the writer's next commit starts
the log from the beginning again, so the log stays near what is written in
one period. Durability is unchanged: the same commits reach the log, and
the same checkpoints the file; only the thread that pays for them differs.

A checkpoint that fails (the disk full, an I/O error) leaves the log whole
(what was committed stays in it, and a reader recovers it from there), but it
is the first sign that the file's disk no longer takes writes: the checkpoint
needs the file to grow while the log still has room. ``Checkpointer.failed``
says so from the first failure until a checkpoint succeeds again; its owner
decides what that means (``baton.durability``), and the thread logs nothing
itself.
"""

from __future__ import annotations

import contextlib
import os
import resource
import sqlite3
import threading
import time
from pathlib import Path

# How often the checkpoint thread copies the log into the file, if anything was written.
CHECKPOINT_EVERY_S = 0.5
# How long closing waits for a checkpoint in progress before it lets the thread go.
CLOSE_WAIT_S = 5.0


class Checkpointer:
    """Checkpoints one WAL file from a thread of its own, on its own connection."""

    def __init__(self, path: Path, every_s: float = CHECKPOINT_EVERY_S) -> None:
        self.path = path
        self.every_s = every_s
        # Checkpoints that copied the whole log into the file (for tests).
        self.complete = 0
        # The error of the last checkpoint, while checkpoints fail ("" once one succeeds),
        # and when the first of those failures happened (Unix seconds).
        self.failed = ""
        self.failed_at = 0.0
        self._stopping = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name=f"checkpoint {path.name}", daemon=True
        )
        self._thread.start()

    def close(self) -> None:
        """Stops the thread after its checkpoint in progress, if any (the file's last
        connection to close checkpoints what is left)."""
        self._stopping.set()
        self._thread.join(CLOSE_WAIT_S)

    def _run(self) -> None:
        db = sqlite3.connect(self.path, isolation_level=None)
        try:
            # ``data_version`` changes when another connection commits: nothing
            # new, no checkpoint.
            seen = None
            while not self._stopping.wait(self.every_s):
                try:
                    (version,) = db.execute("PRAGMA data_version").fetchone()
                    if version == seen:
                        continue
                    busy, frames, copied = db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
                except sqlite3.Error as exc:
                    # The log keeps what was written; the next period tries again.
                    if not self.failed:
                        self.failed_at = time.time()
                    self.failed = describe_write_error(self.path, exc)
                    continue
                self.failed = ""
                if busy or copied < frames:
                    continue  # a reader held part of it back: again next period
                seen = version
                if frames:
                    self.complete += 1
        finally:
            db.close()


def open_wal(path: Path) -> tuple[sqlite3.Connection, Checkpointer]:
    """Opens (creating) ``path`` in WAL mode, ``synchronous=NORMAL``, with its
    checkpoints on their own thread. Raises sqlite3.Error or OSError."""
    db = sqlite3.connect(path, isolation_level=None)
    try:
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA synchronous=NORMAL")
        db.execute("PRAGMA wal_autocheckpoint=0")
    except sqlite3.Error:
        db.close()
        raise
    return db, Checkpointer(path)


def roll_back(db: sqlite3.Connection) -> None:
    """Ends the transaction a failed write left open, if SQLite did not end it itself
    (it rolls back on its own after some I/O errors)."""
    if db.in_transaction:
        with contextlib.suppress(sqlite3.Error):
            db.execute("ROLLBACK")


def describe_write_error(path: Path | None, exc: BaseException) -> str:
    """A failed write's error for a person: SQLite's words and code, then what the
    operating system says about the file's disk (SQLite does not pass the errno on)."""
    text = str(exc)
    code = getattr(exc, "sqlite_errorname", "")  # set by SQLite, not on errors made up
    if code:
        text += f" ({code})"
    if path is None:
        return text
    facts = []
    try:
        disk = os.statvfs(path.parent)
        facts.append(f"{disk.f_bavail * disk.f_frsize} bytes free on its disk")
    except OSError:
        pass
    if not os.access(path.parent, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        facts.append("the file or its folder is read-only")
    limit, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
    if limit != resource.RLIM_INFINITY:
        facts.append(f"this process may write files only up to {limit} bytes (RLIMIT_FSIZE)")
    return text + (f": {', '.join(facts)}" if facts else "")

"""The WAL files' checkpoints run on their own thread, never in a commit (baton.wal)."""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

from waiting import eventually

from baton.controller.history import LogHistory
from baton.drone.store import DroneStore
from baton.v1 import ring_pb2
from baton.wal import Checkpointer, open_wal

MB = 1 << 20


def _write(db: sqlite3.Connection, first: int, megabytes: int) -> None:
    db.execute("CREATE TABLE IF NOT EXISTS blobs (n INTEGER PRIMARY KEY, data BLOB)")
    for n in range(first, first + megabytes):
        db.execute("INSERT INTO blobs VALUES (?, ?)", (n, os.urandom(MB)))


def _size(path: Path) -> int:
    return path.stat().st_size if path.exists() else 0


def test_a_commit_never_checkpoints(tmp_path: Path) -> None:
    """SQLite's own checkpoint would copy the log into the file inside the commit
    that takes it past 4 MB (on the event loop); with open_wal no commit does."""
    path = tmp_path / "state.sqlite"
    db, checkpointer = open_wal(path)
    checkpointer.close()  # nobody checkpoints now: only a commit could
    _write(db, 0, 8)
    assert _size(path) < MB, "a commit copied the log into the file"
    assert _size(Path(f"{path}-wal")) > 8 * MB
    (rows,) = db.execute("SELECT COUNT(*) FROM blobs").fetchone()
    assert rows == 8
    db.close()


async def test_the_thread_checkpoints_and_the_log_is_used_again(tmp_path: Path) -> None:
    path = tmp_path / "state.sqlite"
    db, default = open_wal(path)
    default.close()
    checkpointer = Checkpointer(path, every_s=0.02)
    try:
        _write(db, 0, 6)
        await eventually(lambda: _size(path) >= 6 * MB, "the thread to copy 6 MB into the file")
    finally:
        checkpointer.close()  # after the checkpoint in progress
    assert checkpointer.complete
    # The log was copied whole: the writer's next commit starts it from its
    # beginning again, so the file holds about one batch, not both (12 MB).
    _write(db, 6, 6)
    assert _size(Path(f"{path}-wal")) <= 7 * MB
    checkpointer = Checkpointer(path, every_s=0.02)
    try:
        await eventually(lambda: _size(path) >= 12 * MB, "the thread to copy 6 MB more")
    finally:
        checkpointer.close()
        db.close()


def test_a_reopened_file_holds_what_was_committed_before_any_checkpoint(tmp_path: Path) -> None:
    """What a commit put in the log is there for the next process (a kill -9 before
    the thread's checkpoint loses nothing)."""
    path = tmp_path / "log.sqlite"
    history = LogHistory(path)
    history.add(ring_pb2.LogMessage(lognr=1, epoch=1))
    # No close: the process "dies" with its log unchecked.
    again = LogHistory(path)
    assert again.holds_lognr == 1
    again.close()
    history.close()


def test_the_stores_stop_their_threads_on_close(tmp_path: Path) -> None:
    store = DroneStore(tmp_path / "drone.sqlite")
    history = LogHistory(tmp_path / "log.sqlite")
    threads = {store._checkpointer._thread, history._checkpointer._thread}  # type: ignore[union-attr]
    assert all(thread.is_alive() for thread in threads)
    store.close()
    history.close()
    assert not any(thread.is_alive() for thread in threads)

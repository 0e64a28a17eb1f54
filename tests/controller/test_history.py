"""The controller's log history: on disk, recovered from its file, handover flags cleared."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from helpers.storage import failing_writes

from baton.controller.history import LogHistory, read_saved_log
from baton.v1 import ring_pb2


def message(lognr: int, handover: bool = False) -> ring_pb2.LogMessage:
    entry = ring_pb2.LogEntry(reqnr=lognr, method="/baton.v1.Camera/TakePicture", reply=b"p" * 999)
    return ring_pb2.LogMessage(lognr=lognr, origin=1, handover=handover, entries=[entry])


def test_a_log_file_is_recovered_whole_by_the_next_process(tmp_path: Path) -> None:
    path = tmp_path / "controller-1-log.sqlite"
    history = LogHistory(path)
    for lognr in (1, 2, 4):
        history.add(message(lognr))
    history.add(message(3, handover=True))
    history.add(ring_pb2.LogMessage(lognr=2, origin=9))  # a number held already: ignored
    history.close()
    again = LogHistory(path)
    assert (len(again), again.holds_lognr, list(again.above(1))) == (4, 4, [2, 3, 4])
    assert again.get(2) == message(2)
    assert again.get(3) == message(3)  # handover cleared: replayed history makes no master
    with pytest.raises(KeyError):
        again.get(5)
    again.close()


def test_without_a_file_the_history_leaves_nothing_behind(tmp_path: Path) -> None:
    tempfile.tempdir = str(tmp_path)
    try:
        history = LogHistory()
        history.add(message(1))
        assert history.get(1) == message(1) and history.path is None
        assert list(tmp_path.iterdir()) == []  # unlinked as soon as it was open
        history.close()
    finally:
        tempfile.tempdir = None


def test_an_unusable_log_file_names_itself_and_the_flag(tmp_path: Path) -> None:
    (tmp_path / "not-a-db").write_text("hello, I am text")
    with pytest.raises(OSError, match=r"not-a-db \(--log-file\).*give a writable path"):
        LogHistory(tmp_path / "not-a-db")


def test_the_mastership_epoch_is_kept_with_the_log_and_cleared_with_it(tmp_path: Path) -> None:
    """What a controller restarted from its file tells the drone on Connect: the drone
    fences it if a takeover gave that mastership's log up while it was down."""
    path = tmp_path / "controller-0-log.sqlite"
    history = LogHistory(path)
    assert history.mastership_epoch == 0
    history.add(message(1))
    history.keep_mastership_epoch(3)
    history.close()
    again = LogHistory(path)
    assert again.mastership_epoch == 3
    again.clear()  # fenced: rejoins with nothing
    assert again.mastership_epoch == 0
    again.close()
    assert LogHistory(path).mastership_epoch == 0


def test_a_message_dropped_unhandled_is_forgotten_only_in_its_epoch() -> None:
    """protocol.py Unqueued: a queued message of a replaced framing leaves the history,
    unless the ring's (newer) message with its number took its place meanwhile."""
    history = LogHistory()
    for lognr in (1, 2, 3):
        history.add(message(lognr))
    stale = message(4)
    stale.epoch = 4
    history.add(stale)
    history.discard(4, 6)  # another epoch: kept
    assert history.holds_lognr == 4
    history.discard(2, 0)
    assert (history.holds_lognr, list(history.above(0))) == (1, [1, 3, 4])
    history.add(message(2))
    assert history.holds_lognr == 4
    history.close()


def test_a_failed_write_ends_the_files_durability_once_and_keeps_later_messages_in_memory(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The first failed write is an ERROR naming the file, the write and the error; the
    file is marked whole up to the messages it had, nothing more is written to it (not
    even once writes succeed again: a gap would follow), and the controller still holds
    and gives every message, from memory."""
    path = tmp_path / "controller-1-log.sqlite"
    history = LogHistory(path)
    for lognr in (1, 2, 3):
        history.add(message(lognr))
    disk = failing_writes(history)
    disk.failing = "INTO messages"  # the mark, a small write to meta, still fits
    with caplog.at_level(logging.ERROR):
        for lognr in (4, 5):
            history.add(message(lognr))
    [error] = [r for r in caplog.records if r.levelno == logging.ERROR]
    assert f"cannot write {path}: log message 4 failed: database or disk is full" in (
        error.getMessage()
    )
    assert "the file holds log messages 1-3 whole" in error.getMessage()
    status = history.status()
    assert (status.durable, status.whole_up_to_lognr, status.failures) == (False, 3, 1)
    assert status.failed_write == "log message 4"
    disk.failing = None
    history.add(message(6))
    assert (history.holds_lognr, history.get(5), history.get(6)) == (6, message(5), message(6))
    assert disk.failed == 1  # nothing tried after the first failure
    history.close()
    saved = read_saved_log(path)
    assert (saved.whole_up_to, [m.lognr for m in saved.messages]) == (3, [1, 2, 3])


def test_a_restarted_controller_that_cannot_write_its_file_says_so_at_start(
    tmp_path: Path,
) -> None:
    """In a process whose files may not grow past 32 KiB (RLIMIT_FSIZE, as on a disk
    with that little room: SQLite's shared-memory file fits, its log does not), the
    log file's probe write fails: the ERROR comes at start, before any message, and
    the controller holds what the file held."""
    path = tmp_path / "controller-1-log.sqlite"
    history = LogHistory(path)
    history.add(message(1))
    history.close()
    probe = (
        "import resource, sys\n"
        "from baton.controller.history import LogHistory\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (32768, resource.RLIM_INFINITY))\n"
        f"h = LogHistory({str(path)!r})\n"
        "print(h.health.durable, h.health.failed_write, h.holds_lognr, sep='|')\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "False|the start's probe write|1"
    assert f"cannot write {path}: the start's probe write failed" in result.stdout + result.stderr


def test_a_failed_checkpoint_is_the_files_failure_said_within_a_second(tmp_path: Path) -> None:
    """On a disk that fills (RLIMIT_FSIZE in a process of its own: 600 kB, room for the
    write-ahead log's use between checkpoints, the start's probe included), the
    checkpoint that must grow the file usually fails first while the log still takes
    messages: that failure, seen on the checkpoint's thread, ends durability at the next
    write or poll (the controller polls every 0.5 s); the ERROR says how late it came, and
    the file read afterwards holds every message up to the stated one. On a loaded
    machine the checkpoint may lag and a message's own insert fail first (the
    write-ahead log reached the limit): then durability ends at that message, and the
    file holds every one before it (a CI run: message 11 failed, 10 whole)."""
    path = tmp_path / "controller-1-log.sqlite"
    script = (
        "import json, resource, time\n"
        "from baton.controller.history import LogHistory\n"
        "from baton.logs import configure\n"
        "from baton.v1 import ring_pb2\n"
        "configure()\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (600_000, resource.RLIM_INFINITY))\n"
        f"h = LogHistory({str(path)!r})\n"
        "n = 0\n"
        "while h.health.durable and n < 80:\n"
        "    n += 1\n"
        "    entry = ring_pb2.LogEntry(reqnr=n, reply=bytes(30_000))\n"
        "    h.add(ring_pb2.LogMessage(lognr=n, entries=[entry]))\n"
        "    time.sleep(0.25)\n"
        "    h.poll()\n"
        "print(json.dumps([h.health.failed_write, h.health.whole_up_to, n]))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    *logged, last = (result.stderr + result.stdout).strip().splitlines()
    failed_write, whole, added = json.loads(last)
    if failed_write == "a checkpoint":
        assert whole == added, result.stdout
    else:
        assert (failed_write, whole) == (f"log message {added}", added - 1), result.stdout
    [error] = [json.loads(line) for line in logged if '"level": "error"' in line]
    assert "RLIMIT_FSIZE" in error["error"] and error["said_after_s"] < 1.0, error
    saved = read_saved_log(path)
    assert (saved.whole_up_to, len(saved.messages)) == (whole, whole)

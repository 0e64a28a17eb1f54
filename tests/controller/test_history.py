"""The controller's log history: on disk, recovered from its file, handover flags cleared."""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest

from baton.controller.history import LogHistory
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

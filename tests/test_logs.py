"""The JSON log lines: where they go."""

from __future__ import annotations

import io
import json
import logging
import sys

import pytest

from baton import logs


def test_log_lines_go_to_stderr_as_it_is_when_each_is_written(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A thread that logs after the stderr it was configured with has closed (a test
    harness swaps stderr per test; the sim vehicle's thread printed "--- Logging
    error --- I/O operation on closed file" in the test suite's output)."""
    root = logging.getLogger("baton")
    monkeypatch.setattr(root, "handlers", list(root.handlers))
    monkeypatch.setattr(root, "level", root.level)
    first = io.StringIO()
    monkeypatch.setattr(sys, "stderr", first)
    logs.configure()
    first.close()
    second = io.StringIO()
    monkeypatch.setattr(sys, "stderr", second)
    logs.get_logger("test").info("vehicle state", armed=False)
    line = json.loads(second.getvalue())
    assert (line["msg"], line["armed"]) == ("vehicle state", False)

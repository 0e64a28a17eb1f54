"""A SQLite connection whose writes fail on demand, as on a full disk (unit tests of the
files' owners; the real fault across processes is ``baton testbed --fault full:...``)."""

from __future__ import annotations

import sqlite3
from typing import Any

WRITES = ("INSERT", "DELETE", "UPDATE", "REPLACE")


class FailingWrites:
    """Forwards to ``db``; while ``failing`` is set, a write whose SQL contains it (any
    write for "") raises SQLITE_FULL's error, as SQLite does on a full disk."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self.db = db
        self.failing: str | None = None
        self.failed = 0

    def _check(self, sql: str) -> None:
        if self.failing is None or not sql.lstrip().upper().startswith(WRITES):
            return
        if self.failing in sql:
            self.failed += 1
            raise sqlite3.OperationalError("database or disk is full")

    def execute(self, sql: str, params: Any = ()) -> sqlite3.Cursor:
        self._check(sql)
        return self.db.execute(sql, params)

    def executemany(self, sql: str, rows: Any) -> sqlite3.Cursor:
        self._check(sql)
        return self.db.executemany(sql, rows)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.db, name)


def failing_writes(owner: object) -> FailingWrites:
    """Puts a ``FailingWrites`` between ``owner`` (a LogHistory, a DroneStore) and its file."""
    wrapper = FailingWrites(owner._db)  # type: ignore[attr-defined]
    owner._db = wrapper  # type: ignore[attr-defined]
    return wrapper

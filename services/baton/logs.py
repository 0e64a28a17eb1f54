"""Structured logs: one JSON object a line on stderr.

Every service logs through ``get_logger(component)``; a controller binds its
id, state, reqnr and lognr with ``bind`` so that each line carries them.
"""

from __future__ import annotations

import json
import logging
import sys
from collections.abc import Callable, Mapping
from typing import Any


class JsonFormatter(logging.Formatter):
    """Formats a record as one JSON line with its bound fields."""

    def format(self, record: logging.LogRecord) -> str:
        line: dict[str, Any] = {
            "ts": round(record.created, 6),
            "level": record.levelname.lower(),
            "component": record.name.removeprefix("baton."),
            "msg": record.getMessage(),
        }
        fields = getattr(record, "fields", None)
        if fields:
            line.update(fields)
        if record.exc_info:
            line["exc"] = self.formatException(record.exc_info)
        return json.dumps(line, default=str)


class _StderrHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """Writes to ``sys.stderr`` as it is when each line is written, not as it was when
    logging was configured: a thread (the sim vehicle's) may log after a test harness
    closed the stderr of the test that configured it."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property  # type: ignore[override]
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, value: Any) -> None:
        pass


def configure(level: str = "info") -> None:
    """Sends every baton log line, as JSON, to stderr."""
    handler = _StderrHandler()
    handler.setFormatter(JsonFormatter())
    root = logging.getLogger("baton")
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    root.propagate = False


class BoundLogger:
    """A logger that adds fields (static or computed at each call) to every line."""

    def __init__(
        self,
        logger: logging.Logger,
        fields: Mapping[str, Any] | None = None,
        context: Callable[[], Mapping[str, Any]] | None = None,
    ) -> None:
        self._logger = logger
        self._fields = dict(fields or {})
        self._context = context

    def bind(
        self, context: Callable[[], Mapping[str, Any]] | None = None, **fields: Any
    ) -> BoundLogger:
        """A logger with more fields; ``context`` is called on every line."""
        return BoundLogger(self._logger, {**self._fields, **fields}, context or self._context)

    def _log(self, level: int, msg: str, fields: Mapping[str, Any], exc_info: bool) -> None:
        if not self._logger.isEnabledFor(level):
            return
        merged = dict(self._fields)
        if self._context is not None:
            merged.update(self._context())
        merged.update(fields)
        self._logger.log(level, msg, extra={"fields": merged}, exc_info=exc_info)

    def debug(self, msg: str, **fields: Any) -> None:
        """Logs at debug level."""
        self._log(logging.DEBUG, msg, fields, False)

    def info(self, msg: str, **fields: Any) -> None:
        """Logs at info level."""
        self._log(logging.INFO, msg, fields, False)

    def warning(self, msg: str, **fields: Any) -> None:
        """Logs at warning level."""
        self._log(logging.WARNING, msg, fields, False)

    def error(self, msg: str, exc_info: bool = False, **fields: Any) -> None:
        """Logs at error level, with the current exception if ``exc_info``."""
        self._log(logging.ERROR, msg, fields, exc_info)


def get_logger(component: str, **fields: Any) -> BoundLogger:
    """The structured logger of one component (``drone``, ``controller``, ...)."""
    return BoundLogger(logging.getLogger(f"baton.{component}"), fields)

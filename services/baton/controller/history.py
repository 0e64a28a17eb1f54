"""Every log message a controller holds, on disk: what a restarted successor is given again.

Every controller sees every log number (it received the message, or created
it), so each one can give its successor the whole log again when the
successor comes back with nothing (docs/design.md, "Restarts and catch-up").
The messages are kept in an unnamed temporary file, written once as they
arrive; memory holds an index of a few numbers per message, not the
messages (a mission's pictures would be 100 MB and more in every
controller). The file goes with the process: a restarted controller starts
with nothing and catches up from its predecessor's history.

A message is kept as a normal ring message (``handover`` cleared): history
re-sent to a restarted controller never makes it master; only the drone's
grant or a handover message still owed to it does.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator

from baton.controller.protocol import SeenNumbers
from baton.v1 import ring_pb2


class LogHistory:
    """Log messages by log number, in a temporary file; ``holds_lognr`` is the contiguous top."""

    def __init__(self, directory: str | None = None) -> None:
        self._file = tempfile.TemporaryFile(dir=directory)  # lives as long as the node
        self._index: dict[int, tuple[int, int]] = {}  # lognr -> (offset, length)
        self._held = SeenNumbers()
        self.bytes = 0

    def close(self) -> None:
        """Drops the file."""
        self._file.close()

    def __contains__(self, lognr: object) -> bool:
        return lognr in self._index

    def __len__(self) -> int:
        return len(self._index)

    @property
    def holds_lognr(self) -> int:
        """Every log number up to this one is held."""
        return self._held.upto

    def add(self, message: ring_pb2.LogMessage) -> None:
        """Keeps ``message`` unless a message with its log number is held already."""
        if message.lognr in self._index:
            return
        if message.handover:
            kept = ring_pb2.LogMessage()
            kept.CopyFrom(message)
            kept.handover = False
            message = kept
        data = message.SerializeToString()
        self._file.seek(0, os.SEEK_END)
        offset = self._file.tell()
        self._file.write(data)
        self._index[message.lognr] = (offset, len(data))
        self._held.add(message.lognr)
        self.bytes += len(data)

    def get(self, lognr: int) -> ring_pb2.LogMessage:
        """The message with ``lognr``; KeyError if it is not held."""
        offset, length = self._index[lognr]
        self._file.seek(offset)
        return ring_pb2.LogMessage.FromString(self._file.read(length))

    def above(self, lognr: int) -> Iterator[int]:
        """The held log numbers above ``lognr``, in order."""
        return iter(sorted(n for n in self._index if n > lognr))

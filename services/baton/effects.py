"""Side effects counted where they happen: one append-only JSON-lines file per part.

The drone's audit says what the drone service believes it did. A skeptic's
exactly-once check counts instead where the effect happens: the sim vehicle
writes one line per command it acted on, the drone's camera one per picture
it produced (docs/design.md, "Counting side effects where they happen"). The
testbed reads the files into its snapshots (``read_effects``) and the report
checks them against the mission (``baton.testbed.report.check_side_effects``).

Each line is one JSON object: ``seq`` (1, 2, ... per file, continued by a
process restarted on the same file), ``time`` (Unix seconds, wall clock),
``effect`` (what was done) and the effect's own fields. A line is written and
flushed in one ``write`` as soon as the effect happened, so a process that is
SIGSTOPped or killed leaves on disk every effect it produced (the kernel
holds what was written; a power cut may lose the tail, as for the drone's
state). The file is opened for each line and closed again: nothing is held
open, and two objects in one process may share a path through one
``EffectsFile`` (it serialises its writers).
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any


class EffectsFile:
    """Appends one line per effect to ``path``; with no path, only counts in memory.

    A path that cannot be written is an OSError at once, naming the file and
    ``flag`` (the program's one-line error), not a failure at the first effect.
    """

    def __init__(self, path: str | Path | None, flag: str = "--effects-file") -> None:
        self.path = Path(path) if path is not None else None
        self._lock = threading.Lock()
        self.seq = 0  # the last sequence number given out
        if self.path is None:
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with self.path.open("a", encoding="utf-8"):
                pass
        except OSError as exc:
            raise OSError(
                f"effects file {self.path} ({flag}): {exc.strerror or exc}; give a writable path"
            ) from exc
        self.seq = max((e["seq"] for e in read_effects(self.path)), default=0)
        self._end_a_torn_line(self.path)

    @staticmethod
    def _end_a_torn_line(path: Path) -> None:
        """Ends a last line cut short by a kill, so the next line starts on its own."""
        with path.open("rb") as existing:
            if existing.seek(0, 2) == 0:
                return
            existing.seek(-1, 2)
            torn = existing.read(1) != b"\n"
        if torn:
            with path.open("ab") as out:
                out.write(b"\n")

    def record(self, effect: str, **fields: Any) -> int:
        """Records one effect that has just happened; returns its sequence number."""
        with self._lock:
            self.seq += 1
            if self.path is not None:
                line = {"seq": self.seq, "time": round(time.time(), 6), "effect": effect, **fields}
                self.path.parent.mkdir(parents=True, exist_ok=True)
                with self.path.open("a", encoding="utf-8") as out:
                    out.write(json.dumps(line) + "\n")
            return self.seq


def read_effects(path: str | Path) -> list[dict[str, Any]]:
    """Every effect recorded in ``path``, in order; [] if there is no file yet.

    A line that is not a whole JSON object with a ``seq`` (the tail of a
    process killed while writing) is skipped.
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        return []
    effects = []
    for line in text.splitlines():
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        if isinstance(entry, dict) and isinstance(entry.get("seq"), int):
            effects.append(entry)
    return effects

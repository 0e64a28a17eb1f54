"""The testbed's view of every part's waits: expected ones quietly, stalls loudly. Pure.

Each part judges its own waits (GetStatus ``waits``, stalls.py): a station
that is not master has no stream to the drone while the vehicle is out of its
range, as the policy plans; a new master catches up with the ring within its
bound; everything else needs a person. The progress line names the expected
ones once ("out of range, as planned: c0, c3") and each that needs a person
after "NEEDS A PERSON", with its text and age; ``WaitLog`` keeps both for the
report. An operator who sees "NEEDS A PERSON" must look: that is what it is for.

The controller cannot see where the vehicle is, the drone can: when the drone
waits for a station's link (the vehicle is in its range), that station is not
shown as out of range, whatever the station says.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from baton.v1 import drone_pb2, ring_pb2, waits_pb2

# How an expected wait is named on the progress line and in the report, by key.
EXPECTED_LABELS = {
    "standby": "out of range",
    "drone": "out of range",
    "catch-up": "catching up",
    "link": "link coming up",
    "start": "controllers starting",
}
LOUD = "NEEDS A PERSON"


@dataclass(frozen=True)
class PartWait:
    """One part's wait: ``part`` is "drone" or "c<id>"."""

    part: str
    wait: waits_pb2.Wait

    @property
    def label(self) -> str:
        """The expected wait's short name ("out of range")."""
        kind = self.wait.key.split(" ")[0]
        return EXPECTED_LABELS.get(kind, kind)

    def shown(self) -> str:
        """The wait that needs a person, for the progress line and the report."""
        return f"{self.part}: {self.wait.text} for {self.wait.age_s:.0f} s"


def part_waits(
    drone: drone_pb2.DroneStatus, controllers: Mapping[int, ring_pb2.ControllerStatus]
) -> list[PartWait]:
    """Every part's waits, the drone's first; a station's "no standby stream" is
    dropped when the drone waits for that station's link (the vehicle is in its
    range: the drone's wait says so)."""
    drone_waits = [PartWait("drone", w) for w in drone.waits]
    in_range = {w.wait.key.split(" ")[1] for w in drone_waits if w.wait.key.startswith("link ")}
    waits = list(drone_waits)
    for cid, status in sorted(controllers.items()):
        for w in status.waits:
            if w.key in ("standby", "drone") and not w.needs_person and str(cid) in in_range:
                continue
            waits.append(PartWait(f"c{cid}", w))
    return waits


def waits_line(waits: Iterable[PartWait]) -> str:
    """The progress line's part about waits: each expected kind once with the parts
    ("| out of range, as planned: c0, c3"), then every wait that needs a person
    ("| NEEDS A PERSON: c1: ring stream to controller 2 down ... for 5 s")."""
    expected: dict[str, list[str]] = {}
    loud = []
    for w in waits:
        if w.wait.needs_person:
            loud.append(w.shown())
        else:
            parts = expected.setdefault(w.label, [])
            if w.part not in parts:
                parts.append(w.part)
    line = "".join(f" | {label}, as planned: {', '.join(p)}" for label, p in expected.items())
    return line + (f" | {LOUD}: {'; '.join(loud)}" if loud else "")


class WaitLog:
    """The waits seen over a run, for the report: each that needed a person once by
    part and key, each expected one once by part and label ("c3 out of range"), with
    the longest age seen and when it was first seen."""

    def __init__(self) -> None:
        self._seen: dict[tuple[str, str, bool], dict[str, Any]] = {}

    def add(self, waits: Iterable[PartWait], at_s: float) -> None:
        """The waits of one snapshot, ``at_s`` seconds into the run."""
        for w in waits:
            loud = w.wait.needs_person
            key = (w.part, w.wait.key if loud else w.label, loud)
            entry = self._seen.setdefault(
                key,
                {"part": w.part, "key": w.wait.key, "first_s": round(at_s, 1), "longest_s": 0.0},
            )
            entry["text"] = w.wait.text if loud else w.label
            entry["longest_s"] = max(entry["longest_s"], round(w.wait.age_s, 1))

    def to_json(self) -> dict[str, list[dict[str, Any]]]:
        """``needs_person`` and ``expected``, each in the order first seen."""
        seen = self._seen.items()
        return {
            "needs_person": [entry for (_, _, loud), entry in seen if loud],
            "expected": [entry for (_, _, loud), entry in seen if not loud],
        }


def needed_a_person(waits: dict[str, list[dict[str, Any]]]) -> list[str]:
    """Each wait of the report that needed a person, in words."""
    return [
        f"{e['part']}: {e['text']} (up to {e['longest_s']:.0f} s, "
        f"first seen {e['first_s']:.0f} s into the run)"
        for e in waits["needs_person"]
    ]


def report_lines(waits: dict[str, list[dict[str, Any]]]) -> list[str]:
    """The report's lines about waits: the expected ones in one quiet line, then each
    that needed a person on its own line, loudly."""
    lines = []
    if waits["expected"]:
        seen = ", ".join(
            f"{e['part']} {e['text']} (up to {e['longest_s']:.0f} s)" for e in waits["expected"]
        )
        lines.append(f"expected waits: {seen}")
    return lines + [f"{LOUD}: {line}" for line in needed_a_person(waits)]

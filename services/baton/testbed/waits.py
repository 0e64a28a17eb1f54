"""Which of a controller's waits are expected and which need a person. Pure.

A controller's GetStatus ``waiting`` lists its stalls ("; "-separated, each
ending "for N s"). Some are the design at work: with radio range, a station
the vehicle is out of range of has no stream to the drone, by the same map
the drone's handover policy uses (its ``location`` and ``range_m``), and the
drone could not make it master anyway. Those are shown as expected, never as
a warning; every other wait (a stream that should be up and is not, a log
message that does not come, a request without an answer) is a warning. An
operator who sees a warning must look: that is what it is for.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from baton.config import BatonConfig
from baton.link.radio import RadioRange

# The waits that mean "no link to the drone", which radio range explains.
LINK_TO_DRONE = ("no standby stream to the drone", "no Connect stream to the drone")


@dataclass(frozen=True)
class Waits:
    """One controller's waits, sorted: ``expected`` by design, ``warnings`` for a person."""

    expected: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def out_of_range(config: BatonConfig, cid: int, position: tuple[float, float] | None) -> bool:
    """The vehicle at ``position`` (latitude, longitude; None: unknown) is out of radio
    range of controller ``cid``, on the map the handover policy uses."""
    if not config.radio_range or position is None:
        return False
    station = config.controller(cid)
    if station.location is None or station.range_m is None:
        return False
    radio = RadioRange(
        station.location.latitude_deg, station.location.longitude_deg, station.range_m
    )
    return not radio.covers(*position)


def sort_waits(waiting: str, beyond_range: bool) -> Waits:
    """A controller's ``waiting`` text as expected waits and warnings (``beyond_range``:
    the vehicle is out of this controller's radio range)."""
    waits = Waits()
    for wait in (w.strip() for w in waiting.split("; ")):
        if not wait:
            continue
        if beyond_range and wait.startswith(LINK_TO_DRONE):
            waits.expected.append(wait)
        else:
            waits.warnings.append(wait)
    return waits


def waits_line(
    config: BatonConfig | None,
    waiting: dict[int, str],
    position: tuple[float, float] | None,
) -> str:
    """The progress line's part about controllers' waits: the stations out of range by
    design, named once ("out of range, as planned: c0, c3"), then each warning
    ("c1 waiting: ...")."""
    expected, warnings = [], []
    for cid, text in sorted(waiting.items()):
        beyond = config is not None and out_of_range(config, cid, position)
        waits = sort_waits(text, beyond)
        if waits.expected:
            expected.append(f"c{cid}")
        if waits.warnings:
            warnings.append(f" | c{cid} waiting: {'; '.join(waits.warnings)}")
    line = f" | out of range, as planned: {', '.join(expected)}" if expected else ""
    return line + "".join(warnings)

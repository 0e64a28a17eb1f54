"""Radio range for the link emulator: a link that is up only while the vehicle is near.

A controller's link to the drone is a radio: it works while the vehicle is
within the controller's range and not beyond. The local testbed emulates it
with the ground truth, not with anything baton computes: the sim vehicle
writes where it is to a *position file* (``baton sim-vehicle
--position-file``, JSON, rewritten atomically 20 times a second), and the
link emulator in front of the drone for that controller (``baton link
--range LAT,LON,METRES --position-file PATH``) reads it, refuses connections
while the vehicle is out of range and cuts the open ones when it leaves
(docs/design.md, "Radio range in the testbed").

Optionally the link also *fades* (``Fade``, ``--fade BEGINS,LATENCY,FACTOR``):
over the last part of the range, from ``BEGINS`` (a fraction of the range)
to the circle, the one-way latency grows linearly by up to ``LATENCY`` and
the bandwidth falls linearly to ``FACTOR`` of its own, in both directions.
A simple, documented model, not a radio's physics: enough that a link at
the edge of range is slower than one near the station, as a policy that
waits for the last moment would find.

The distance is horizontal, measured as the drone's policy measures it
(``baton.sdk.geo.north_east_m`` from the station), so the two agree on the
circle. A file that is missing or cannot be read means the vehicle's
position is not known: out of range, said in the log. A file that stops
changing is a vehicle that stopped (or was stopped): its last position holds.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

from baton.config import LinkSpec, parse_duration
from baton.lifecycle import write_atomically
from baton.sdk import Position
from baton.sdk.geo import north_east_m

# How often the sim vehicle writes its position file, and the link reads it (wall seconds).
POSITION_PERIOD_S = 0.05


@dataclass(frozen=True)
class RadioRange:
    """A station's antenna and how far it reaches."""

    latitude_deg: float
    longitude_deg: float
    range_m: float

    def distance_m(self, latitude_deg: float, longitude_deg: float) -> float:
        """Horizontal metres from the antenna to a point."""
        origin = Position(self.latitude_deg, self.longitude_deg)
        north, east = north_east_m(origin, Position(latitude_deg, longitude_deg))
        return math.hypot(north, east)

    def covers(self, latitude_deg: float, longitude_deg: float) -> bool:
        """Whether a vehicle there is in range (on the circle counts)."""
        return self.distance_m(latitude_deg, longitude_deg) <= self.range_m


@dataclass(frozen=True)
class Fade:
    """How a link degrades over the last part of a radio's range (the module docstring)."""

    begins: float  # the fraction of the range where fading begins, in [0, 1)
    latency_s: float  # one-way latency added at the circle
    bandwidth_factor: float  # the fraction of the bandwidth left at the circle, in (0, 1]

    def __post_init__(self) -> None:
        if not 0 <= self.begins < 1:
            raise ValueError(
                f"the fade begins at a fraction of the range in [0, 1), got {self.begins!r}"
            )
        if not 0 <= self.latency_s < math.inf:
            raise ValueError(f"the fade's latency must be >= 0 and finite, got {self.latency_s!r}")
        if not 0 < self.bandwidth_factor <= 1:
            raise ValueError(
                f"the fade's bandwidth factor must be in (0, 1], got {self.bandwidth_factor!r}"
            )

    def depth(self, distance_m: float, range_m: float) -> float:
        """0 up to where fading begins, rising linearly to 1 on the circle (and beyond)."""
        return min(1.0, max(0.0, (distance_m / range_m - self.begins) / (1 - self.begins)))

    def spec(self, base: LinkSpec, depth: float) -> LinkSpec:
        """``base`` faded to ``depth``: an unlimited bandwidth stays unlimited."""
        bandwidth = base.bandwidth
        if bandwidth is not None:
            bandwidth *= 1 - depth * (1 - self.bandwidth_factor)
        return LinkSpec(latency=base.latency + depth * self.latency_s, bandwidth=bandwidth)


def parse_fade(text: str) -> Fade:
    """``BEGINS,LATENCY,FACTOR`` like ``0.8,50ms,0.25``; ValueError saying what is wrong."""
    parts = text.split(",")
    example = (
        "like '0.8,50ms,0.25' (from 80% of the range, +50 ms and a quarter of the "
        "bandwidth at the circle)"
    )
    if len(parts) != 3:
        raise ValueError(f"expected BEGINS,LATENCY,FACTOR {example}, got {text!r}")
    try:
        begins, factor = float(parts[0]), float(parts[2])
        latency = parse_duration(parts[1])
    except ValueError as exc:
        raise ValueError(f"expected BEGINS,LATENCY,FACTOR {example}, got {text!r}: {exc}") from None
    return Fade(begins, latency, factor)


def parse_radio_range(text: str) -> RadioRange:
    """``LAT,LON,METRES``; ValueError saying what is wrong."""
    parts = text.split(",")
    try:
        lat, lon, metres = (float(part) for part in parts)
    except ValueError:
        raise ValueError(
            f"expected LAT,LON,METRES like '47.3977,8.5456,500', got {text!r}"
        ) from None
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise ValueError(f"latitude/longitude out of range in {text!r}")
    if not 0 < metres < math.inf:
        raise ValueError(f"the range must be > 0 metres and finite, got {text!r}")
    return RadioRange(lat, lon, metres)


def write_position(
    path: Path, latitude_deg: float, longitude_deg: float, altitude_m: float
) -> None:
    """Writes the vehicle's position file (all of it or nothing, for the readers)."""
    document = {
        "time": time.time(),
        "latitude_deg": latitude_deg,
        "longitude_deg": longitude_deg,
        "relative_altitude_m": altitude_m,
    }
    write_atomically(path, json.dumps(document) + "\n")


def read_position(path: Path) -> tuple[float, float] | None:
    """(latitude, longitude) from the position file; None if missing or unreadable."""
    try:
        document = json.loads(path.read_text())
        return float(document["latitude_deg"]), float(document["longitude_deg"])
    except (OSError, ValueError, KeyError, TypeError):
        return None

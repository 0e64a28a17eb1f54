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

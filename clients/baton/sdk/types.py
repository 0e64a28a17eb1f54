"""Typed results of drone-API calls."""

from __future__ import annotations

from dataclasses import dataclass

from baton.v1 import drone_api_pb2 as api


@dataclass(frozen=True)
class Position:
    """A position: latitude/longitude in degrees, altitudes in metres."""

    latitude_deg: float
    longitude_deg: float
    absolute_altitude_m: float = 0.0
    relative_altitude_m: float = 0.0

    @classmethod
    def from_proto(cls, p: api.Position) -> Position:
        """From the wire message."""
        return cls(p.latitude_deg, p.longitude_deg, p.absolute_altitude_m, p.relative_altitude_m)


@dataclass(frozen=True)
class FlightState:
    """Armed, in air, flight mode, battery, readiness and why not (see drone_api.proto)."""

    armed: bool
    in_air: bool
    flight_mode: str
    landed_state: str
    battery_percent: float
    ready: bool
    armable: bool = False
    not_ready_reason: str = ""
    autopilot_mode: str = ""
    autopilot: str = ""

    @classmethod
    def from_proto(cls, r: api.GetFlightStateReply) -> FlightState:
        """From the wire message."""
        return cls(
            r.armed,
            r.in_air,
            r.flight_mode,
            r.landed_state,
            r.battery_percent,
            r.ready,
            r.armable,
            r.not_ready_reason,
            r.autopilot_mode,
            r.autopilot,
        )


@dataclass(frozen=True)
class Picture:
    """An image from the drone's camera."""

    image: bytes
    format: str
    width: int
    height: int
    position: Position
    sequence: int
    # The region of interest the gimbal pointed at; None: it looked where the vehicle was.
    looking_at: Position | None = None

    @classmethod
    def from_proto(cls, r: api.TakePictureReply) -> Picture:
        """From the wire message."""
        looking_at = Position.from_proto(r.looking_at) if r.HasField("looking_at") else None
        return cls(
            r.image,
            r.format,
            r.width,
            r.height,
            Position.from_proto(r.position),
            r.sequence,
            looking_at,
        )

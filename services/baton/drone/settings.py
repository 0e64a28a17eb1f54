"""What ``baton drone`` runs with: the settings from the model and the flags, and
the parts of the model the drone service takes in its own units (wall seconds)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from baton.config import BatonConfig, controllers_only, detection_time_s
from baton.drone.camera import DEFAULT_RESOLUTION
from baton.drone.core import RESTART_GRACE_S
from baton.drone.dedupe import DEFAULT_WINDOW
from baton.drone.policy import LinkBounds, PolicyParams, Station
from baton.drone.safety import SafetyParams
from baton.drone.sequencer import ScriptedHandover
from baton.rpc.tls import Tls


@dataclass(frozen=True)
class Race:
    """Forces footnote 2's race one way at scripted handovers (fault injection for tests).

    ``notice-first`` holds the reply of the request after which the drone
    hands over, so the old master gets the notice while its call is still in
    flight; ``reply-first`` holds the notice, so the reply is logged first.
    """

    order: str
    delay_s: float


@dataclass(frozen=True)
class DroneSettings:
    """Everything ``baton drone`` runs with: the testbed model (``baton.config``: its
    address, vehicle URL, controllers, master, speed-up, takeover and prepare times;
    the --config file with the flags merged in) and what only the drone's flags give."""

    config: BatonConfig = field(default_factory=lambda: controllers_only([0]))
    handover_script: Mapping[int, ScriptedHandover] = field(default_factory=dict)
    image_file: str | None = None
    resolution: tuple[int, int] = DEFAULT_RESOLUTION
    cache_window: int = DEFAULT_WINDOW
    address_file: str | None = None
    race: Race | None = None
    state_file: str | None = None  # the durable state (store.py); None: memory only
    camera_effects_file: str | None = None  # pictures counted (baton.effects); None: no file
    thumbnails_dir: str | None = None  # a small JPEG of each picture kept here; None: none
    # The drone's certificate (mutual TLS); None: an insecure port open to anyone.
    tls: Tls | None = None
    # The MAVLink signing key (signing.py), read from config.drone.mavlink_key;
    # None: the autopilot link unsigned.
    mavlink_key: bytes | None = None
    # The handover policy (policy.py) and every controller's station; None: the
    # script and the operator only.
    policy: PolicyParams | None = None
    stations: Mapping[int, Station] = field(default_factory=dict)

    @property
    def address(self) -> str:
        """Where the drone serves."""
        return self.config.drone.address

    @property
    def vehicle_url(self) -> str:
        """The autopilot's MAVLink URL."""
        return self.config.drone.vehicle_url

    @property
    def controllers(self) -> tuple[int, ...]:
        """The controllers that may become master, in ring order."""
        return tuple(self.config.ring_order)

    @property
    def master(self) -> int:
        """The initial master: given, else the first controller."""
        return self.config.master_id

    @property
    def speedup(self) -> float:
        """The mission's speed-up."""
        return self.config.speedup

    @property
    def takeover_after(self) -> float:
        """The master is lost after this long without a stream or a request, in
        mission seconds (divided by speedup); 0: never."""
        return self.config.takeover_after

    @property
    def prepare_timeout_s(self) -> float:
        """How long a prepared handover waits for its target (wall seconds)."""
        return self.config.prepare_timeout

    @property
    def link_bounds(self) -> LinkBounds:
        """What a healthy controller link is (GetStatus's links and the log, whatever the
        policy; the policy's are the same, ``drone.cli.handover_policy``)."""
        return link_bounds(self.config)


def link_bounds(config: BatonConfig) -> LinkBounds:
    """The model's bounds of a healthy controller link (``handover_policy.max_rtt`` and
    ``rtt_stale``), as the policy and the link probes take them."""
    return LinkBounds(config.handover_policy.max_rtt, config.handover_policy.rtt_stale)


def safety_params(config: BatonConfig) -> SafetyParams:
    """The model's safety net in wall seconds (mission seconds / speed-up)."""
    safety = config.safety
    return SafetyParams(
        # At least the detection time in wall seconds, as a takeover's (its floor).
        lost_link_s=detection_time_s(safety.lost_link, config.speedup),
        lost_link_action=safety.lost_link_action,
        max_speed_m_s=safety.max_speed,
        max_altitude_m=safety.max_altitude,
        battery_reserve_pct=safety.battery_reserve,
        battery_action=safety.battery_action,
        fence=safety.fence.fence() if safety.fence is not None else None,
    )


def autopilot_gcs_timeout_s(config: BatonConfig) -> float:
    """The autopilot's own GCS failsafe time (its clock: mission seconds): the model's
    ``safety.autopilot_gcs_timeout``, but never shorter than a restart of the drone
    service takes (the restart grace, in wall seconds, times the speed-up), so that a
    restart is not taken for the drone service's death; 0: left alone."""
    configured = config.safety.autopilot_gcs_timeout
    if configured <= 0:
        return 0.0
    return max(configured, RESTART_GRACE_S * config.speedup)


def landing_stations(config: BatonConfig) -> dict[int, Station]:
    """Every controller with a location, as a station to land at (nearest_station)."""
    from baton.sdk.types import Position

    return {
        c.id: Station(c.id, Position(c.location.latitude_deg, c.location.longitude_deg), 0.0)
        for c in config.controllers
        if c.location is not None
    }

"""The testbed configuration: one typed, validated model for every program.

One YAML file lists every endpoint, as the paper's testbed did: the drone
service, the controllers with their ring order, locations and ranges, the
initial master and the flush limit. Programs load it with ``load_config`` and
pass the model down; nothing else reads files or the environment for settings.

Sizes accept units (``2MB``, ``512KiB``, ``0``); MB means 2**20 bytes, as in
docs/design.md's performance model. Rates accept ``25Mbit``; Mbit means 10**6 bits.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StrictInt,
    ValidationError,
    field_validator,
    model_validator,
)

from baton.drone.policy import LinkBounds, PolicyParams
from baton.rpc.mission import MISSION_ID_PATTERN
from baton.rpc.ports import MAX_FRAME_BYTES
from baton.rpc.tls import DRONE_NAME_PATTERN, Identity, Tls
from baton.sdk.fence import Fence, FenceCircle, FencePolygon, open_ring
from baton.sdk.fence import polygon_problem as fence_polygon_problem

_SIZE_UNITS = {
    "": 1,
    "b": 1,
    "k": 2**10,
    "kb": 2**10,
    "kib": 2**10,
    "m": 2**20,
    "mb": 2**20,
    "mib": 2**20,
    "g": 2**30,
    "gb": 2**30,
    "gib": 2**30,
}
_RATE_UNITS = {
    "": 1,
    "bit": 1,
    "bps": 1,
    "kbit": 10**3,
    "kbps": 10**3,
    "mbit": 10**6,
    "mbps": 10**6,
    "gbit": 10**9,
    "gbps": 10**9,
}
_TIME_UNITS = {"": 1.0, "s": 1.0, "ms": 1e-3, "us": 1e-6, "min": 60.0, "h": 3600.0}
_NUMBER_WITH_UNIT = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([a-zA-Z/]*)\s*$")


def _parse_with_units(value: Any, units: dict[str, Any], what: str, example: str) -> float:
    if isinstance(value, bool):
        raise ValueError(f"expected {what} like {example!r}, got {value!r}")
    if isinstance(value, int | float):
        if not math.isfinite(value):
            raise ValueError(f"expected {what} like {example!r}, got {value!r}: it must be finite")
        return float(value)
    match = _NUMBER_WITH_UNIT.match(str(value))
    unit = match.group(2).lower() if match else None
    if match is None or unit not in units:
        known = ", ".join(u for u in units if u)
        raise ValueError(f"expected {what} like {example!r} (units: {known}), got {value!r}")
    number = float(match.group(1)) * units[unit]
    if not math.isfinite(number):
        raise ValueError(f"expected {what} like {example!r}, got {value!r}: it must be finite")
    return number


# The fastest a mission's clock and the sim vehicle may run.
MAX_SPEEDUP = 1000.0

# The longest duration a testbed file or flag may give (a link's latency, a
# timeout): a day. 1e999 used to make a link that never delivers.
MAX_DURATION_S = 86_400.0


def parse_size(value: Any) -> int:
    """Bytes from ``2MB``, ``512KiB``, ``1048576`` or ``0`` (MB = 2**20 bytes)."""
    size = _parse_with_units(value, _SIZE_UNITS, "a size", "2MB")
    if size < 0:
        raise ValueError(f"a size must be >= 0, got {value!r}")
    return int(size)


def parse_rate(value: Any) -> float:
    """Bits per second from ``25Mbit``, ``54Mbps`` or ``25e6``."""
    rate = _parse_with_units(value, _RATE_UNITS, "a bandwidth", "25Mbit")
    if rate <= 0:
        raise ValueError(f"a bandwidth must be > 0, got {value!r}")
    return rate


def parse_duration(value: Any) -> float:
    """Seconds from ``20ms``, ``0.02``, ``1s``."""
    seconds = _parse_with_units(value, _TIME_UNITS, "a duration", "20ms")
    if seconds < 0:
        raise ValueError(f"a duration must be >= 0, got {value!r}")
    if seconds > MAX_DURATION_S:
        raise ValueError(
            f"a duration must be at most a day ({MAX_DURATION_S:g} s), got {value!r}: no link "
            "delay, timeout or takeover time of a mission is longer"
        )
    return seconds


# The detection time never goes below this in wall seconds, however sped up
# the mission: a stream that breaks and is re-opened at once under load (the
# parts re-open within 50 ms to 1 s) must not count as a loss.
DETECTION_FLOOR_S = 1.0


def detection_time_s(takeover_after: float, speedup: float) -> float:
    """Wall seconds after which a master (the drone) or a ring successor (a controller)
    not seen counts as lost: ``takeover_after`` mission seconds, at least
    DETECTION_FLOOR_S; 0 when turned off."""
    if takeover_after <= 0:
        return 0.0
    return max(takeover_after / speedup, DETECTION_FLOOR_S)


# How long a prepared handover waits for its target to catch up before the
# drone forces it (wall seconds; docs/design.md, "Prepared handover").
PREPARE_TIMEOUT_S = 10.0


# The longest a controller waits between two repairs of the same gap (seconds).
GAP_REPAIR_MAX_S = 8.0


def gap_repair_s(detection_s: float) -> float:
    """How long a log message may be missing while later ones are queued before the
    controller has its predecessors re-send from its hello: the detection time, or its
    floor when takeovers are off (``ControllerCore.gap_due``)."""
    return max(detection_s, DETECTION_FLOOR_S)


def parse_address(value: Any) -> str:
    """A ``host:port`` string with a port in 0..65535."""
    text = str(value).strip()
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"expected host:port like '127.0.0.1:7100', got {value!r}")
    return text


Size = Annotated[int, BeforeValidator(parse_size)]
# Room above the flush limit for a log message's last entry (max_log_message),
# and the Reassembler's default bound.
MAX_LOG_MESSAGE_DEFAULT = 256 * 2**20
Rate = Annotated[float, BeforeValidator(parse_rate)]
Duration = Annotated[float, BeforeValidator(parse_duration)]
Address = Annotated[str, BeforeValidator(parse_address)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Location(_Model):
    """A ground location (a controller's antenna, the drone's home)."""

    latitude_deg: float = Field(ge=-90, le=90)
    longitude_deg: float = Field(ge=-180, le=180)
    altitude_m: float = 0.0


class LinkSpec(_Model):
    """Emulated link characteristics, per direction (see ``baton link``)."""

    latency: Duration = 0.0
    bandwidth: Rate | None = None  # None: unlimited

    @property
    def emulated(self) -> bool:
        """Whether this link adds any delay at all."""
        return self.latency > 0 or self.bandwidth is not None


class DroneConfig(_Model):
    """The drone service."""

    address: Address = "127.0.0.1:50051"
    # The drone's name in its certificate, in a fleet where each drone has its own
    # (spiffe://baton/drone/NAME, files drone-NAME.crt/.key); "" for the mission's
    # one drone (spiffe://baton/drone, drone.crt). Its controllers accept no other.
    name: str = Field(default="", pattern=f"^(|{DRONE_NAME_PATTERN})$")
    vehicle_url: str = "udpin://127.0.0.1:14540"
    # MAVLink 2 signing between the drone service and the autopilot (off by
    # default: usually a serial cable on the airframe); a key file made by
    # `baton certs mavlink-key`, relative to the configuration file's folder.
    # The sim vehicle of the testbed checks and signs with the same key.
    mavlink_key: Path | None = None
    home: Location = Location(latitude_deg=47.397742, longitude_deg=8.545594, altitude_m=488.0)
    # Ground stations that watch live: the autopilot's MAVLink is forwarded to each
    # (udp:HOST:PORT, where QGroundControl or MAVProxy listens; drone/gcs.py).
    gcs: list[str] = []
    # A ground station's command is an operator override that pauses the mission
    # (false: refused, watch only).
    gcs_override: bool = False

    @field_validator("gcs")
    @classmethod
    def _gcs_endpoints(cls, value: list[str]) -> list[str]:
        from baton.drone.gcs import GcsEndpoint

        for text in value:
            GcsEndpoint.parse(text)  # ValueError names it and the fix
        return value


class RingConfig(_Model):
    """The ring: its order and how log messages travel along it.

    The testbed file's ``ring`` is either the order alone (``ring: [0, 1, 2]``)
    or this mapping (``ring: {order: [0, 1, 2], forwarding: store-and-forward}``).
    """

    # Ring order by controller id; defaults to the order of ``controllers``.
    order: list[StrictInt] | None = None
    # cut-through: each frame is passed on as it arrives, and a handover's
    # target gets what it lacks straight from the old master (docs/design.md,
    # "The ring's forwarding"); store-and-forward: the paper's protocol, a
    # message is passed on once whole.
    forwarding: Literal["cut-through", "store-and-forward"] = "cut-through"
    # The slice of a log message one frame carries: the per-hop delay of
    # cut-through is one frame's time on the link.
    frame_bytes: Size = Field(default=16 * 2**10, ge=2**10, le=MAX_FRAME_BYTES)

    @property
    def cut_through(self) -> bool:
        """Whether frames are passed on as they arrive."""
        return self.forwarding == "cut-through"


class ControllerConfig(_Model):
    """One mission controller."""

    id: int = Field(ge=0, le=2**31 - 1, strict=True)  # strict: `true` is not 1
    address: Address
    # How the other controllers reach this one (a link emulator in the
    # testbed); defaults to ``address``.
    peer_address: Address | None = None
    # How this controller reaches the drone; defaults to ``drone.address``.
    drone_address: Address | None = None
    # Where its mission program calls the drone API: loopback by default, so
    # that only a program on the same node can (and, with the mission token,
    # only the one it started); port 0 picks a free one.
    mission_address: Address = "127.0.0.1:0"
    location: Location | None = None
    range_m: float | None = Field(default=None, gt=0)

    @property
    def reach(self) -> str:
        """The address peers use for this controller."""
        return self.peer_address or self.address


def _policy_shorthand(value: Any) -> Any:
    """``handover_policy: nearest`` is ``handover_policy: {name: nearest}``."""
    return {"name": value} if isinstance(value, str) else value


_POLICY, _LINK_BOUNDS = PolicyParams(), LinkBounds()


class HandoverPolicyConfig(_Model):
    """The drone's handover policy (docs/design.md, "Range-driven handovers")."""

    # none: only the handover script and the operator move the master (the
    # paper's experiments); nearest or predictive: the drone picks its master
    # from where it is (drone/policy.py).
    name: Literal["none", "nearest", "predictive"] = "none"
    # The thresholds' defaults are the pure policy's (drone/policy.py PolicyParams,
    # LinkBounds): one place each.
    # nearest: hand over once another station is this much nearer...
    margin_m: float = Field(default=_POLICY.margin_m, ge=0, allow_inf_nan=False)
    # ... for this long (mission time).
    dwell: Duration = _POLICY.dwell_s
    # predictive: hand over this long (mission time) before the master's range runs out.
    lead: Duration = _POLICY.lead_s
    # No controller usable, the vehicle flown into a station's range: that
    # station's link has this long (mission time) to come up before the vehicle
    # holds (a controller's reconnect backs off to 1 s of wall time).
    link_up: Duration = _POLICY.link_up_s
    # A controller's link is healthy while its last round trip (the drone's ping
    # on its standby stream, drone/link_probe.py) took at most max_rtt and is at
    # most rtt_stale old; the policy never hands over to one that is not. Wall
    # time: a network does not speed up with the mission. With takeovers on, the
    # drone's keepalive drops a link slower than 2 s anyway. Read by the drone
    # whatever the policy, for GetStatus's links.
    max_rtt: Duration = Field(default=_LINK_BOUNDS.max_rtt_s, gt=0)
    rtt_stale: Duration = Field(default=_LINK_BOUNDS.rtt_stale_s, gt=0)


PolicySetting = Annotated[HandoverPolicyConfig, BeforeValidator(_policy_shorthand)]


class RadioFadeConfig(_Model):
    """A radio link degrading with distance (link/radio.py ``Fade``): from
    ``begins_at`` of a controller's range to its circle, its link to the drone's
    one-way latency grows linearly by up to ``latency`` and its bandwidth falls
    linearly to ``bandwidth_factor`` of the link's own."""

    begins_at: float = Field(default=0.8, ge=0, lt=1)
    latency: Duration = 0.05
    bandwidth_factor: float = Field(default=0.25, gt=0, le=1)

    def link_arg(self) -> str:
        """``baton link --fade``'s value."""
        return f"{self.begins_at},{self.latency}s,{self.bandwidth_factor}"


FailsafeAction = Literal["hold", "land", "rtl", "nearest_station"]


class FencePolygonConfig(_Model):
    """One polygon of the fence: its vertices, ``[latitude, longitude]`` each, in order
    around the area (the first may be repeated last)."""

    vertices: list[list[float]]
    # true: the vehicle stays inside it; false: outside it (a no-fly zone).
    inclusion: bool = True

    @field_validator("vertices")
    @classmethod
    def _a_polygon(cls, vertices: list[list[float]]) -> list[list[float]]:
        problem = fence_polygon_problem(vertices)
        if problem is not None:
            raise ValueError(problem)
        return vertices


class FenceCircleConfig(_Model):
    """One circle of the fence: its ``center`` ``[latitude, longitude]`` and radius."""

    center: list[float] = Field(min_length=2, max_length=2)
    radius: float = Field(gt=0, allow_inf_nan=False)
    inclusion: bool = True

    @field_validator("center")
    @classmethod
    def _a_place(cls, center: list[float]) -> list[float]:
        lat, lon = center
        if not (math.isfinite(lat) and math.isfinite(lon)) or abs(lat) > 90 or abs(lon) > 180:
            raise ValueError(
                f"center {center} is not a place: give [latitude, longitude], latitude in "
                "[-90, 90], longitude in [-180, 180]"
            )
        return center


def _fence_shorthand(value: Any) -> Any:
    """``fence: {polygon: [[lat, lon], ...]}`` is one inclusion polygon of ``polygons``."""
    if isinstance(value, dict) and "polygon" in value:
        value = dict(value)
        polygons = [{"vertices": value.pop("polygon")}, *value.get("polygons", [])]
        value["polygons"] = polygons
    return value


class FenceConfig(_Model):
    """The mission's geofence (drone/fence.py; docs/operating.md, "The safety net"):
    areas the vehicle stays inside (inclusion) or outside of, and a ceiling in metres
    above home. Every Goto outside it is refused; a vehicle found outside is put in
    failsafe with ``action``; it is uploaded to the autopilot before arming."""

    polygons: list[FencePolygonConfig] = []
    circles: list[FenceCircleConfig] = []
    ceiling: float
    # What a breach makes the vehicle do: no hold (a vehicle holding outside its fence
    # stays out), no nearest_station (a station may lie outside it).
    action: Literal["rtl", "land"] = "rtl"

    @field_validator("ceiling")
    @classmethod
    def _a_ceiling(cls, ceiling: float) -> float:
        if not math.isfinite(ceiling) or ceiling <= 0:
            raise ValueError(
                f"the ceiling is {ceiling}: give the metres above home the vehicle may fly "
                "up to, a number > 0 (e.g. 120, the open category's limit)"
            )
        return ceiling

    def fence(self) -> Fence:
        """The pure fence the drone checks and uploads."""
        return Fence(
            tuple(
                FencePolygon(open_ring([(v[0], v[1]) for v in p.vertices]), p.inclusion)
                for p in self.polygons
            ),
            tuple(
                FenceCircle(c.center[0], c.center[1], c.radius, c.inclusion) for c in self.circles
            ),
            self.ceiling,
            self.action,
        )


FenceSetting = Annotated[FenceConfig, BeforeValidator(_fence_shorthand)]


class SafetyConfig(_Model):
    """The operator's safety net at the drone (docs/operating.md, "The safety net").

    Times are mission seconds, like ``takeover_after``. The defaults are chosen
    for a vehicle flying beyond sight of its operator: ``rtl`` after 30 s with
    no usable controller (home is where the vehicle was armed, a place known to
    be clear; a hold only waits for the battery to run out, a landing comes
    down wherever the link was lost), and the limits of a small multicopter
    flown under the open category's 120 m ceiling.
    """

    # No usable controller (no request, no stream) for this long: the failsafe
    # action. 0: never (the vehicle holds and waits, the old behaviour).
    lost_link: Duration = 30.0
    lost_link_action: FailsafeAction = "rtl"
    # Below this battery percentage the mission ends with battery_action; 0: off.
    battery_reserve: float = Field(default=20.0, ge=0, le=100, allow_inf_nan=False)
    battery_action: Literal["land", "rtl", "nearest_station"] = "rtl"
    # The fastest a SetSpeed may ask for and the highest a Takeoff or Goto may
    # fly (metres above home); the autopilot's own maximum, where it says it,
    # is the bound when lower.
    max_speed: float = Field(default=15.0, gt=0, allow_inf_nan=False)
    max_altitude: float = Field(default=120.0, gt=0, allow_inf_nan=False)
    # The longest Clock.Sleep a mission may ask for.
    max_sleep: Duration = 600.0
    # The autopilot's own GCS failsafe, set at connect: if the drone service
    # itself stops talking to the autopilot for this long (seconds of the
    # autopilot's clock), the autopilot returns home. 0: left as it is.
    autopilot_gcs_timeout: Duration = 10.0
    # The mission's geofence (``FenceConfig``); absent: none (a QGroundControl plan's
    # geoFence is the testbed's when it flies one).
    fence: FenceSetting | None = None


class TlsConfig(_Model):
    """Mutual TLS (docs/design.md, Security): where every part finds its certificate."""

    # ca.crt, and NAME.crt and NAME.key per part (baton certs init); a relative
    # folder is read from the configuration file's folder.
    certs: Path = Path("certs")
    # Every port plain and open to anyone on the network: for debugging only,
    # and every program says so when it starts.
    insecure: bool = False


class BatonConfig(_Model):
    """The whole testbed: drone, controllers, ring, protocol parameters."""

    drone: DroneConfig = DroneConfig()
    controllers: list[ControllerConfig] = Field(min_length=1)
    # Ring order and forwarding (``RingConfig``); a list is the order alone.
    ring: RingConfig = RingConfig()
    initial_master: StrictInt | None = None
    flush_limit: Size = 2 * 2**20
    speedup: float = Field(default=1.0, gt=0, le=MAX_SPEEDUP)
    controller_link: LinkSpec = LinkSpec()
    drone_link: LinkSpec = LinkSpec()
    # How long an ACTIVE controller keeps re-sending a request that the drone
    # could not take (drone unreachable, vehicle link down: nothing executed)
    # before the call fails with UNAVAILABLE; wall time.
    drone_retry_limit: Duration = 300.0
    # The drone takes over a master it has not seen (no stream, no request)
    # for this long, in mission seconds (docs/design.md, "Takeover"); 0: never.
    takeover_after: Duration = 3.0
    # How long a prepared handover waits for its target to catch up before the
    # drone forces it (wall seconds; docs/design.md, "Prepared handover").
    prepare_timeout: Duration = Field(default=PREPARE_TIMEOUT_S, gt=0)
    # The largest log message a controller accepts from the ring: the flush
    # limit plus the largest entry (a picture), with room to spare; default
    # flush_limit + 256 MiB (see ``log_message_cap``). A frame claiming more
    # is refused before anything is buffered.
    max_log_message: Size | None = None
    tls: TlsConfig = TlsConfig()
    # Who the drone makes master as it flies (``nearest``, ``predictive``);
    # ``none`` by default: the handover script and the operator only.
    handover_policy: PolicySetting = HandoverPolicyConfig()
    # The local testbed's link emulators carry a controller's link to the drone
    # only while the sim vehicle is within that controller's range_m of its
    # location (link/radio.py); off: every controller reaches the drone anywhere.
    radio_range: bool = False
    # With radio_range: each such link also fades towards the edge of range
    # (latency up, bandwidth down); absent: a link is as good anywhere in range.
    radio_fade: RadioFadeConfig | None = None
    # Lost link, battery reserve and the limits a vehicle can fly (``SafetyConfig``).
    safety: SafetyConfig = SafetyConfig()
    # The mission's id on a station network (``baton station``): a station serves
    # every mission on one port, so each controller's ring streams name the mission
    # (rpc/mission.py, the baton-mission metadata); absent for a controller that
    # serves one mission on a port of its own.
    mission_id: str | None = Field(default=None, pattern=MISSION_ID_PATTERN)

    @field_validator("ring", mode="before")
    @classmethod
    def _ring_order_alone(cls, ring: Any) -> Any:
        return {"order": ring} if isinstance(ring, list) else ring

    @field_validator("controllers")
    @classmethod
    def _unique_ids(cls, controllers: list[ControllerConfig]) -> list[ControllerConfig]:
        seen: set[int] = set()
        for c in controllers:
            if c.id in seen:
                raise ValueError(f"controller id {c.id} appears twice; give each a unique id")
            seen.add(c.id)
        return controllers

    @model_validator(mode="after")
    def _one_part_per_address(self) -> BatonConfig:
        owners: dict[str, str] = {}
        parts = [("the drone", self.drone.address)]
        parts += [(f"controller {c.id}", c.address) for c in self.controllers]
        for owner, address in parts:
            if address.endswith(":0"):
                continue  # port 0: each picks a free port
            if address in owners:
                first = owners[address]
                both = (
                    f"controllers {first.split()[1]} and {owner.split()[1]}"
                    if first.startswith("controller") and owner.startswith("controller")
                    else f"{first} and {owner}"
                )
                raise ValueError(f"{both} both listen on {address}; give each part its own port")
            owners[address] = owner
        return self

    @model_validator(mode="after")
    def _ring_and_master(self) -> BatonConfig:
        ids = [c.id for c in self.controllers]
        order = self.ring.order
        if order is not None and sorted(order) != sorted(ids):
            raise ValueError(
                f"ring {order} must list every controller id exactly once: {sorted(ids)}"
            )
        if self.initial_master is not None and self.initial_master not in ids:
            raise ValueError(
                f"initial_master {self.initial_master} is not a controller id; use one of {ids}"
            )
        placed = [
            (what, fix)
            for what, fix, on in (
                (
                    f"handover_policy {self.handover_policy.name}",
                    "use handover_policy: none",
                    self.handover_policy.name != "none",
                ),
                ("radio_range", "set radio_range: false", self.radio_range),
            )
            if on
        ]
        for what, fix in placed:
            for c in self.controllers:
                if c.location is None or c.range_m is None:
                    missing = "location" if c.location is None else "range_m"
                    raise ValueError(
                        f"{what} needs every controller's location and range_m; controller "
                        f"{c.id} has no {missing}: add it, or {fix}"
                    )
        if self.radio_fade is not None and not self.radio_range:
            raise ValueError(
                "radio_fade fades the radio range's links: set radio_range: true, or drop "
                "radio_fade"
            )
        lost_link = self.safety.lost_link
        if lost_link and self.takeover_after and lost_link <= self.takeover_after:
            raise ValueError(
                f"safety.lost_link ({lost_link:g} s) must be longer than takeover_after "
                f"({self.takeover_after:g} s): a master lost alone is taken over, and only "
                "when no controller is left does the failsafe act; raise safety.lost_link"
            )
        fence = self.safety.fence
        if fence is not None:
            home = self.drone.home
            why = fence.fence().outside(home.latitude_deg, home.longitude_deg)
            if why is not None:
                raise ValueError(
                    f"safety.fence: the mission's start, drone.home ({home.latitude_deg:.7f}, "
                    f"{home.longitude_deg:.7f}), is {why}: the vehicle would take off in "
                    "breach; draw the fence around the home, or fix drone.home"
                )
        if self.max_log_message is not None and self.max_log_message <= self.flush_limit:
            raise ValueError(
                f"max_log_message ({self.max_log_message} bytes) must be above flush_limit "
                f"({self.flush_limit} bytes): a flushed message holds the limit plus one entry"
            )
        return self

    @property
    def log_message_cap(self) -> int:
        """The largest log message accepted from the ring, bytes (max_log_message)."""
        if self.max_log_message is not None:
            return self.max_log_message
        return self.flush_limit + MAX_LOG_MESSAGE_DEFAULT

    @property
    def detection_s(self) -> float:
        """The detection time in wall seconds (``detection_time_s``)."""
        return detection_time_s(self.takeover_after, self.speedup)

    @property
    def ring_order(self) -> list[int]:
        """Controller ids in ring order."""
        order = self.ring.order
        return list(order) if order is not None else [c.id for c in self.controllers]

    @property
    def master_id(self) -> int:
        """The initial master: configured, else the first in ring order (the paper's n_0)."""
        return self.initial_master if self.initial_master is not None else self.ring_order[0]

    @property
    def drone_identity(self) -> Identity:
        """The identity of this mission's drone (``drone.name``)."""
        return Identity.drone(self.drone.name)

    def tls_for(self, identity: Identity) -> Tls | None:
        """The certificate ``identity`` presents, or None when the file says insecure;
        TlsError names the missing file and the fix."""
        if self.tls.insecure:
            return None
        return Tls.load(self.tls.certs, identity)

    def controller(self, cid: int) -> ControllerConfig:
        """The controller with id ``cid``; KeyError naming the known ids otherwise."""
        for c in self.controllers:
            if c.id == cid:
                return c
        raise KeyError(f"no controller with id {cid}; known ids: {self.ring_order}")

    def successor(self, cid: int) -> int:
        """The next controller in the ring (Algorithm 1's nxtid)."""
        order = self.ring_order
        return order[(order.index(cid) + 1) % len(order)]

    def hops(self, src: int, dst: int) -> int:
        """Hops along the ring from ``src`` to ``dst``."""
        order = self.ring_order
        return (order.index(dst) - order.index(src)) % len(order)

    def drone_address_for(self, cid: int) -> str:
        """Where controller ``cid`` reaches the drone."""
        return self.controller(cid).drone_address or self.drone.address


class ConfigError(ValueError):
    """A configuration file that cannot be used; the message names file, field and fix."""


def _field_path(loc: tuple[int | str, ...]) -> str:
    path = ""
    for part in loc:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    return path or "(top level)"


def format_validation_error(source: str, error: ValidationError) -> str:
    """One line per problem: ``FILE: FIELD: what is wrong``."""
    lines = []
    for problem in error.errors():
        field = _field_path(tuple(problem["loc"]))
        msg = problem["msg"].removeprefix("Value error, ")
        if problem["type"] == "extra_forbidden":
            msg = "unknown field; remove it or check its spelling"
        elif problem["type"] == "missing":
            msg = "required field is missing; add it"
        elif problem["type"] == "too_short":
            msg = f"needs at least {problem['ctx']['min_length']} entry; add one"
        lines.append(f"{source}: {field}: {msg}")
    return "\n".join(lines)


def parse_config(data: Any, source: str = "<config>") -> BatonConfig:
    """Validates a parsed YAML document; ConfigError says what to fix."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: (top level): expected a mapping of fields, got {data!r}")
    try:
        return BatonConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(source, exc)) from None


def read_yaml(path: Path, what: str = "configuration file") -> Any:
    """The parsed YAML document of ``path``; ConfigError naming the file otherwise."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the {what}: {exc.strerror}") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None


def load_config(path: str | Path) -> BatonConfig:
    """Reads and validates a testbed YAML file."""
    path = Path(path)
    config = parse_config(read_yaml(path), str(path))
    key = config.drone.mavlink_key
    if key is not None and not key.is_absolute():
        drone = config.drone.model_copy(update={"mavlink_key": path.parent / key})
        config = config.model_copy(update={"drone": drone})
    if config.tls.certs.is_absolute():
        return config
    tls = config.tls.model_copy(update={"certs": path.parent / config.tls.certs})
    return config.model_copy(update={"tls": tls})


def controllers_only(ids: Sequence[int]) -> BatonConfig:
    """The model of a program given controller ids and no file (``baton drone
    --controllers``, ``baton testbed --controllers``): every other field its default.
    Each controller's address is port 0: a program started this way never reaches a
    controller by it (the drone is called, the local testbed picks free ports)."""
    return parse_config({"controllers": [{"id": cid, "address": "127.0.0.1:0"} for cid in ids]})


def merge(
    config: BatonConfig, flags: Iterable[tuple[str, str, Any]], source: str = ""
) -> BatonConfig:
    """``config`` with the flags that were given put in their fields, validated whole.

    The one way a program combines its ``--config`` file with its flags: every flag
    defaults to None ("not given"), so a flag given with the default's value still
    wins over the file. ``flags`` are (flag, field path, value) like ``("--flush-limit",
    "flush_limit", "2MB")``, the path dotted (``controller_link.latency``); a value of
    None is left out. ConfigError names the flag, the value and what to write instead.
    """
    given = [(flag, path, value) for flag, path, value in flags if value is not None]
    if not given:
        return config
    document = config.model_dump(exclude_unset=True)
    for _, path, value in given:
        *parents, name = path.split(".")
        node = document
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):  # a shorthand the model keeps as a mapping
                raise TypeError(f"{path}: {part} is not a mapping")
        node[name] = value
    try:
        return BatonConfig.model_validate(document)
    except ValidationError as exc:
        raise ConfigError(_flag_errors(exc, given, source)) from None


def _flag_errors(error: ValidationError, given: list[tuple[str, str, Any]], source: str) -> str:
    """One line per problem, naming the flag that caused it (or every flag given, for
    a problem of the whole, like an initial master that is not a controller)."""
    by_path = {path: f"{flag} {_shown(value)}".rstrip() for flag, path, value in given}
    everything = " ".join(by_path.values())
    lines = []
    for problem in error.errors():
        path = ".".join(str(part) for part in problem["loc"])
        msg = problem["msg"].removeprefix("Value error, ")
        named = next((by_path[p] for p in by_path if path == p or path.startswith(p + ".")), None)
        where = f" (over {source})" if source else ""
        lines.append(f"{named or everything}{where}: {msg}")
    return "\n".join(lines)


def _shown(value: Any) -> str:
    """A flag's value as it was typed."""
    if isinstance(value, list | tuple):
        return ",".join(str(v) for v in value)
    return "" if value is True else str(value)

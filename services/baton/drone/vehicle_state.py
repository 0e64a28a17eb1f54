"""What the drone service knows of its autopilot: link health, readiness, mode names. Pure.

The MAVSDK backend (``mobility.py``) feeds this module what arrives, with the
time it arrived, and asks it what to answer; nothing here touches MAVSDK, a
socket or a clock, so every corner (an autopilot that dies, one that reboots
and forgets the streams it was asked for, one that is not armable yet) is
tested by calling it with chosen times.

Why these rules, found against ArduCopter SITL (docs/design.md, "The real
autopilot"):

- A real autopilot streams almost nothing until asked, and forgets what it
  was asked when it reboots; after a TCP reconnect MAVSDK does not ask again.
  So the streams are (re)requested whenever heartbeats arrive but position
  telemetry does not: on first contact, after a reconnect and after a reboot
  alike (``LinkMonitor.wants_streams``).
- MAVSDK keeps the last value of each stream forever: for 2.4 s after the
  autopilot died it still reported it "connected" and served the last
  position. A position older than ``position_max_age_s`` is an outage, and
  every read and command is refused during one.
- "Position and home known" is not "armable": ArduCopter has both about 20 s
  after boot and arms only once its EKF uses GPS (about 40 s). It says why in
  "PreArm: ..." STATUSTEXT messages, which are passed on.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass
from types import SimpleNamespace

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega
from pymavlink.dialects.v20 import common as mavlink

from baton.v1 import drone_pb2

ARDUPILOT = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
PX4 = mavlink.MAV_AUTOPILOT_PX4
# ArduPilot's flight mode in which a copter arms, takes off and flies to a
# location on a ground station's command (MAVSDK reports it as OFFBOARD).
ARDUPILOT_COMMAND_MODE = "GUIDED"
# How long a "PreArm: ..." message explains a refusal: ArduPilot repeats it
# every 30 s while the check fails.
PREARM_TEXT_VALID_S = 60.0


@dataclass(frozen=True)
class Heartbeat:
    """The fields of the autopilot's HEARTBEAT that name it and its mode."""

    autopilot: int
    vehicle_type: int
    base_mode: int
    custom_mode: int

    @property
    def is_ardupilot(self) -> bool:
        """ArduPilot firmware (custom modes from its own table)."""
        return self.autopilot == ARDUPILOT

    def autopilot_name(self) -> str:
        """``ArduPilot``, ``PX4``, or the MAV_AUTOPILOT enum's name for others."""
        if self.autopilot == ARDUPILOT:
            return "ArduPilot"
        if self.autopilot == PX4:
            return "PX4"
        entry = mavlink.enums["MAV_AUTOPILOT"].get(self.autopilot)
        return entry.name.removeprefix("MAV_AUTOPILOT_") if entry else f"AUTOPILOT_{self.autopilot}"

    def mode_name(self) -> str:
        """The flight mode as the autopilot names it (ArduCopter GUIDED, PX4 LOITER, ...)."""
        message = SimpleNamespace(
            autopilot=self.autopilot,
            type=self.vehicle_type,
            base_mode=self.base_mode,
            custom_mode=self.custom_mode,
            get_type=lambda: "HEARTBEAT",
        )
        return str(mavutil.mode_string_v10(message))

    def custom_mode_number(self, name: str) -> int | None:
        """ArduPilot's custom mode number for ``name`` on this vehicle type, if it has one."""
        mapping = mavutil.mode_mapping_byname(self.vehicle_type) if self.is_ardupilot else None
        return mapping.get(name) if mapping else None


@dataclass(frozen=True)
class Health:
    """What readiness needs, read from this autopilot's own latest messages.

    Not MAVSDK's ``subscribe_health``: MAVSDK keeps one Health per system id
    and re-sends it whole whenever any part changes (a HOME_POSITION, say),
    so after an autopilot reboot it reported the dead one's "global position
    ok" and "armable" before the new one had sent a single SYS_STATUS.
    """

    is_global_position_ok: bool
    is_home_position_ok: bool
    is_armable: bool

    @classmethod
    def from_messages(
        cls, sys_status: dict[str, int], home_known: bool, ekf_flags: int | None = None
    ) -> Health:
        """Global position: the GPS present, enabled and healthy in SYS_STATUS and,
        where the autopilot reports its EKF (ArduPilot's EKF_STATUS_REPORT), the
        EKF holding an absolute horizontal position. Armable: SYS_STATUS's
        pre-arm bit healthy.

        ArduCopter SITL at speed-up 10, measured: GPS healthy at 0.9 s, the
        pre-arm bit at 2.3 s (enough for STABILIZE), the EKF using GPS at
        4.1 s; GUIDED arms only from then on.
        """
        present = sys_status["onboard_control_sensors_present"]
        enabled = sys_status["onboard_control_sensors_enabled"]
        health = sys_status["onboard_control_sensors_health"]
        gps_ok = bool(present & enabled & health & mavlink.MAV_SYS_STATUS_SENSOR_GPS)
        if ekf_flags is not None:
            gps_ok = gps_ok and ekf_has_absolute_position(ekf_flags)
        return cls(
            is_global_position_ok=gps_ok,
            is_home_position_ok=home_known,
            is_armable=bool(health & mavlink.MAV_SYS_STATUS_PREARM_CHECK),
        )


def ekf_has_absolute_position(flags: int) -> bool:
    """ArduPilot's EKF_STATUS_REPORT flags: an absolute horizontal position, not the
    constant-position mode it holds before GPS is used."""
    return bool(flags & ardupilotmega.EKF_POS_HORIZ_ABS) and not (
        flags & ardupilotmega.EKF_CONST_POS_MODE
    )


@dataclass(frozen=True)
class Readiness:
    """Whether the vehicle can be armed and flown, and why not."""

    ready: bool
    armable: bool
    reason: str  # empty when ready


def readiness(
    health: Health | None,
    armed: bool,
    prearm_text: str | None,
) -> Readiness:
    """Ready = global position and home known and (armed or armable).

    ``prearm_text`` is the autopilot's latest "PreArm: ..." message still
    valid (see ``PREARM_TEXT_VALID_S``), the best reason there is.
    """
    if health is None:
        return Readiness(False, False, "no health report (SYS_STATUS) from the autopilot yet")
    armable = bool(health.is_armable and health.is_global_position_ok)
    missing = []
    if not health.is_global_position_ok:
        missing.append("no global position yet (estimator not using GPS)")
    if not health.is_home_position_ok:
        missing.append("no home position yet")
    if not (armed or health.is_armable):
        missing.append("pre-arm checks failing")
    if not missing:
        return Readiness(True, armable, "")
    reason = "; ".join(missing)
    if prearm_text and not armed:
        reason = f"{prearm_text} ({reason})"
    return Readiness(False, armable, reason)


# What a flight state is made of, by the telemetry cache's name, and the message that
# brings it. Until each has arrived MAVSDK's cache holds nothing for it, and a default
# (disarmed, on the ground) would be an answer the autopilot never gave: a restarted
# drone's first look would take a hovering vehicle for one its autopilot landed.
FLIGHT_STATE_PARTS = (
    ("armed", "armed state (HEARTBEAT)"),
    ("in_air", "landed state (EXTENDED_SYS_STATE)"),
)


def flight_state_missing(heard: Collection[str]) -> str | None:
    """What of the flight state the autopilot has not sent yet (``FLIGHT_STATE_PARTS``
    not in ``heard``), for a person; None once it is all known."""
    missing = [what for name, what in FLIGHT_STATE_PARTS if name not in heard]
    return " and ".join(missing) or None


def is_prearm_text(text: str) -> bool:
    """An autopilot's explanation of why it will not arm (ArduPilot and PX4 wording)."""
    lowered = text.lower()
    return lowered.startswith(("prearm", "pre-arm", "arm:", "preflight fail"))


@dataclass
class LinkMonitor:
    """Heartbeat and position ages, outages, and when to (re)request the streams.

    Times are monotonic wall seconds, given by the caller. An outage starts
    when the link stops being healthy (no heartbeat for ``heartbeat_timeout_s``,
    or the newest position older than ``position_max_age_s``) after it was
    healthy once, and ends when it is healthy again.
    """

    heartbeat_timeout_s: float = 3.0
    position_max_age_s: float = 1.0
    # Streams are asked for again at most this often while they do not come.
    stream_retry_s: float = 2.0
    heartbeat_at: float | None = None
    position_at: float | None = None
    # SYS_STATUS, which readiness reads; asked for at 2 Hz.
    status_max_age_s: float = 3.0
    status_at: float | None = None
    outage_since: float | None = None
    outages: int = 0
    stream_requests: int = 0
    last_stream_request_at: float | None = None
    was_healthy: bool = False
    # The connect-time set-up (fence, GCS failsafe, bounds) ran in this contact.
    set_up: bool = False

    def heard(self, now: float) -> None:
        """A heartbeat arrived from the autopilot."""
        self.heartbeat_at = now

    def position(self, now: float) -> None:
        """A position sample arrived."""
        self.position_at = now

    def status(self, now: float) -> None:
        """A SYS_STATUS arrived."""
        self.status_at = now

    def heartbeat_age(self, now: float) -> float | None:
        """Seconds since the last heartbeat; None before the first."""
        return None if self.heartbeat_at is None else now - self.heartbeat_at

    def position_age(self, now: float) -> float | None:
        """Seconds since the last position sample; None before the first."""
        return None if self.position_at is None else now - self.position_at

    def problem(self, now: float) -> str:
        """What is wrong with the link now, for a person; empty when healthy."""
        heartbeat = self.heartbeat_age(now)
        if heartbeat is None:
            return "no heartbeat from the autopilot yet"
        if heartbeat > self.heartbeat_timeout_s:
            return f"no heartbeat for {heartbeat:.1f} s"
        position = self.position_age(now)
        if position is None:
            return "heartbeats arrive but no position telemetry yet"
        if position > self.position_max_age_s:
            return (
                f"position telemetry {position:.1f} s old "
                f"(bound {self.position_max_age_s:g} s): stream stopped"
            )
        return ""

    def healthy(self, now: float) -> bool:
        """Heartbeats arrive and the position is fresh."""
        return not self.problem(now)

    def update(self, now: float) -> str | None:
        """Notes outages starting and ending; returns "outage" or "recovered" on a change."""
        healthy = self.healthy(now)
        if healthy:
            self.was_healthy = True
            if self.outage_since is not None:
                self.outage_since = None
                return "recovered"
            return None
        if self.was_healthy and self.outage_since is None:
            self.outage_since = self._went_bad_at(now)
            self.outages += 1
            self.set_up = False  # a rebooted autopilot may have lost what it was given
            return "outage"
        return None

    def _went_bad_at(self, now: float) -> float:
        """When the link stopped being healthy: a bound passed, not when it was noticed."""
        times = [now]
        if self.heartbeat_at is not None:
            times.append(self.heartbeat_at + self.heartbeat_timeout_s)
        if self.position_at is not None:
            times.append(self.position_at + self.position_max_age_s)
        return min(times)

    def wants_streams(self, now: float) -> bool:
        """Heartbeats arrive but position or SYS_STATUS does not: (re)request the streams now.

        True on first contact, after a reconnect and after an autopilot
        reboot (it forgets what it was asked), at most every ``stream_retry_s``.
        Both streams count: another ground station may have asked for the
        position alone (an autopilot sends what one asked to all), and then
        readiness would wait for SYS_STATUS for ever.
        """
        heartbeat = self.heartbeat_age(now)
        if heartbeat is None or heartbeat > self.heartbeat_timeout_s:
            return False  # nobody to ask
        position = self.position_age(now)
        status = None if self.status_at is None else now - self.status_at
        if (
            position is not None
            and position <= self.position_max_age_s
            and status is not None
            and status <= self.status_max_age_s
        ):
            return False
        last = self.last_stream_request_at
        return last is None or now - last >= self.stream_retry_s

    def wants_set_up(self, now: float) -> bool:
        """The autopilot is there and was not set up in this contact: at first contact and
        after each outage, whether or not its streams flow. A restarted drone service
        finds them flowing at the rates the one before asked for; the set-up is due all
        the same. Due again whenever the streams are asked for (``streams_requested``):
        an autopilot that did not answer the last set-up may answer this one."""
        heartbeat = self.heartbeat_age(now)
        if heartbeat is None or heartbeat > self.heartbeat_timeout_s:
            return False  # nobody to set up
        return not self.set_up

    def setting_up(self) -> None:
        """The set-up starts now (``wants_set_up``)."""
        self.set_up = True

    def streams_requested(self, now: float) -> None:
        """The streams were just requested."""
        self.stream_requests += 1
        self.last_stream_request_at = now
        self.set_up = False

    def snapshot(self, now: float) -> drone_pb2.VehicleLink:
        """The link as GetStatus reports it (call ``update`` first)."""
        heartbeat, position = self.heartbeat_age(now), self.position_age(now)
        problem = self.problem(now)
        return drone_pb2.VehicleLink(
            healthy=not problem,
            heartbeat_age_s=-1.0 if heartbeat is None else heartbeat,
            position_age_s=-1.0 if position is None else position,
            problem=problem,
            outage_s=0.0 if self.outage_since is None else now - self.outage_since,
            outages=self.outages,
            stream_requests=self.stream_requests,
        )

"""The sim vehicle's MAVLink side: a UDP server speaking the PX4 dialect.

MAVSDK connects with ``udpout://127.0.0.1:PORT`` exactly as to PX4 SITL. The
vehicle binds a port (0 by default, so the kernel picks a free one: UDP
listeners let a second process bind a taken port silently, see docs/design.md,
"Notes on MAVSDK 4.x and the sim vehicle") and learns each ground station's
address from the first packet it sends; MAVSDK sends its own heartbeat as soon
as the connection is added, so discovery is immediate. Packets for another
system id are ignored, so vehicles never answer each other's ground stations.

The set of messages and commands is the one that section found sufficient for
MAVSDK 4.x (heartbeat with the PX4 custom mode, SYS_STATUS, position, home,
extended state, GPS, battery; arm, takeoff, land, mode, reposition, speed,
RTL, message requests and intervals; the parameter protocol for
MIS_TAKEOFF_ALT, PX4's link-loss and geofence parameters and MPC_XY_VEL_MAX (the
fastest it flies); the mission protocol for fence uploads, ``fence_upload.py``,
``state().fence`` the fence held and each upload accepted counted as ``fence``, a
breach acted on as GF_ACTION says and counted as ``fence_breach``).
Unknown commands get COMMAND_ACK UNSUPPORTED.

It has a gimbal, which it manages itself as an autopilot does: a region of
interest (``MAV_CMD_DO_SET_ROI_LOCATION``, ``MAV_CMD_DO_SET_ROI`` in location
mode) points it at a location until ``MAV_CMD_DO_SET_ROI_NONE`` (or
``DO_SET_ROI`` mode none) clears it; ``state().looking_at`` is where it
points, and each change is counted as a flight command is (``roi``,
``roi_none``).

Two habits of a real ArduPilot that the project must not forget, kept here
(docs/design.md, "The real autopilot"):

- Unasked, it streams only HEARTBEAT (plus STATUSTEXT and the replies to
  commands and parameter requests). Every other message comes only once a
  ground station asked with MAV_CMD_SET_MESSAGE_INTERVAL, or once per
  MAV_CMD_REQUEST_MESSAGE. MAVSDK's Telemetry ``set_rate_*`` calls ask for
  GLOBAL_POSITION_INT (position), HOME_POSITION (home), EXTENDED_SYS_STATE
  (in air, landed state), BATTERY_STATUS (battery) and SYS_STATUS (health).
  All ground stations share one set of intervals, as on an autopilot's one
  UDP port: what one asked for, all get.
- Until its estimator has warmed up (``FlightParams.warmup_s``) it is not
  armable: SYS_STATUS has the GPS unhealthy and no pre-arm bit (MAVSDK's
  ``Health.is_armable`` reads MAV_SYS_STATUS_PREARM_CHECK), HOME_POSITION is
  not sent, and an arm command is DENIED with a "PreArm: ..." STATUSTEXT,
  which is also repeated every 30 s of simulated time.

Command parameters may be NaN, MAVLink's "unset": it means the default, and
a parameter without one makes the command DENIED. One datagram that cannot be
handled is logged and skipped; the vehicle's thread never dies of it.

Its battery is set anew by ArduPilot's ``MAV_CMD_BATTERY_RESET`` (ardupilotmega.xml:
param1 the batteries, bit 0 its one; param2 the percentage): it reads that from then
on and drains on from there (``Kinematics.reset_battery``), as an ArduPilot battery
monitor that counts the charge spent does (ArduPilot's own autotest lowers SITL's
battery so). The testbed's battery fault sends it (``baton.testbed.battery``); it is
the one command of ardupilotmega.xml the vehicle takes beside PX4's dialect.

Every flight command the vehicle acts on (arm, disarm, takeoff, land, return
to launch, mode, reposition, speed) is counted where it happens, one line in
its effects file (``baton.effects``, ``--effects-file``), for the testbed's
exactly-once check, and so is a battery reset (``battery_reset``: the percentage
and what it read before); telemetry requests and parameter writes change no
flight and are not counted. A retransmission of a command it already acted on is
acknowledged again but neither acted on nor counted (``retransmissions.py``
has the rule and its limit; it reads the kernel's arrival stamp of each
datagram).

Everything runs on one thread per vehicle, so ``SimVehicle`` works the same
in the ``baton sim-vehicle`` process and inside a test.
"""

from __future__ import annotations

import math
import select
import socket
import struct
import sys
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega
from pymavlink.dialects.v20 import common as mavlink

from baton import logs, signing
from baton.effects import EffectsFile
from baton.sdk.fence import Fence
from baton.sim_vehicle.fence_upload import FENCE, Ack, FenceUpload, Request
from baton.sim_vehicle.kinematics import (
    ArmCheckFailed,
    FlightParams,
    GeoPoint,
    Kinematics,
    Phase,
    PreArmFailed,
    Refused,
)
from baton.sim_vehicle.retransmissions import Retransmissions, command_key

# Physics and scheduling tick, in wall seconds.
TICK_S = 0.02
# A ground station that has sent nothing for this long is dropped.
PEER_TIMEOUT_S = 10.0

# PX4 custom mode: main mode in bits 16..23, sub mode in bits 24..31.
PX4_MAIN_MANUAL, PX4_MAIN_POSCTL, PX4_MAIN_AUTO = 1, 3, 4
PX4_AUTO_READY, PX4_AUTO_TAKEOFF, PX4_AUTO_LOITER = 1, 2, 3
PX4_AUTO_MISSION, PX4_AUTO_RTL, PX4_AUTO_LAND = 4, 5, 6

_MODE_OF_PHASE = {
    Phase.ON_GROUND: (PX4_MAIN_AUTO, PX4_AUTO_LOITER),
    Phase.TAKEOFF: (PX4_MAIN_AUTO, PX4_AUTO_TAKEOFF),
    Phase.HOLD: (PX4_MAIN_AUTO, PX4_AUTO_LOITER),
    Phase.GOTO: (PX4_MAIN_AUTO, PX4_AUTO_LOITER),  # PX4 flies a reposition in Hold
    Phase.LAND: (PX4_MAIN_AUTO, PX4_AUTO_LAND),
    Phase.RETURN: (PX4_MAIN_AUTO, PX4_AUTO_RTL),
}
_MODE_NAMES = {
    PX4_AUTO_TAKEOFF: "TAKEOFF",
    PX4_AUTO_LOITER: "HOLD",
    PX4_AUTO_RTL: "RETURN_TO_LAUNCH",
    PX4_AUTO_LAND: "LAND",
}

# Sensors reported present, enabled and healthy, so MAVSDK's health checks
# (gyro/accel/mag calibration, local and global position) all pass once the
# estimator is ready; before, the GPS is reported unhealthy (MAVSDK's
# is_global_position_ok and is_local_position_ok read that bit).
_SENSORS = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS
    | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
)

# The messages the vehicle streams and their default intervals (wall seconds),
# used when SET_MESSAGE_INTERVAL asks for interval 0, "the default rate".
DEFAULT_INTERVALS_S = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 0.1,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 0.05,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 0.2,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 0.2,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: 1.0,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 0.2,
    mavlink.MAVLINK_MSG_ID_BATTERY_STATUS: 1.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 0.1,
}
# What a ground station gets without asking: only the heartbeat, as from ArduPilot.
UNASKED_STREAMS = (mavlink.MAVLINK_MSG_ID_HEARTBEAT,)
# Messages a REQUEST_MESSAGE can ask for once.
REQUESTABLE = frozenset(DEFAULT_INTERVALS_S) | {mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION}
MIN_INTERVAL_S = 0.01  # a requested rate above 100 Hz is capped

# Linux's SO_TIMESTAMPNS (not in Python's socket module): the kernel stamps
# each datagram with the wall time it reached the socket, which a vehicle
# that was stopped or slow to read cannot blur (retransmissions.py uses it).
_SO_TIMESTAMPNS = 35
_TIMESPEC = struct.Struct("@ll")

PARAM_TAKEOFF_ALT = "MIS_TAKEOFF_ALT"
# PX4's data-link loss failsafe, which the drone service sets at connect: after
# COM_DL_LOSS_T seconds (simulated) without a ground station's HEARTBEAT, in the
# air, NAV_DLL_ACT 2 returns home (0: nothing, PX4's default).
PARAM_DL_LOSS_T, PARAM_DLL_ACT = "COM_DL_LOSS_T", "NAV_DLL_ACT"
RETURN_ON_LINK_LOSS = 2
PARAM_GF_MAX_VER_DIST, PARAM_GF_ACTION = "GF_MAX_VER_DIST", "GF_ACTION"
# PX4's absolute maximum horizontal speed (m/s): the vehicle flies no faster.
PARAM_XY_VEL_MAX = "MPC_XY_VEL_MAX"
GF_RETURN, GF_LAND = 3, 5  # GF_ACTION values it acts on (PX4's; 1, a warning, is its default)
# The region-of-interest commands its gimbal obeys.
ROI_COMMANDS = (
    mavlink.MAV_CMD_DO_SET_ROI_LOCATION,
    mavlink.MAV_CMD_DO_SET_ROI,
    mavlink.MAV_CMD_DO_SET_ROI_NONE,
)
FORCE_DISARM_MAGIC = 21196
# ArduPilot's command that sets a battery's remaining percentage (not in common.xml).
MAV_CMD_BATTERY_RESET = ardupilotmega.MAV_CMD_BATTERY_RESET


@dataclass(frozen=True)
class VehicleState:
    """A snapshot of the vehicle, for tests and log lines."""

    system_id: int
    armed: bool
    mode: str
    phase: str
    in_air: bool
    latitude_deg: float
    longitude_deg: float
    altitude_amsl_m: float
    relative_altitude_m: float
    home: GeoPoint
    armable: bool  # the estimator has warmed up
    speed_m_s: float
    battery_pct: float
    time_s: float
    peers: int
    looking_at: GeoPoint | None = None  # the gimbal's region of interest, if one is set
    fence: Fence | None = None  # the fence a ground station uploaded (None: none)
    fence_action: int = 1  # GF_ACTION: what it does out of the fence (1: warn only)

    def as_fields(self) -> dict[str, Any]:
        """The state as flat log fields."""
        return {
            "system_id": self.system_id,
            "armed": self.armed,
            "mode": self.mode,
            "phase": self.phase,
            "in_air": self.in_air,
            "armable": self.armable,
            "lat": round(self.latitude_deg, 7),
            "lon": round(self.longitude_deg, 7),
            "rel_alt_m": round(self.relative_altitude_m, 2),
            "sim_time_s": round(self.time_s, 2),
        }


class _PeerSink:
    """The file pymavlink writes to: every known ground station gets each packet."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.peers: dict[tuple[str, int], float] = {}  # address -> last heard (monotonic)

    def write(self, data: bytes) -> None:
        for address in list(self.peers):
            try:
                self.sock.sendto(data, address)
            except OSError:
                self.peers.pop(address, None)


class SimVehicle:
    """One simulated multicopter behind a MAVLink UDP port.

    ``start()`` binds and starts the vehicle's thread, ``stop()`` ends it,
    ``state()`` and ``streams()`` are snapshots readable from any thread,
    ``url`` is what a MAVSDK client connects to. ``effects`` counts the
    commands it acted on (in memory only unless it has a file; vehicles of
    one process may share one).
    """

    def __init__(
        self,
        home: GeoPoint,
        *,
        system_id: int = 1,
        host: str = "127.0.0.1",
        port: int = 0,
        speedup: float = 1.0,
        params: FlightParams | None = None,
        on_state: Callable[[VehicleState], None] | None = None,
        effects: EffectsFile | None = None,
        signing_key: bytes | None = None,
    ) -> None:
        if speedup <= 0 or not math.isfinite(speedup):
            raise ValueError(f"speedup must be > 0, got {speedup}")
        if not 1 <= system_id <= 255:
            raise ValueError(f"system id must be in 1..255, got {system_id}")
        self.system_id = system_id
        self.speedup = speedup
        self._host, self._requested_port = host, port
        self._kinematics = Kinematics(home, params)
        self._on_state = on_state
        self.effects = effects if effects is not None else EffectsFile(None)
        self._signing_key = signing_key
        # Frames refused for their signature; logged at most every REFUSAL_LOG_S.
        self.refused_frames = 0
        self._refusals_logged_at = -math.inf
        self._retransmissions = Retransmissions()
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._sock: socket.socket | None = None
        self._sink: _PeerSink | None = None
        self._mav: mavlink.MAVLink | None = None
        # Message id -> wall interval (s) of what is streamed now; 0 = off.
        self._intervals = {msg_id: DEFAULT_INTERVALS_S[msg_id] for msg_id in UNASKED_STREAMS}
        self._next_due: dict[int, float] = {}
        self._last_reported: tuple[Any, ...] | None = None
        # The gimbal's region of interest (AMSL); None: it looks where the vehicle goes.
        self._roi: GeoPoint | None = None
        # The fence held (uploaded whole: fence_upload.py) and the upload under way.
        self._fence: Fence | None = None
        self._fence_upload = FenceUpload()
        self.port = 0
        self._log = logs.get_logger("sim_vehicle", system_id=system_id)
        # PX4's data-link loss parameters (PX4's defaults: 10 s, no action), when a
        # ground station's HEARTBEAT came last (None: never), and whether the vehicle
        # already returned for this loss.
        self._link_loss: dict[str, float] = {PARAM_DL_LOSS_T: 10.0, PARAM_DLL_ACT: 0.0}
        # PX4's geofence parameters the drone sets beside a fence upload (safety.py
        # fence_params; PX4's defaults: no ceiling, warn only), and whether the vehicle
        # already acted on this breach.
        self._geofence_params: dict[str, float] = {PARAM_GF_MAX_VER_DIST: 0.0, PARAM_GF_ACTION: 1.0}
        self._gcs_seen_at: float | None = None
        self._link_loss_acted = False
        self._fence_acted = False

    # --- lifecycle ---------------------------------------------------------------

    @property
    def url(self) -> str:
        """The MAVLink URL a MAVSDK client should use."""
        return f"udpout://{self._host}:{self.port}"

    def start(self) -> None:
        """Binds the port and starts the vehicle's thread."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        if sys.platform.startswith("linux"):
            sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        sock.bind((self._host, self._requested_port))
        self.port = sock.getsockname()[1]
        self._sock = sock
        self._sink = _PeerSink(sock)
        self._mav = mavlink.MAVLink(self._sink, srcSystem=self.system_id, srcComponent=1)
        if self._signing_key is not None:
            signing.enable(self._mav, self._signing_key, sign_outgoing=True)
        self._thread = threading.Thread(
            target=self._run, name=f"sim-vehicle-{self.system_id}", daemon=True
        )
        self._thread.start()
        self._log.info(
            "vehicle listening",
            url=self.url,
            speedup=self.speedup,
            signing=self._signing_key is not None,
        )

    def stop(self) -> None:
        """Stops the thread and closes the port; idempotent."""
        self._stopping.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None
            self._log.info("vehicle stopped")

    def __enter__(self) -> SimVehicle:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def state(self) -> VehicleState:
        """A consistent snapshot of the vehicle."""
        with self._lock:
            return self._snapshot()

    def streams(self) -> dict[int, float]:
        """What is streamed now (message id -> wall interval, s): heartbeat and what was asked."""
        with self._lock:
            return {msg_id: every for msg_id, every in self._intervals.items() if every > 0}

    def _snapshot(self) -> VehicleState:
        k = self._kinematics
        here = k.geo_position()
        return VehicleState(
            system_id=self.system_id,
            armed=k.armed,
            mode=_MODE_NAMES[_MODE_OF_PHASE[k.phase][1]],
            phase=k.phase.value,
            in_air=k.in_air,
            latitude_deg=here.latitude_deg,
            longitude_deg=here.longitude_deg,
            altitude_amsl_m=here.altitude_amsl_m,
            relative_altitude_m=k.relative_altitude_m,
            home=k.geo_home(),
            armable=k.estimator_ready,
            speed_m_s=k.speed_m_s,
            battery_pct=k.battery_pct,
            time_s=k.time_s,
            peers=len(self._sink.peers) if self._sink else 0,
            looking_at=self._roi,
            fence=self._fence,
            fence_action=round(self._geofence_params[PARAM_GF_ACTION]),
        )

    # --- the vehicle's thread ------------------------------------------------------

    def _run(self) -> None:
        assert self._sock is not None
        last = next_tick = time.monotonic()
        while not self._stopping.is_set():
            timeout = max(0.0, next_tick - time.monotonic())
            readable, _, _ = select.select([self._sock], [], [], timeout)
            if readable:
                try:
                    data, address, arrived_at = _receive_stamped(self._sock)
                except OSError:
                    continue
                try:
                    with self._lock:
                        self._receive(data, address, arrived_at)
                except Exception as exc:
                    # A bug or a datagram nobody foresaw must not silence the
                    # vehicle: its ground stations would see it die.
                    where = traceback.extract_tb(exc.__traceback__)[-1]
                    self._log.warning(
                        "datagram skipped: handling it failed",
                        peer=f"{address[0]}:{address[1]}",
                        error=repr(exc),
                        at=f"{where.filename}:{where.lineno}",
                    )
            now = time.monotonic()
            if now >= next_tick:
                with self._lock:
                    self._kinematics.step((now - last) * self.speedup)
                    self._watch_link_loss(now)
                    self._watch_fence()
                    last = now
                    self._send_due(now)
                    self._report_if_changed()
                next_tick = max(next_tick + TICK_S, now)

    def _report_if_changed(self) -> None:
        k = self._kinematics
        peers = len(self._sink.peers) if self._sink else 0
        key = (k.armed, k.phase, k.speed_m_s, k.estimator_ready, peers)
        if key != self._last_reported:
            self._last_reported = key
            snapshot = self._snapshot()
            self._log.info("vehicle state", **snapshot.as_fields(), peers=snapshot.peers)
            if self._on_state is not None:
                self._on_state(snapshot)

    def _receive(self, data: bytes, address: tuple[str, int], arrived_at: float) -> None:
        assert self._mav is not None and self._sink is not None
        self._sink.peers[address] = time.monotonic()
        # A fresh parser per datagram: a datagram holds whole packets, and the
        # rest of a truncated one would swallow the next datagram's command.
        parser = mavlink.MAVLink(None, srcSystem=self.system_id, srcComponent=1)
        parser.robust_parsing = True
        if self._signing_key is not None:
            parser.signing = self._mav.signing  # one clock and one replay guard per vehicle
        try:
            messages = parser.parse_buffer(data) or []
        except mavlink.MAVError as exc:
            messages = [mavlink.MAVLink_bad_data(data, str(exc))]
        if parser.buf_len() > 0:
            messages.append(mavlink.MAVLink_bad_data(data, "truncated packet"))
        bad = [msg for msg in messages if msg.get_msgId() == mavlink.MAVLINK_MSG_ID_BAD_DATA]
        refused = [msg for msg in bad if msg.reason == signing.REFUSED_REASON]
        if refused:
            self._refused(refused, address)
            bad = [msg for msg in bad if msg.reason != signing.REFUSED_REASON]
        if bad:  # not MAVLink, or a bad checksum: one line per datagram, not per byte
            self._log.warning(
                "bad data skipped",
                peer=f"{address[0]}:{address[1]}",
                pieces=len(bad),
                reason=bad[0].reason,
            )
        for msg in messages:
            if msg.get_msgId() in (mavlink.MAVLINK_MSG_ID_BAD_DATA, mavlink.MAVLINK_MSG_ID_UNKNOWN):
                continue  # unknown: another dialect's message, nothing for this vehicle
            target = getattr(msg, "target_system", 0)
            if target not in (0, self.system_id):
                continue  # another vehicle's traffic
            self._handle(msg, arrived_at)

    def _refused(self, refused: list[Any], address: tuple[str, int]) -> None:
        """Counts frames refused by signing, and says so at most every REFUSAL_LOG_S."""
        self.refused_frames += len(refused)
        now = time.monotonic()
        if now - self._refusals_logged_at >= signing.REFUSAL_LOG_S:
            self._refusals_logged_at = now
            self._log.warning(
                "MAVLink frames refused: not signed with the vehicle's key, or replayed",
                peer=f"{address[0]}:{address[1]}",
                refused=self.refused_frames,
            )

    # --- telemetry -----------------------------------------------------------------

    def _send_due(self, now: float) -> None:
        assert self._sink is not None
        for address, heard in list(self._sink.peers.items()):
            if now - heard > PEER_TIMEOUT_S:
                del self._sink.peers[address]
        if not self._sink.peers:
            return
        if self._signing_key is not None and self._mav is not None:
            # pymavlink counts one per frame; the clock must keep up with time,
            # or a ground station that starts later takes our frames for replays.
            self._mav.signing.timestamp = max(self._mav.signing.timestamp, signing.timestamp_now())
        for msg_id, interval in self._intervals.items():
            if interval <= 0:
                continue
            if now >= self._next_due.get(msg_id, 0.0):
                self._send_message(msg_id)
                self._next_due[msg_id] = now + interval
        # Past the return above: the first report goes to the first ground station.
        failure = self._kinematics.prearm_report_due()
        if failure is not None:
            self._send_prearm_failure(failure)

    def _send_prearm_failure(self, reason: str) -> None:
        """ArduPilot's way of saying why it will not arm: a CRITICAL "PreArm: ..." text."""
        assert self._mav is not None
        self._mav.statustext_send(mavlink.MAV_SEVERITY_CRITICAL, f"PreArm: {reason}".encode())

    def _custom_mode(self) -> int:
        main, sub = _MODE_OF_PHASE[self._kinematics.phase]
        return (main << 16) | (sub << 24)

    def _send_message(self, msg_id: int) -> bool:
        """Sends one message by id; False if this vehicle cannot produce it."""
        assert self._mav is not None
        k, mav = self._kinematics, self._mav
        boot_ms = int(k.time_s * 1000) & 0xFFFFFFFF
        here = k.geo_position()
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            if k.armed:
                base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
            status = mavlink.MAV_STATE_ACTIVE if k.armed else mavlink.MAV_STATE_STANDBY
            mav.heartbeat_send(
                mavlink.MAV_TYPE_QUADROTOR,
                mavlink.MAV_AUTOPILOT_PX4,
                base,
                self._custom_mode(),
                status,
            )
        elif msg_id == mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            mav.global_position_int_send(
                boot_ms,
                round(here.latitude_deg * 1e7),
                round(here.longitude_deg * 1e7),
                round(here.altitude_amsl_m * 1000),
                round(k.relative_altitude_m * 1000),
                round(k.velocity.north_m * 100),
                round(k.velocity.east_m * 100),
                round(-k.velocity.up_m * 100),
                round(k.heading_deg * 100) % 36000,
            )
        elif msg_id == mavlink.MAVLINK_MSG_ID_SYS_STATUS:
            present = enabled = health = _SENSORS
            if k.estimator_ready:
                # Set in all three, as ArduPilot does once its checks pass
                # (MAVLink: always healthy when armed).
                present |= mavlink.MAV_SYS_STATUS_PREARM_CHECK
                enabled |= mavlink.MAV_SYS_STATUS_PREARM_CHECK
                health |= mavlink.MAV_SYS_STATUS_PREARM_CHECK
            else:
                health &= ~mavlink.MAV_SYS_STATUS_SENSOR_GPS
            mav.sys_status_send(
                present,
                enabled,
                health,
                100,
                16000,
                1000,
                round(k.battery_pct),
                0,
                0,
                0,
                0,
                0,
                0,
            )
        elif msg_id == mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            landed = {
                Phase.ON_GROUND: mavlink.MAV_LANDED_STATE_ON_GROUND,
                Phase.TAKEOFF: mavlink.MAV_LANDED_STATE_TAKEOFF,
                Phase.LAND: mavlink.MAV_LANDED_STATE_LANDING,
            }.get(k.phase, mavlink.MAV_LANDED_STATE_IN_AIR)
            mav.extended_sys_state_send(mavlink.MAV_VTOL_STATE_MC, landed)
        elif msg_id == mavlink.MAVLINK_MSG_ID_HOME_POSITION:
            if not k.estimator_ready:
                return True  # no home yet: ArduPilot sends nothing, even when asked
            home = k.geo_home()
            local = k.frame.to_local(home)
            mav.home_position_send(
                round(home.latitude_deg * 1e7),
                round(home.longitude_deg * 1e7),
                round(home.altitude_amsl_m * 1000),
                local.north_m,
                local.east_m,
                -local.up_m,
                [1.0, 0.0, 0.0, 0.0],
                0.0,
                0.0,
                0.0,
                int(k.time_s * 1e6),
            )
        elif msg_id == mavlink.MAVLINK_MSG_ID_GPS_RAW_INT:
            ground_speed = math.hypot(k.velocity.north_m, k.velocity.east_m)
            mav.gps_raw_int_send(
                int(k.time_s * 1e6),
                mavlink.GPS_FIX_TYPE_3D_FIX if k.estimator_ready else mavlink.GPS_FIX_TYPE_NO_FIX,
                round(here.latitude_deg * 1e7),
                round(here.longitude_deg * 1e7),
                round(here.altitude_amsl_m * 1000),
                70,  # eph, cm
                100,  # epv, cm
                round(ground_speed * 100),
                round(k.heading_deg * 100) % 36000,
                12,
            )
        elif msg_id == mavlink.MAVLINK_MSG_ID_BATTERY_STATUS:
            mav.battery_status_send(
                0,
                mavlink.MAV_BATTERY_FUNCTION_ALL,
                mavlink.MAV_BATTERY_TYPE_LIPO,
                2500,
                [4000, 4000, 4000, 4000] + [65535] * 6,
                1000,
                -1,
                -1,
                round(k.battery_pct),
            )
        elif msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE:
            yaw = math.radians(((k.heading_deg + 180.0) % 360.0) - 180.0)
            mav.attitude_send(boot_ms, 0.0, 0.0, yaw, 0.0, 0.0, 0.0)
        elif msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            capabilities = (
                mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
            )
            mav.autopilot_version_send(
                capabilities, 0x010F0000, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, self.system_id
            )
        else:
            return False
        return True

    # --- incoming messages -----------------------------------------------------------

    def _handle(self, msg: Any, arrived_at: float) -> None:
        kind = msg.get_type()
        if kind == "COMMAND_LONG":
            params = [msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6]
            self._command(msg, arrived_at, msg.command, params, msg.param7, None, None, None)
        elif kind == "COMMAND_INT":
            params = [msg.param1, msg.param2, msg.param3, msg.param4, math.nan, math.nan]
            self._command(msg, arrived_at, msg.command, params, msg.z, msg.frame, msg.x, msg.y)
        elif kind in ("PARAM_REQUEST_READ", "PARAM_REQUEST_LIST", "PARAM_SET"):
            self._param(msg, kind)
        elif kind == "HEARTBEAT" and msg.type == mavlink.MAV_TYPE_GCS:
            self._gcs_seen_at = time.monotonic()
        elif kind in ("MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_CLEAR_ALL"):
            self._mission(msg, kind)

    def _mission(self, msg: Any, kind: str) -> None:
        """The mission protocol, fence uploads only (fence_upload.py); a mission of another
        type is refused MAV_MISSION_UNSUPPORTED (baton flies missions call by call)."""
        assert self._mav is not None
        to = (msg.get_srcSystem(), msg.get_srcComponent())
        if msg.mission_type != FENCE:
            if kind != "MISSION_ITEM_INT":
                self._mav.mission_ack_send(*to, mavlink.MAV_MISSION_UNSUPPORTED, msg.mission_type)
            return
        upload = self._fence_upload
        if kind == "MISSION_COUNT":
            step: Request | Ack | None = upload.on_count(msg.count)
        elif kind == "MISSION_ITEM_INT":
            step = upload.on_item(msg)
        else:
            step = upload.on_clear()
        if isinstance(step, Request):
            self._mav.mission_request_int_send(*to, step.seq, FENCE)
            return
        if step is None:
            return
        if step.fence is not None or step.cleared:
            self._fence = step.fence
            fence = step.fence or Fence()
            self.effects.record(
                "fence",
                system_id=self.system_id,
                polygons=[[list(v) for v in p.vertices] for p in fence.polygons],
                inclusion=[p.inclusion for p in fence.polygons],
                circles=len(fence.circles),
            )
            self._log.info("fence held", polygons=len(fence.polygons), circles=len(fence.circles))
        else:
            self._log.info("fence upload refused", result=step.result)
        self._mav.mission_ack_send(*to, step.result, FENCE)

    def _command(
        self,
        msg: Any,
        arrived_at: float,
        command: int,
        p: list[float],
        p7: float,
        frame: int | None,
        x: int | None,
        y: int | None,
    ) -> None:
        """Runs one COMMAND_LONG / COMMAND_INT, records the effect, and acknowledges it.

        A retransmission of a command it acted on is acknowledged as that one
        was (ACCEPTED), and neither acted on nor recorded again.
        """
        assert self._mav is not None
        key, confirmation = command_key(msg), getattr(msg, "confirmation", None)
        copied = self._retransmissions.original(key, confirmation, arrived_at)
        result = mavlink.MAV_RESULT_ACCEPTED
        after_ack: Callable[[], object] | None = None
        if copied is not None:
            self._log.info(
                "retransmission recognised: acknowledged, not acted on again",
                command=command,
                effect_seq=copied,
                confirmation=confirmation,
            )
        else:
            result, after_ack, effect = self._act(command, p, p7, frame, x, y)
            if effect is not None and result == mavlink.MAV_RESULT_ACCEPTED:
                # Before the ACK: whoever saw it accepted finds it counted.
                name, fields = effect
                seq = self.effects.record(name, system_id=self.system_id, **fields)
                self._retransmissions.acted(key, seq, arrived_at, acked_at=time.time())
        self._mav.command_ack_send(
            command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
        )
        if after_ack is not None:
            after_ack()
        # Right after each reply, so MAVSDK sees the new mode and armed state
        # without waiting for the next periodic heartbeat.
        self._send_message(mavlink.MAVLINK_MSG_ID_HEARTBEAT)
        self._report_if_changed()

    def _act(
        self,
        command: int,
        p: list[float],
        p7: float,
        frame: int | None,
        x: int | None,
        y: int | None,
    ) -> tuple[int, Callable[[], object] | None, tuple[str, dict[str, Any]] | None]:
        """Acts on one command: its ACK result, what to send after the ACK, and the
        flight effect to count (name and fields; None for telemetry requests)."""
        k = self._kinematics
        result = mavlink.MAV_RESULT_ACCEPTED
        after_ack: Callable[[], object] | None = None
        effect: tuple[str, dict[str, Any]] | None = None
        try:
            if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
                if _required_int(p[0], "param1 (arm)") >= 1:
                    k.arm()
                    effect = ("arm", {})
                else:
                    forced = _int_or(p[1], 0) == FORCE_DISARM_MAGIC
                    k.disarm(force=forced)
                    effect = ("disarm", {"forced": forced})
            elif command == mavlink.MAV_CMD_NAV_TAKEOFF:
                # param7 is the AMSL altitude; NaN means "use MIS_TAKEOFF_ALT".
                altitude = p7 - k.geo_home().altitude_amsl_m if math.isfinite(p7) else None
                k.takeoff(altitude)
                climb = k.takeoff_altitude_m if altitude is None else altitude
                effect = ("takeoff", {"relative_altitude_m": round(climb, 3)})
            elif command == mavlink.MAV_CMD_NAV_LAND:
                k.land()
                effect = ("land", {})
            elif command == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
                k.return_to_launch()
                effect = ("return_to_launch", {})
            elif command == mavlink.MAV_CMD_DO_SET_MODE:
                main, sub = _required_int(p[1], "param2 (custom mode)"), _int_or(p[2], 0)
                self._set_mode(main, sub)
                effect = ("set_mode", {"mode": _MODE_NAMES.get(sub, f"{main}/{sub}")})
            elif command == mavlink.MAV_CMD_DO_REPOSITION:
                target = self._reposition_target(p, p7, frame, x, y)
                k.goto_geo(target, speed_m_s=p[0])
                effect = (
                    "goto",
                    {
                        "latitude_deg": target.latitude_deg,
                        "longitude_deg": target.longitude_deg,
                        "altitude_amsl_m": round(target.altitude_amsl_m, 3),
                    },
                )
            elif command in ROI_COMMANDS:
                effect = self._point_gimbal(command, p, p7, frame, x, y)
            elif command == MAV_CMD_BATTERY_RESET:
                effect = self._reset_battery(p)
            elif command == mavlink.MAV_CMD_DO_CHANGE_SPEED:
                if p[1] > 0:
                    k.set_speed(p[1])
                    effect = ("set_speed", {"speed_m_s": p[1]})
            elif command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
                # An unset interval is the default rate (0).
                result = self._set_interval(
                    _required_int(p[0], "param1 (message id)"), 0.0 if math.isnan(p[1]) else p[1]
                )
            elif command in (
                mavlink.MAV_CMD_REQUEST_MESSAGE,
                mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
            ):
                msg_id = (
                    _required_int(p[0], "param1 (message id)")
                    if command == mavlink.MAV_CMD_REQUEST_MESSAGE
                    else mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION
                )
                if msg_id in REQUESTABLE:
                    after_ack = lambda: self._send_message(msg_id)  # noqa: E731
                else:
                    result = mavlink.MAV_RESULT_UNSUPPORTED
            else:
                result = mavlink.MAV_RESULT_UNSUPPORTED
        except Refused as refusal:
            failed = isinstance(refusal, ArmCheckFailed)  # ArduPilot answers FAILED
            result = mavlink.MAV_RESULT_FAILED if failed else mavlink.MAV_RESULT_DENIED
            self._log.info("command denied", command=command, reason=str(refusal))
            if isinstance(refusal, PreArmFailed):
                # Before the ACK, so the reason is there when the refusal arrives.
                self._send_prearm_failure(str(refusal))
        return result, after_ack, effect

    def _point_gimbal(
        self,
        command: int,
        p: list[float],
        p7: float,
        frame: int | None,
        x: int | None,
        y: int | None,
    ) -> tuple[str, dict[str, Any]]:
        """Sets or clears the gimbal's region of interest; the effect to count."""
        mode = mavlink.MAV_ROI_LOCATION
        if command == mavlink.MAV_CMD_DO_SET_ROI_NONE:
            mode = mavlink.MAV_ROI_NONE
        elif command == mavlink.MAV_CMD_DO_SET_ROI:
            mode = _required_int(p[0], "param1 (ROI mode)")
        if mode == mavlink.MAV_ROI_NONE:
            self._roi = None
            return ("roi_none", {})
        if mode != mavlink.MAV_ROI_LOCATION:
            raise Refused(f"ROI mode {mode} is not supported by the sim vehicle (location is)")
        target = self._reposition_target(p, p7, frame, x, y)
        self._roi = target
        return (
            "roi",
            {
                "latitude_deg": target.latitude_deg,
                "longitude_deg": target.longitude_deg,
                "altitude_amsl_m": round(target.altitude_amsl_m, 3),
            },
        )

    def _reset_battery(self, p: list[float]) -> tuple[str, dict[str, Any]]:
        """MAV_CMD_BATTERY_RESET: its one battery (bit 0 of param1) reads param2 percent
        from now on; the effect to count. Refused for no battery of its own, or a
        percentage that is not one (ArduPilot clamps it; the sim vehicle says so)."""
        k = self._kinematics
        mask = _required_int(p[0], "param1 (battery mask)")
        if not mask & 1:
            raise Refused(f"battery mask {mask} names no battery of the sim vehicle (1: its one)")
        was = k.battery_pct
        k.reset_battery(p[1])
        self._log.warning(
            "battery reset", percent=round(k.battery_pct, 3), was_percent=round(was, 3)
        )
        return ("battery_reset", {"percent": k.battery_pct, "was_percent": round(was, 3)})

    def _set_mode(self, main: int, sub: int) -> None:
        k = self._kinematics
        if main != PX4_MAIN_AUTO:
            raise Refused(f"mode {main}/{sub} not supported by the sim vehicle")
        if sub == PX4_AUTO_LOITER:
            k.hold()
        elif sub == PX4_AUTO_LAND:
            k.land()
        elif sub == PX4_AUTO_RTL:
            k.return_to_launch()
        elif sub == PX4_AUTO_TAKEOFF:
            k.takeoff()
        elif sub == PX4_AUTO_READY:
            return
        else:
            raise Refused(f"auto sub mode {sub} not supported by the sim vehicle")

    def _reposition_target(
        self, p: list[float], p7: float, frame: int | None, x: int | None, y: int | None
    ) -> GeoPoint:
        k = self._kinematics
        here = k.geo_position()
        if x is not None and y is not None:
            latitude, longitude = x / 1e7, y / 1e7
        else:
            latitude, longitude = p[4], p[5]
        relative_frames = (
            mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
            mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        )
        altitude = p7
        if math.isfinite(altitude) and frame in relative_frames:
            altitude += k.geo_home().altitude_amsl_m
        # NaN fields mean "keep the current value", as in the MAVLink spec.
        return GeoPoint(
            latitude if math.isfinite(latitude) and (x is None or x != 0) else here.latitude_deg,
            longitude if math.isfinite(longitude) and (y is None or y != 0) else here.longitude_deg,
            altitude if math.isfinite(altitude) else here.altitude_amsl_m,
        )

    def _set_interval(self, msg_id: int, interval_us: float) -> int:
        if msg_id not in DEFAULT_INTERVALS_S:
            return mavlink.MAV_RESULT_UNSUPPORTED
        if interval_us < 0:
            self._intervals[msg_id] = 0.0  # disabled
        elif interval_us == 0:
            self._intervals[msg_id] = DEFAULT_INTERVALS_S[msg_id]
        else:
            self._intervals[msg_id] = max(MIN_INTERVAL_S, interval_us / 1e6)
        self._next_due.pop(msg_id, None)
        return mavlink.MAV_RESULT_ACCEPTED

    # --- parameters -----------------------------------------------------------------

    def _param(self, msg: Any, kind: str) -> None:
        name = PARAM_TAKEOFF_ALT
        if kind == "PARAM_SET":
            name = _param_name(msg.param_id)
            if name in self._link_loss:
                self._link_loss[name] = float(_int_from_bytewise(msg.param_value))
            elif name == PARAM_GF_ACTION:
                self._geofence_params[name] = float(_int_from_bytewise(msg.param_value))
            elif name == PARAM_GF_MAX_VER_DIST:
                if math.isfinite(msg.param_value) and msg.param_value >= 0:
                    self._geofence_params[name] = float(msg.param_value)
            elif name == PARAM_XY_VEL_MAX:
                if math.isfinite(msg.param_value) and msg.param_value > 0:
                    self._kinematics.max_speed_m_s = float(msg.param_value)
            elif name != PARAM_TAKEOFF_ALT:
                return  # PX4 stays silent about unknown parameters
            elif math.isfinite(msg.param_value) and msg.param_value > 0:
                self._kinematics.takeoff_altitude_m = float(msg.param_value)
        elif kind == "PARAM_REQUEST_READ":
            name = _param_name(msg.param_id)
            if msg.param_index == 0:
                name = PARAM_TAKEOFF_ALT
            elif name not in self._param_names():
                return
        self._send_param(name)

    def _param_names(self) -> list[str]:
        """Every parameter it knows, in index order."""
        return [PARAM_TAKEOFF_ALT, *self._link_loss, *self._geofence_params, PARAM_XY_VEL_MAX]

    def _send_param(self, name: str = PARAM_TAKEOFF_ALT) -> None:
        assert self._mav is not None
        value = self._kinematics.takeoff_altitude_m
        kind = mavlink.MAV_PARAM_TYPE_REAL32
        if name in self._link_loss or name == PARAM_GF_ACTION:
            kind = mavlink.MAV_PARAM_TYPE_INT32
            held = {**self._link_loss, **self._geofence_params}[name]
            value = _int_to_bytewise(round(held))
        elif name == PARAM_GF_MAX_VER_DIST:
            value = self._geofence_params[name]
        elif name == PARAM_XY_VEL_MAX:
            value = self._kinematics.max_speed_m_s
        names = self._param_names()
        self._mav.param_value_send(name.encode(), value, kind, len(names), names.index(name))

    def _watch_link_loss(self, now: float) -> None:
        """PX4's data-link loss failsafe (COM_DL_LOSS_T, NAV_DLL_ACT): in the air with no
        ground station heard for the time, the vehicle returns home, once per loss."""
        seen = self._gcs_seen_at
        k = self._kinematics
        if seen is None or self._link_loss[PARAM_DLL_ACT] != RETURN_ON_LINK_LOSS:
            return
        lost = (now - seen) * self.speedup >= self._link_loss[PARAM_DL_LOSS_T]
        if not lost:
            self._link_loss_acted = False
        elif not self._link_loss_acted and k.in_air and k.phase is not Phase.RETURN:
            self._link_loss_acted = True
            k.return_to_launch()
            self.effects.record("link_loss_return", system_id=self.system_id)
            self._log.warning("ground station lost: returning (NAV_DLL_ACT)")

    def _watch_fence(self) -> None:
        """PX4's geofence action (GF_ACTION, GF_MAX_VER_DIST over the uploaded fence): in
        the air and out of the fence, Return (3) or Land (5), once per breach; the drone
        service acts on the same breach from its telemetry, this is the vehicle's own."""
        k, fence = self._kinematics, self._fence
        action = round(self._geofence_params[PARAM_GF_ACTION])
        if fence is None or action not in (GF_RETURN, GF_LAND) or not k.in_air:
            return
        here = k.geo_position()
        ceiling = self._geofence_params[PARAM_GF_MAX_VER_DIST] or math.inf
        bounded = replace(fence, ceiling_m=ceiling)
        if bounded.outside(here.latitude_deg, here.longitude_deg, k.relative_altitude_m) is None:
            self._fence_acted = False
        elif not self._fence_acted and k.phase not in (Phase.RETURN, Phase.LAND):
            self._fence_acted = True
            if action == GF_RETURN:
                k.return_to_launch()
            else:
                k.land()
            self.effects.record("fence_breach", system_id=self.system_id, action=action)
            self._log.warning("out of the fence: acting (GF_ACTION)", action=action)


def _receive_stamped(sock: socket.socket) -> tuple[bytes, tuple[str, int], float]:
    """One datagram, its sender and when it reached the socket (wall clock; the
    kernel's stamp where there is one, else now)."""
    data, ancillary, _, address = sock.recvmsg(65535, socket.CMSG_SPACE(_TIMESPEC.size))
    for level, kind, payload in ancillary:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS:
            seconds, nanoseconds = _TIMESPEC.unpack_from(payload)
            return data, address, seconds + nanoseconds / 1e9
    return data, address, time.time()


def _int_or(value: float, default: int) -> int:
    """An integer command parameter; NaN (MAVLink's "unset") gives the default."""
    return default if not math.isfinite(value) else round(value)


def _required_int(value: float, name: str) -> int:
    """An integer command parameter that has no default: unset (NaN) is refused."""
    if not math.isfinite(value):
        raise Refused(f"{name} must be set, got {value}")
    return round(value)


def _int_from_bytewise(value: float) -> int:
    """An INT32 parameter's value as PX4 carries it in a float field: its four bytes."""
    return int(struct.unpack("<i", struct.pack("<f", value))[0])


def _int_to_bytewise(value: int) -> float:
    """The float field whose four bytes are the INT32 ``value`` (PX4's encoding)."""
    return float(struct.unpack("<f", struct.pack("<i", value))[0])


def _param_name(raw: str | bytes) -> str:
    text = raw.decode(errors="replace") if isinstance(raw, bytes) else raw
    return text.rstrip("\x00")

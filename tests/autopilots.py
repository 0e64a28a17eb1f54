"""Autopilots for the tests: ArduPilot SITL as a real process, and a monitor of its own.

``Sitl`` runs ``baton sitl`` (baton's supervised wrapper of an ArduCopter
SITL build, found as ``baton sitl`` finds it: ``BATON_SITL_BINARY``, else
``arducopter`` on PATH) and can kill -9 and restart it on the same
instance. ``TelemetryMonitor`` holds a second MAVLink connection to SITL's
SERIAL1 with pymavlink, independent of the drone service and MAVSDK, and
records where SITL itself says the vehicle was: the witness the tests check
pictures against.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from pymavlink import mavutil

from baton.sitl.launcher import HOW_TO_POINT_AT_A_BUILD, SitlBinaryNotFound, find_binary

SITL_SPEEDUP = 10.0
SKIP_REASON = (
    f"the sitl tests fly ArduPilot Copter SITL, and none was found: {HOW_TO_POINT_AT_A_BUILD}"
)


def sitl_binary() -> Path | None:
    """The SITL binary the tests fly (``BATON_SITL_BINARY``, else ``arducopter`` on
    PATH), or None where this machine has none."""
    try:
        return find_binary(None, os.environ)
    except SitlBinaryNotFound:
        return None


class Sitl:
    """``baton sitl`` as a process: start, kill -9, restart on the same instance."""

    def __init__(
        self, workdir: Path, speedup: float = SITL_SPEEDUP, mavlink_key: Path | None = None
    ) -> None:
        self.workdir = workdir
        self.speedup = speedup
        # With a key, SITL holds it and url is SERIAL1, monitor_url SERIAL2 (signed only).
        self.mavlink_key = mavlink_key
        self.process: subprocess.Popen[bytes] | None = None
        self.url = ""
        self.monitor_url = ""
        self.instance: int | None = None

    def start(self, timeout_s: float = 30.0) -> None:
        """Starts SITL (the same instance again after a kill) and waits for its ports."""
        ready = self.workdir / "sitl.url"
        ready.unlink(missing_ok=True)
        argv = [
            sys.executable,
            "-m",
            "baton.cli",
            "--die-with-parent",
            str(os.getpid()),
            "sitl",
            "--speedup",
            str(self.speedup),
            "--workdir",
            str(self.workdir / "sitl"),
            "--url-file",
            str(ready),
        ]
        if self.instance is not None:
            argv += ["--instance", str(self.instance)]
        if self.mavlink_key is not None:
            argv += ["--mavlink-key", str(self.mavlink_key)]
        log = (self.workdir / "sitl.log").open("ab")
        self.process = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout_s
        while not ready.exists():
            if self.process.poll() is not None:
                raise RuntimeError(f"baton sitl exited: {(self.workdir / 'sitl.log').read_text()}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"SITL not listening after {timeout_s} s")
            time.sleep(0.05)
        self.url, self.monitor_url = ready.read_text().split()
        self.instance = (int(self.url.rsplit(":", 1)[1]) - 5760) // 10

    def kill(self) -> None:
        """kill -9 of the autopilot itself (the wrapper goes with it)."""
        assert self.process is not None
        children = subprocess.run(
            ["pgrep", "-P", str(self.process.pid)], capture_output=True, text=True
        ).stdout.split()
        for pid in children:
            os.kill(int(pid), signal.SIGKILL)
        self.process.kill()
        self.process.wait(10)

    def stop(self) -> None:
        """SIGTERM, then SIGKILL."""
        if self.process is None or self.process.poll() is not None:
            return
        self.process.terminate()
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait(5)


@dataclass
class Sample:
    """Where SITL said the vehicle was, at a wall time of this machine."""

    at: float
    latitude_deg: float
    longitude_deg: float
    relative_altitude_m: float
    ground_speed_m_s: float
    boot_s: float = 0.0  # the vehicle's own clock (time_boot_ms), in its simulated seconds


@dataclass(frozen=True)
class ModeReport:
    """An autopilot's HEARTBEAT: its flight mode by pymavlink's name (ArduCopter's
    custom_mode: GUIDED, RTL, LAND, BRAKE...) and whether it is armed, at a wall time."""

    at: float
    mode: str
    armed: bool


def mode_report(heartbeat: Any, at: float) -> ModeReport | None:
    """The autopilot's own HEARTBEAT as a ModeReport; None for anyone else's (a ground
    station's, the drone's, another component's)."""
    if heartbeat.autopilot == mavutil.mavlink.MAV_AUTOPILOT_INVALID:
        return None
    if heartbeat.get_srcComponent() != mavutil.mavlink.MAV_COMP_ID_AUTOPILOT1:
        return None
    armed = bool(heartbeat.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
    return ModeReport(at, mavutil.mode_string_v10(heartbeat), armed)


@dataclass
class TelemetryMonitor:
    """Records an autopilot's GLOBAL_POSITION_INT, HOME_POSITION and its HEARTBEATs'
    flight modes (``modes``) with pymavlink.

    SITL's SERIAL1 (``tcp:HOST:PORT``) or the sim vehicle's port (``udpout:HOST:PORT``).
    """

    url: str
    speedup: float = 1.0  # the vehicle's simulated seconds per wall second
    samples: list[Sample] = field(default_factory=list)
    homes: list[tuple[float, float, float]] = field(default_factory=list)  # (at, lat, lon)
    modes: list[ModeReport] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def start(self) -> None:
        """Connects and starts recording in a thread."""
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stops recording."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10)

    def _run(self) -> None:
        link = mavutil.mavlink_connection(self.url, source_system=254, autoreconnect=True)

        def beat() -> None:  # as a ground station does, 1 Hz: a UDP vehicle forgets silent ones
            link.mav.heartbeat_send(
                mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
            )

        beat()
        link.wait_heartbeat(timeout=30)
        beaten = time.monotonic()
        for msg_id, hz in (
            (mavutil.mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 20),
            (mavutil.mavlink.MAVLINK_MSG_ID_HOME_POSITION, 2),
        ):
            link.mav.command_long_send(
                link.target_system,
                link.target_component,
                mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                0,
                msg_id,
                1e6 / hz,
                0,
                0,
                0,
                0,
                0,
            )
        while not self._stop.is_set():
            if time.monotonic() - beaten >= 1.0:
                with contextlib.suppress(OSError):
                    beat()
                beaten = time.monotonic()
            try:
                msg = link.recv_match(
                    type=["GLOBAL_POSITION_INT", "HOME_POSITION", "HEARTBEAT"], timeout=0.5
                )
            except OSError:
                break  # SITL stopped at the end of the run
            if msg is None:
                continue
            now = time.time()
            if msg.get_type() == "GLOBAL_POSITION_INT":
                self.samples.append(
                    Sample(
                        now,
                        msg.lat / 1e7,
                        msg.lon / 1e7,
                        msg.relative_alt / 1000,
                        math.hypot(msg.vx, msg.vy) / 100,
                        msg.time_boot_ms / 1000,
                    )
                )
            elif msg.get_type() == "HOME_POSITION":
                self.homes.append((now, msg.latitude / 1e7, msg.longitude / 1e7))
            elif (report := mode_report(msg, now)) is not None:
                self.modes.append(report)
        with contextlib.suppress(AttributeError, OSError):  # already gone with SITL
            link.close()

    def position_at(self, at: float) -> Sample:
        """The sample nearest to wall time ``at`` (``sent_at``)."""
        assert self.samples, "the monitor recorded no position"
        return min(self.sent_at(), key=lambda s: abs(s.at - at))

    def sent_at(self) -> list[Sample]:
        """The samples at the wall time the vehicle sent them, as near as it can be told.

        A sample is stamped when this thread reads it; on a loaded machine the thread
        may not run for a while and then reads what queued meanwhile in a burst, all
        stamped alike (a run read a sample 9.9 m short of a waypoint as the position
        at its picture). By the vehicle's own clock, a sample was sent at the latest
        as long before each later one as their clocks differ: the earliest of those
        bounds and its own stamp."""
        placed: list[Sample] = []
        later: Sample | None = None
        for sample in reversed(self.samples):
            at = sample.at
            if later is not None and later.boot_s >= sample.boot_s:  # not across a reboot
                at = min(at, later.at - (later.boot_s - sample.boot_s) / self.speedup)
            later = replace(sample, at=at)
            placed.append(later)
        return placed[::-1]


def distance_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Horizontal metres between two WGS84 points (flat Earth, fine over kilometres)."""
    north = math.radians(lat2 - lat1) * 6_378_137.0
    east = math.radians(lon2 - lon1) * 6_378_137.0 * math.cos(math.radians((lat1 + lat2) / 2))
    return math.hypot(north, east)

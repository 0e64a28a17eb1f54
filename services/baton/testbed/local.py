"""The local testbed: sim vehicle, drone service, links and controllers on loopback.

``LocalTestbed`` starts every part as a real process (``baton sim-vehicle``,
``baton drone``, ``baton link`` on every link, ``baton controller`` with the
mission program), writes the testbed configuration they all read, follows the
mission through the services' status RPCs, and stops everything. The tests,
``baton testbed`` and the benchmarks all run missions through it.

The sim vehicle and the drone's camera count their side effects in files of
the workdir (``baton.effects``), which every snapshot reads: the report's
exactly-once check that does not rest on the drone's own audit.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import random
import signal
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc
import yaml

from baton.certs.make import ensure
from baton.config import BatonConfig, LinkSpec, controllers_only, merge, parse_config
from baton.drone.camera import THUMBNAIL_GLOB
from baton.effects import read_effects
from baton.lifecycle import write_atomically
from baton.missions import corridor as corridor_mission
from baton.missions import grid as grid_mission
from baton.rpc.channels import aio_channel
from baton.rpc.labels import label
from baton.rpc.methods import path
from baton.rpc.mission import MISSION_TOKEN_ENV
from baton.rpc.tls import CA_CERT, OPERATOR, Identity, Tls
from baton.signing import read_key
from baton.testbed.battery import reset_battery
from baton.testbed.faults import Fault, FaultInjector, PartDeath, check_parts
from baton.testbed.plan_fence import with_plan_fence
from baton.testbed.supervisor import ManagedProcess, PartNotReady, Supervisor, baton_argv
from baton.v1 import drone_pb2, drone_pb2_grpc, ring_pb2, ring_pb2_grpc

GRID_MISSION = Path(grid_mission.__file__)
CORRIDOR_MISSION = Path(corridor_mission.__file__)
MISSION_KINDS = ("grid", "corridor")
TAKE_PICTURE = path("Camera.TakePicture")

# The local testbed's own defaults, where its configuration says nothing: the paper's
# three controllers, ten times real time (BatonConfig's flush limit default, 2 MB, is the
# testbed's too), and the paper's links: 20 ms and 25 Mbit/s between controllers, WiFi
# to the drone.
DEFAULT_CONTROLLERS = 3
DEFAULT_SPEEDUP = 10.0
PAPER_CONTROLLER_LINK = LinkSpec(latency=0.020, bandwidth=25e6)
WIFI_DRONE_LINK = LinkSpec(latency=0.002, bandwidth=20e6)


def with_testbed_defaults(config: BatonConfig, from_file: bool) -> BatonConfig:
    """``config`` with the local testbed's own defaults where it says nothing: the paper's
    links where it emulates none, and, when it is not a testbed file, speed-up 10."""
    own = [
        ("controller_link", None if config.controller_link.emulated else PAPER_CONTROLLER_LINK),
        ("drone_link", None if config.drone_link.emulated else WIFI_DRONE_LINK),
        ("speedup", None if from_file else DEFAULT_SPEEDUP),
    ]
    return config.model_copy(update={name: value for name, value in own if value is not None})


def local_config(controllers: int = DEFAULT_CONTROLLERS, **fields: Any) -> BatonConfig:
    """The one model of a local testbed without a file: ``controllers`` controllers (the
    testbed picks their ports), its own defaults, and ``fields`` over them, validated
    (BatonConfig's fields: ``flush_limit=0``, ``speedup=20.0``, ``drone_link=LinkSpec(...)``,
    ``ring={"forwarding": "store-and-forward"}``; None: not given)."""
    config = with_testbed_defaults(controllers_only(range(controllers)), from_file=False)
    return merge(config, ((name, name, value) for name, value in fields.items()))


@dataclass(frozen=True)
class MissionPlan:
    """The survey the testbed flies and its parameters: the paper's grid
    (``baton.missions.grid``) or a corridor (``baton.missions.corridor``)."""

    grid: int = 5
    spacing_m: float = 50.0
    altitude_m: float = 10.0
    speed_m_s: float = 5.0
    poll_s: float = 1.0
    kind: str = "grid"  # or "corridor"
    length_m: float = 1500.0  # the corridor's
    bearing_deg: float = 90.0  # the corridor's direction from the take-off point (east)

    def __post_init__(self) -> None:
        if self.kind not in MISSION_KINDS:
            raise ValueError(f"unknown mission {self.kind!r}; use one of {MISSION_KINDS}")

    @property
    def file(self) -> Path:
        """The mission program."""
        return GRID_MISSION if self.kind == "grid" else CORRIDOR_MISSION

    def args(self) -> list[str]:
        """``--mission-arg`` values for ``baton controller``."""
        shape: dict[str, float] = (
            {"grid": self.grid}
            if self.kind == "grid"
            else {"length_m": self.length_m, "bearing_deg": self.bearing_deg}
        )
        common = ("spacing_m", "altitude_m", "speed_m_s", "poll_s")
        values = {**shape, **{name: getattr(self, name) for name in common}}
        return [f"{name}={value}" for name, value in values.items()]

    def targets(self) -> list[tuple[float, float]]:
        """The waypoints, metres (north, east) of the take-off point, in flying order."""
        if self.kind == "grid":
            return grid_mission.waypoints(self.grid, self.spacing_m)
        return corridor_mission.waypoints(self.length_m, self.spacing_m, self.bearing_deg)

    def describe(self) -> str:
        """For a person: "5x5 grid", "corridor of 1500 m"."""
        if self.kind == "grid":
            return f"{self.grid}x{self.grid} grid"
        toward = "" if self.bearing_deg == 90.0 else f" toward {self.bearing_deg:g} deg"
        return f"corridor of {self.length_m:g} m{toward}"


@dataclass(frozen=True)
class TestbedPlan:
    """What to run: the one configuration model (controllers, ring, protocol parameters,
    links, policy, TLS), and the handovers, the mission and how the parts are started."""

    __test__ = False  # not a pytest test class, despite its name

    config: BatonConfig = field(default_factory=local_config)
    # ``config`` is a testbed file's (``--config``): its addresses and certificate
    # folder are used as they are. Otherwise the testbed picks free ports on loopback
    # and makes the certificates in the workdir.
    from_file: bool = False
    handovers: tuple[tuple[int, int], ...] = ()  # (after reqnr, new master)
    # The scripted handovers are prepared ones (docs/design.md, "Prepared handover").
    prepared: bool = False
    mission: MissionPlan = MissionPlan()
    # A mission program of one's own (given only mission_args); default: the
    # plan's mission, grid or corridor, with its parameters.
    mission_file: Path | None = None
    emulate_links: bool = True
    resolution: str | None = None
    drone_args: tuple[str, ...] = ()  # extra `baton drone` options (e.g. --force-race)
    # Extra `baton link` options by link name ("link-drone-0", "link-ring-1"),
    # e.g. an asymmetric link: (("link-drone-0", ("--up-latency", "3s")),).
    link_args: tuple[tuple[str, tuple[str, ...]], ...] = ()
    # Link emulators cut before the controllers start ("link-ring-1"): what must not get
    # through from the mission's first request on, whatever the machine's speed
    # (``restore_link`` brings one back).
    links_cut: tuple[str, ...] = ()
    # Extra `baton sim-vehicle` options (e.g. --battery-capacity-wh 8).
    vehicle_args: tuple[str, ...] = ()
    mission_args: tuple[str, ...] = ()  # extra mission parameters, key=value
    # The controllers' mission token (baton.rpc.mission), for a caller that acts
    # as a mission program itself (the micro benchmark); default: each makes one.
    mission_token: str | None = None
    # The Python that runs the mission program on every controller (``baton
    # controller --mission-python``), e.g. a virtualenv with only baton-sdk.
    mission_python: Path | None = None
    # The autopilot: "sim" (the embedded sim vehicle), "sitl" (ArduPilot SITL,
    # started by the testbed at the same speed-up) or the MAVLink URL of one
    # that runs already.
    vehicle: str = "sim"
    # None: ``baton sitl`` finds one (baton.sitl.launcher.find_binary).
    sitl_binary: Path | None = None
    # SITL's own parameters of this run over its defaults (``baton sitl --param``), e.g.
    # (("BATT_CAPACITY", 1000.0),): what vehicle_args are to the sim vehicle.
    sitl_params: tuple[tuple[str, float], ...] = ()
    # A QGroundControl plan the mission file flies (baton.missions.plan), for the
    # report's side-effect check; None for the grid or another mission.
    flight_plan: Path | None = None
    # A part that dies (killed from outside, crashed) is reported and the run goes on
    # while the mission can (``baton testbed``); False: it fails the run (PartDied), as
    # a test wants when a part crashes.
    keep_going: bool = False
    # A dead part is started again with its command line (and state, log file and
    # address), as a supervisor would (``baton testbed --restart-parts``).
    restart_parts: bool = False
    faults: tuple[Fault, ...] = ()  # ``baton testbed --fault``, fired by FaultInjector

    def all_mission_args(self) -> list[str]:
        """Every ``--mission-arg`` the controllers' mission program gets."""
        own = self.mission.args() if self.mission_file is None else []
        return [*own, *self.mission_args]

    @property
    def program(self) -> Path:
        """The mission file the controllers run: one's own, else the survey's."""
        return self.mission_file or self.mission.file

    def part_names(self) -> list[str]:
        """The parts this plan starts, by name (what ``--fault`` may name)."""
        names = ["drone"]
        if self.vehicle in ("sim", "sitl"):
            names.append("sim-vehicle" if self.vehicle == "sim" else "sitl")
        for cid in self.config.ring_order:
            names.append(f"controller-{cid}")
            if self.emulate_links:
                names += [f"link-ring-{cid}", f"link-drone-{cid}"]
        return names

    def describe_mission(self) -> str:
        """For a person, the mission flown: "5x5 grid", "corridor of 1500 m", "plan
        survey.plan", "mission my_mission.py"."""
        if self.flight_plan is not None:
            return f"plan {self.flight_plan.name}"
        if self.mission_file is not None:
            return f"mission {self.mission_file.name}"
        return self.mission.describe()


# The side effects counted where they happen (baton.effects), in the workdir.
VEHICLE_EFFECTS_FILE = "vehicle-effects.jsonl"  # commands the sim vehicle acted on
CAMERA_EFFECTS_FILE = "camera-effects.jsonl"  # pictures the drone's camera produced
THUMBNAILS_DIR = "thumbnails"  # a small JPEG of each picture (baton drone --thumbnails-dir)
# Where the sim vehicle is, for the link emulators' radio range (link/radio.py).
VEHICLE_POSITION_FILE = "vehicle-position.json"

# The drone's telemetry logs (``baton drone --tlog-dir``), one per drone process.
TLOG_GLOB = "drone_*.tlog"

# Wall seconds the testbed waits for the vehicle to become ready (armable)
# before it starts the mission: ArduPilot needs ~45 s of its own time after boot.
VEHICLE_READY_TIMEOUT_S = 180.0

# Ports the kernel hands out for port 0 and for outgoing connections; fixed
# ports are chosen below them, so that no link emulator binding port 0 and no
# client connection can take a port between choosing it and binding it.
_EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
_FIXED_PORTS_FROM = 20_000
# LOW-HIGH: the ports free_port draws from (HIGH excluded), for processes that start
# testbeds at the same time (the test suite gives each pytest-xdist worker its share).
FREE_PORTS_ENV = "BATON_FREE_PORTS"


# Ports free_port returned in this process: never twice.
_HANDED_OUT: set[int] = set()


def free_port_range() -> tuple[int, int]:
    """Where free_port draws (HIGH excluded): ``BATON_FREE_PORTS=LOW-HIGH`` where set,
    else from 20,000 up to the kernel's ephemeral range."""
    given = os.environ.get(FREE_PORTS_ENV)
    if given:
        low, _, high = given.partition("-")
        if not (low.isdigit() and high.isdigit() and 0 < int(low) < int(high) <= 65_536):
            raise ValueError(
                f"{FREE_PORTS_ENV}={given!r}: expected LOW-HIGH, two port numbers with LOW "
                "below HIGH (e.g. 20000-26000), or leave it unset"
            )
        return int(low), int(high)
    try:
        ephemeral_low = int(_EPHEMERAL_RANGE.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        ephemeral_low = 32_768
    return _FIXED_PORTS_FROM, max(ephemeral_low, _FIXED_PORTS_FROM + 1000)


def free_port() -> int:
    """A TCP port free on loopback now, outside the kernel's ephemeral range, and not one
    this process handed out before (drawn at random, two parts of one testbed drew the
    same free port: "controllers 0 and 1 both listen on ...", a flaky test)."""
    low, high = free_port_range()
    for _ in range(200):
        port = random.randrange(low, high)
        if port in _HANDED_OUT:
            continue
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            _HANDED_OUT.add(port)
            return port
    raise OSError(f"no free port on 127.0.0.1 between {low} and {high - 1}")


def _link_args(spec: LinkSpec) -> list[str]:
    if not spec.emulated:
        return ["--off"]
    args = ["--latency", f"{spec.latency}s"]
    if spec.bandwidth is not None:
        args += ["--bandwidth", f"{spec.bandwidth}bit"]
    return args


def remove_sqlite(path: Path) -> None:
    """Deletes a SQLite file of an earlier run, its WAL and shared-memory files too."""
    for part in (path, path.with_name(path.name + "-wal"), path.with_name(path.name + "-shm")):
        part.unlink(missing_ok=True)


async def drone_status(
    stub: drone_pb2_grpc.DroneAsyncStub, audit: bool = True, wait_for_ready: bool = False
) -> drone_pb2.DroneStatus:
    """The drone's status with, if ``audit``, every audit entry it holds (page by page)."""
    request = drone_pb2.GetDroneStatusRequest(include_audit=audit)
    status: drone_pb2.DroneStatus = await stub.GetStatus(
        request, timeout=10, wait_for_ready=wait_for_ready
    )
    while status.audit_more:
        request.audit_after_reqnr = status.audit[-1].reqnr
        page = await stub.GetStatus(request, timeout=10, wait_for_ready=wait_for_ready)
        status.audit.extend(page.audit)
        status.audit_more = page.audit_more
    return status


def handover_file_text(handovers: tuple[tuple[int, int], ...], prepared: bool = False) -> str:
    """The drone's handover script: ``reqnr mid`` lines (``reqnr mid prepared``)."""
    kind = " prepared" if prepared else ""
    return "".join(f"{reqnr} {mid}{kind}\n" for reqnr, mid in handovers)


Effects = list[dict[str, Any]]


@dataclass
class Snapshot:
    """The drone's and every controller's status at one moment, and the side effects
    counted where they happened: each command the sim vehicle acted on, each picture
    the camera produced (``baton.effects`` lines; None where nothing counts them:
    SITL, an autopilot that runs already, the compose testbed)."""

    drone: drone_pb2.DroneStatus
    controllers: dict[int, ring_pb2.ControllerStatus] = field(default_factory=dict)
    vehicle_effects: Effects | None = None
    camera_effects: Effects | None = None
    # Parts not answering on purpose or dead, by name: "dead", "stopped", "cut" (a fault).
    absent: dict[str, str] = field(default_factory=dict)

    @property
    def missions_ended(self) -> bool:
        """Every controller's mission program has ended (done or failed), and no
        prepared handover is still under way at the drone: one the script began near
        the end moves the master once its target caught up (the master's word) or at
        the prepare timeout, after the last request."""
        ended = all(
            c.mission in (ring_pb2.MISSION_STATE_DONE, ring_pb2.MISSION_STATE_FAILED)
            for c in self.controllers.values()
        )
        return ended and self.drone.preparing_for < 0

    @property
    def pictures(self) -> int:
        """Pictures the drone has taken."""
        return sum(1 for a in self.drone.audit if a.method == TAKE_PICTURE)


class LocalTestbed:
    """Every part of one testbed run, as supervised processes."""

    def __init__(self, plan: TestbedPlan, workdir: Path) -> None:
        self.plan = plan
        self.workdir = workdir
        self.supervisor = Supervisor(workdir / "logs")
        self.config: BatonConfig | None = None
        self.config_path = workdir / "testbed.yaml"
        self._channels: list[grpc.aio.Channel] = []
        self.drone_stub: drone_pb2_grpc.DroneAsyncStub | None = None
        self.controller_stubs: dict[int, ring_pb2_grpc.ControllerRingAsyncStub] = {}
        # The operator's certificate the testbed calls with; None: insecure.
        self.tls: Tls | None = None
        self.dead: set[int] = set()  # controllers killed on purpose, not restarted
        # SITL's second MAVLink port (tcp:HOST:PORT), for an independent monitor.
        self.sitl_monitor_url: str | None = None
        # Every part that died while the mission ran, in order (``keep_going``).
        self.deaths: list[PartDeath] = []
        self._seen_dead: set[int] = set()  # pids whose death is recorded
        # Parts a fault holds down (a cut link, a kill with for=): not restarted meanwhile.
        self.held_down: set[str] = set()
        # Why the run ended before the mission did (the drone died, not restarted).
        self.ended_early = ""
        self.started_at = 0.0  # monotonic, when the controllers started
        # Where the testbed says what happens to its parts (faults, deaths, restarts).
        self.say: Callable[[str], None] = print
        self.injector = FaultInjector(self, plan.faults, lambda text: self.say(text))

    # -- start ----------------------------------------------------------------------

    async def start(
        self, vehicle_wait: Callable[[drone_pb2.DroneStatus], None] | None = None
    ) -> BatonConfig:
        """Starts every part; returns the configuration they run with.

        The controllers (and so the mission) start only once the vehicle is
        ready to arm; ``vehicle_wait`` sees the drone's status meanwhile.
        """
        plan = self.plan
        config = plan.config
        try:
            check_parts(plan.faults, plan.part_names())
        except ValueError as exc:
            raise PartNotReady(str(exc)) from None
        links = [name for name in plan.part_names() if name.startswith("link-")]
        unknown = sorted(set(plan.links_cut) - set(links))
        if unknown:
            raise PartNotReady(
                f"TestbedPlan.links_cut: {', '.join(unknown)} is no link emulator of this "
                f"testbed; its links: {', '.join(links) or 'none (emulate_links is off)'}"
            )
        if plan.flight_plan is not None:  # flown in its fence (testbed/plan_fence.py)
            try:
                config = with_plan_fence(config, plan.flight_plan)
            except ValueError as exc:
                raise PartNotReady(str(exc)) from None
        if config.radio_range and (plan.vehicle != "sim" or not plan.emulate_links):
            raise PartNotReady(
                "radio_range needs the sim vehicle (its position file) and the link emulators; "
                "run with --vehicle sim and without --no-links, or set radio_range: false"
            )
        ids = config.ring_order
        if plan.from_file:
            own = {c.id: c.address for c in config.controllers}
            drone_address = config.drone.address
        else:
            own = {cid: f"127.0.0.1:{free_port()}" for cid in ids}
            drone_address = f"127.0.0.1:{free_port()}"
        # The vehicle and the link emulators need nothing of each other: they start
        # together (one after the other, a second each, was most of a test's start).
        parts = [] if (vehicle := self._vehicle_part()) is None else [vehicle]
        if plan.emulate_links:
            for cid in ids:
                parts.append(self._link_part(f"link-ring-{cid}", own[cid], config.controller_link))
                parts.append(
                    self._link_part(
                        f"link-drone-{cid}", drone_address, config.drone_link, self._radio_args(cid)
                    )
                )
        announced = dict(
            zip(
                (name for name, _, _ in parts),
                await self.supervisor.start_ready_together(parts),
                strict=True,
            )
        )
        vehicle_url = self._vehicle_url(announced)
        controllers = []
        for cid in ids:
            entry: dict[str, Any] = {"id": cid, "address": own[cid]}
            if plan.emulate_links:
                entry["peer_address"] = announced[f"link-ring-{cid}"]
                entry["drone_address"] = announced[f"link-drone-{cid}"]
            original = config.controller(cid)
            if original.location is not None:
                entry["location"] = original.location.model_dump()
            if original.range_m is not None:
                entry["range_m"] = original.range_m
            controllers.append(entry)
        drone: dict[str, Any] = {
            "address": drone_address,
            "vehicle_url": vehicle_url,
            "home": config.drone.home.model_dump(),
        }
        if self._mavlink_key() is not None:
            drone["mavlink_key"] = str(self._mavlink_key())
        if config.drone.gcs:  # ground stations watching live (drone/gcs.py)
            drone["gcs"] = list(config.drone.gcs)
            drone["gcs_override"] = config.drone.gcs_override
        document: dict[str, Any] = {
            "drone": drone,
            "controllers": controllers,
            "ring": self._ring(ids),
            "initial_master": config.master_id,
            "flush_limit": config.flush_limit,
            "speedup": config.speedup,
            "prepare_timeout": config.prepare_timeout,
            # Given to the parts as given to the testbed (a file's takeover_after was
            # silently dropped: every part ran with the default).
            "takeover_after": config.takeover_after,
            "drone_retry_limit": config.drone_retry_limit,
        }
        if config.max_log_message is not None:
            document["max_log_message"] = config.max_log_message
        if plan.emulate_links:
            document["controller_link"] = config.controller_link.model_dump()
            document["drone_link"] = config.drone_link.model_dump()
        document["handover_policy"] = config.handover_policy.model_dump()
        document["radio_range"] = config.radio_range
        document["safety"] = config.safety.model_dump()
        if config.radio_fade is not None:
            document["radio_fade"] = config.radio_fade.model_dump()
        document["tls"] = self._certificates(ids)
        self.config_path.write_text(yaml.safe_dump(document, sort_keys=False))
        self.config = parse_config(document, str(self.config_path))
        await self._start_drone()
        await self.wait_vehicle_ready(VEHICLE_READY_TIMEOUT_S, vehicle_wait)
        for name in plan.links_cut:
            await self.cut_link(name)
        await self._start_controllers()
        self.started_at = time.monotonic()
        return self.config

    def _certificates(self, ids: list[int]) -> dict[str, Any]:
        """The testbed file's ``tls``: the given file's certificate folder if it holds a
        CA, else one made in the workdir (missing parts added); or insecure."""
        tls = self.plan.config.tls
        if tls.insecure:
            return {"insecure": True}
        folder = self.workdir / "certs"
        if self.plan.from_file and (tls.certs / CA_CERT).exists():
            folder = tls.certs
        drone = self.plan.config.drone_identity
        ensure(folder, [*(Identity.controller(cid) for cid in ids), drone, OPERATOR])
        self.tls = Tls.load(folder, OPERATOR)
        return {"certs": str(folder.resolve())}

    def _radio_args(self, cid: int) -> list[str]:
        """``baton link`` options of controller ``cid``'s link to the drone: its radio
        range, from the testbed file, when the file asks for radio range."""
        config = self.plan.config
        if not config.radio_range:
            return []
        station = config.controller(cid)
        assert station.location is not None and station.range_m is not None
        where = f"{station.location.latitude_deg},{station.location.longitude_deg}"
        position = self.workdir / VEHICLE_POSITION_FILE
        fade = [] if config.radio_fade is None else ["--fade", config.radio_fade.link_arg()]
        return ["--range", f"{where},{station.range_m}", "--position-file", str(position), *fade]

    def _home(self) -> str:
        home = self.plan.config.drone.home
        return f"{home.latitude_deg},{home.longitude_deg},{home.altitude_m}"

    def _vehicle_part(self) -> tuple[str, list[str], Path] | None:
        """The sim vehicle or SITL to start, as planned (name, argv, ready file); None for
        an autopilot that runs already."""
        vehicle = self.plan.vehicle
        if vehicle not in ("sim", "sitl"):
            return None
        ready = self.workdir / "vehicle.url"
        speedup = str(self.plan.config.speedup)
        if vehicle == "sim":
            # A new run counts from zero; a restarted vehicle of this run (the
            # same argv) appends to the same file.
            effects = self.workdir / VEHICLE_EFFECTS_FILE
            effects.unlink(missing_ok=True)
            argv = baton_argv("sim-vehicle", "--speedup", speedup, "--url-file", str(ready))
            argv += ["--home", self._home(), "--effects-file", str(effects)]
            if self.plan.config.radio_range:
                position = self.workdir / VEHICLE_POSITION_FILE
                position.unlink(missing_ok=True)
                argv += ["--position-file", str(position)]
            argv += self._mavlink_key_args()
            argv += self.plan.vehicle_args
            return "sim-vehicle", argv, ready
        argv = baton_argv("sitl", "--speedup", speedup, "--home", self._home())
        argv += ["--workdir", str(self.workdir / "sitl"), "--url-file", str(ready)]
        if self.plan.sitl_binary is not None:
            argv += ["--sitl-binary", str(self.plan.sitl_binary)]
        for name, value in self.plan.sitl_params:
            argv += ["--param", f"{name}={value:.10g}"]
        argv += self._mavlink_key_args()
        return "sitl", argv, ready

    def _vehicle_url(self, announced: dict[str, str]) -> str:
        """The drone's vehicle URL, from what the started vehicle announced."""
        if "sim-vehicle" in announced:
            return announced["sim-vehicle"].splitlines()[0]
        if "sitl" in announced:
            url, self.sitl_monitor_url = announced["sitl"].split()
            return url
        return self.plan.vehicle  # an autopilot that runs already

    def _ring(self, ids: list[int]) -> dict[str, Any]:
        """The testbed file's ring: the configuration's, in the order ``ids``."""
        return {**self.plan.config.ring.model_dump(), "order": ids}

    def _mavlink_key(self) -> Path | None:
        """The testbed file's MAVLink signing key (drone.mavlink_key), if any."""
        key = self.plan.config.drone.mavlink_key
        return key.resolve() if key is not None else None

    def _mavlink_key_args(self) -> list[str]:
        """The vehicle holds the drone's key: ``--mavlink-key`` for sim-vehicle and sitl."""
        key = self._mavlink_key()
        return ["--mavlink-key", str(key)] if key is not None else []

    def _link_part(
        self, name: str, target: str, spec: LinkSpec, radio: list[str] | None = None
    ) -> tuple[str, list[str], Path]:
        """Link emulator ``name`` in front of ``target`` (name, argv, ready file), with
        ``radio``: its radio range options (``_radio_args``)."""
        ready = self.workdir / f"{name}.address"
        argv = baton_argv(
            "link",
            "--listen",
            "127.0.0.1:0",
            "--target",
            target,
            *_link_args(spec),
            *(radio or []),
            *dict(self.plan.link_args).get(name, ()),
            "--shape-file",
            str(self._shape_file(name)),
            "--address-file",
            str(ready),
        )
        return name, argv, ready

    def _shape_file(self, name: str) -> Path:
        """Where link emulator ``name`` reads a new shape on SIGHUP (``reshape_link``)."""
        return self.workdir / f"{name}.shape.json"

    async def _start_drone(self) -> None:
        assert self.config is not None
        script = self.workdir / "handovers.txt"
        script.write_text(handover_file_text(self.plan.handovers, self.plan.prepared))
        ready = self.workdir / "drone.address"
        # A new mission: no state and no pictures of an earlier run in this
        # workdir (a restarted drone of this run keeps them: the same argv).
        state = self.drone_state
        camera_effects = self.workdir / CAMERA_EFFECTS_FILE
        remove_sqlite(state)
        camera_effects.unlink(missing_ok=True)
        for tlog in self.workdir.glob(TLOG_GLOB):
            tlog.unlink()
        for thumbnail in self.thumbnails_dir.glob(THUMBNAIL_GLOB):
            thumbnail.unlink()
        argv = baton_argv(
            "drone",
            "--config",
            str(self.config_path),
            "--handover-file",
            str(script),
            "--address-file",
            str(ready),
            "--state",
            str(state),
            "--camera-effects-file",
            str(camera_effects),
            "--tlog-dir",
            str(self.workdir),
            "--thumbnails-dir",
            str(self.thumbnails_dir),
        )
        if self.plan.resolution:
            argv += ["--resolution", self.plan.resolution]
        argv += self.plan.drone_args
        address = await self.supervisor.start_ready("drone", argv, ready)
        channel = aio_channel(address, self.tls, self.plan.config.drone_identity)
        self._channels.append(channel)
        self.drone_stub = drone_pb2_grpc.DroneStub(channel)

    @property
    def thumbnails_dir(self) -> Path:
        """Where the drone's camera keeps a thumbnail of each picture (``thumbnail_name``)."""
        return self.workdir / THUMBNAILS_DIR

    @property
    def drone_state(self) -> Path:
        """The drone's state file (``--state``)."""
        return self.workdir / "drone-state.sqlite"

    def controller_log(self, cid: int) -> Path:
        """Controller ``cid``'s log file (``--log-file``): what ``baton replay`` replays."""
        return self.workdir / f"controller-{cid}-log.sqlite"

    def files(self) -> dict[str, Any]:
        """What the run leaves in the workdir for a person: every controller's log (for
        ``baton replay``, with the mission it ran), the drone's telemetry logs, the
        pictures' thumbnails."""
        ring = self.config.ring_order if self.config is not None else []
        return {
            "workdir": str(self.workdir),
            "controller_logs": {str(cid): str(self.controller_log(cid)) for cid in ring},
            "mission": {
                "file": str(self.plan.program),
                "args": self.plan.all_mission_args(),
            },
            "tlogs": sorted(str(path) for path in self.workdir.glob(TLOG_GLOB)),
            "thumbnails": str(self.thumbnails_dir),
        }

    async def _start_controllers(self) -> None:
        assert self.config is not None
        starts = []
        for cid in self.config.ring_order:
            ready = self.workdir / f"controller-{cid}.address"
            # A new mission: no log of an earlier run (a restarted controller of
            # this run recovers from it: the same argv).
            log_file = self.controller_log(cid)
            remove_sqlite(log_file)
            argv = baton_argv(
                "controller",
                "--id",
                str(cid),
                "--config",
                str(self.config_path),
                "--mission",
                str(self.plan.program),
                "--address-file",
                str(ready),
                "--log-file",
                str(log_file),
            )
            for arg in self.plan.all_mission_args():
                argv += ["--mission-arg", arg]
            if self.plan.mission_python is not None:
                argv += ["--mission-python", str(self.plan.mission_python)]
            env = None
            if self.plan.mission_token is not None:
                env = {**os.environ, MISSION_TOKEN_ENV: self.plan.mission_token}
            starts.append((f"controller-{cid}", argv, ready, env))
        with self.supervisor.together():
            parts = [
                await self.supervisor.start(name, argv, ready, env=env)
                for name, argv, ready, env in starts
            ]
        addresses = await self.supervisor.wait_all_ready(parts)
        for cid, address in zip(self.config.ring_order, addresses, strict=True):
            channel = aio_channel(address, self.tls, Identity.controller(cid))
            self._channels.append(channel)
            self.controller_stubs[cid] = ring_pb2_grpc.ControllerRingStub(channel)

    # -- follow -----------------------------------------------------------------------

    async def wait_vehicle_ready(
        self,
        timeout: float,
        progress: Callable[[drone_pb2.DroneStatus], None] | None = None,
        period: float = 0.25,
    ) -> drone_pb2.DroneStatus:
        """Waits until the drone reports the vehicle connected and ready to arm."""
        assert self.drone_stub is not None
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            self.supervisor.check()
            status = await self.drone_stub.GetStatus(drone_pb2.GetDroneStatusRequest(), timeout=10)
            if status.vehicle_connected and status.flight_state.ready:
                return status
            if loop.time() > deadline:
                why = status.vehicle.problem or status.flight_state.not_ready_reason
                raise PartNotReady(
                    f"the vehicle at {status.vehicle_url} is not ready after {timeout:.0f} s: "
                    f"{why or 'no reason given'}"
                )
            if progress is not None:
                progress(status)
            await asyncio.sleep(period)

    async def kill_controller(self, cid: int) -> None:
        """kill -9 of controller ``cid`` (its mission program dies with it); it stays dead
        until ``restart_controller``, and snapshots leave it out meanwhile."""
        await self.supervisor.kill(f"controller-{cid}")
        self.dead.add(cid)

    async def restart_controller(self, cid: int) -> None:
        """Starts a killed controller again, with the same command line (and log file)."""
        await self.supervisor.restart(f"controller-{cid}")
        self.dead.discard(cid)

    async def operator(self, command: str, note: str = "") -> str:
        """The operator's ``command`` to the drone (``baton operator``'s, with the
        testbed's operator certificate): one line of what the drone took; AioRpcError if
        it refused."""
        from baton.drone.operator_cli import describe, send_command

        assert self.drone_stub is not None, "the drone is not started"
        return describe(await send_command(self.drone_stub, command, note))

    async def set_battery(self, percent: float) -> int:
        """Sets the sim vehicle's battery to ``percent``: it reads that from then on and
        drains on from there (ArduPilot's MAV_CMD_BATTERY_RESET to the vehicle's own port,
        signed with its key if it holds one: ``testbed/battery.py``). Returns what the
        vehicle reads then; BatteryResetError if it refused or did not answer."""
        part = self.supervisor.parts["sim-vehicle"]
        url = part.ready_text.splitlines()[0]
        key_file = self._mavlink_key()
        key = read_key(key_file) if key_file is not None else None
        return await asyncio.to_thread(reset_battery, url, percent, key)

    async def cut_link(self, name: str) -> None:
        """Stops link emulator ``name`` (e.g. ``link-drone-0``): every connection through
        it breaks and none can be made, while the parts on both sides live on (until
        ``restore_link``; ``--restart-parts`` leaves a cut link cut)."""
        self.held_down.add(name)
        await self.supervisor.kill(name)

    def blackhole_link(self, name: str) -> None:
        """Freezes link emulator ``name``: its connections stay open but carry nothing, in
        either direction (a radio link that fades without a reset); ``thaw_link`` ends it."""
        self.supervisor.freeze(name)

    def reshape_link(self, name: str, up: LinkSpec, down: LinkSpec | None = None) -> None:
        """Gives link emulator ``name`` a new latency and bandwidth (``down`` defaults to
        ``up``): its open connections follow at once (``baton link --shape-file``)."""
        shape = {"up": up.model_dump(), "down": (down or up).model_dump()}
        write_atomically(self._shape_file(name), json.dumps(shape))
        self.supervisor.send_signal(name, signal.SIGHUP)

    def thaw_link(self, name: str) -> None:
        """Ends a blackhole: what waited in the sockets flows again."""
        self.supervisor.thaw(name)

    async def restore_link(self, name: str) -> None:
        """Starts a cut link emulator again on the address it had."""
        part = self.supervisor.parts[name]
        argv = list(part.argv)
        argv[argv.index("--listen") + 1] = part.ready_text
        restored = await self.supervisor.start(name, argv, part.ready_file, append=True)
        await self.supervisor.wait_ready(restored)
        self.held_down.discard(name)

    # -- parts that die -------------------------------------------------------------------

    async def drone_reqnr(self) -> tuple[int | None, int | None]:
        """The drone's last request number and master now; (None, None) if it does not
        answer within a second (dead, stopped or restarting)."""
        if self.drone_stub is None:
            return None, None
        try:
            status = await self.drone_stub.GetStatus(drone_pb2.GetDroneStatusRequest(), timeout=1)
        except grpc.aio.AioRpcError:
            return None, None
        return status.last_reqnr, status.master

    def _since_start(self) -> float:
        """Seconds since the mission started (the controllers did)."""
        return time.monotonic() - self.started_at

    async def _record_death(
        self, part: ManagedProcess, cause: str, at: tuple[int | None, int | None] | None = None
    ) -> PartDeath:
        """Keeps part ``part``'s death for the report (``at``: the drone's last request
        number and master then, if known) and says it, unless a fault caused it (the
        fault says so itself)."""
        assert part.process is not None
        self._seen_dead.add(part.process.pid)
        if at is None:
            at = await self.drone_reqnr() if part.name != "drone" else (None, None)
        reqnr, master = at
        death = PartDeath(
            part.name,
            self._since_start(),
            time.time(),
            part.returncode,
            reqnr,
            master,
            cause,
        )
        self.deaths.append(death)
        if cause == "outside":
            self.say(death.describe().partition("; ")[0])
        return death

    async def kill_part(
        self,
        name: str,
        cause: str,
        at: tuple[int | None, int | None] | None = None,
        restart_later: bool = False,
    ) -> None:
        """kill -9 of part ``name`` by the fault ``cause`` (``at``: the drone's last
        request number and master); recorded as a death. It stays dead if
        ``restart_later`` (the fault restarts it) or without ``restart_parts``."""
        if restart_later:
            self.held_down.add(name)
        part = await self.supervisor.kill(name)
        await self._record_death(part, cause, at)
        self._mark_dead(name)

    def _mark_dead(self, name: str) -> None:
        if name.startswith("controller-"):
            self.dead.add(int(name.rpartition("-")[2]))

    async def restart_part(self, name: str) -> None:
        """Starts dead part ``name`` again with its command line: a controller keeps its
        log file, the drone its state file, a link emulator and the sim vehicle their
        address (the sim vehicle starts again at home, on the ground)."""
        self.held_down.discard(name)
        if name.startswith("link-"):
            await self.restore_link(name)
        elif name == "sim-vehicle":
            part = self.supervisor.parts[name]
            url = part.ready_text.splitlines()[0]
            argv = [*part.argv, "--port", url.rpartition(":")[2]]
            restarted = await self.supervisor.start(name, argv, part.ready_file, append=True)
            await self.supervisor.wait_ready(restarted)
        else:
            await self.supervisor.restart(name)
        if name.startswith("controller-"):
            self.dead.discard(int(name.rpartition("-")[2]))
        for death in reversed(self.deaths):
            if death.part == name and death.restarted_at_s is None:
                death.restarted_at_s = self._since_start()
                break
        self.say(f"{name} restarted with its command line")

    async def watch_parts(self) -> None:
        """Parts that died: without ``keep_going``, PartDied for the first; else each is
        recorded (by a fault or from outside), restarted if ``restart_parts`` (unless a
        fault holds it down), and the run ends early (``ended_early``) only when the
        mission cannot go on: the drone or the vehicle dead for good, or every controller."""
        if not self.plan.keep_going:
            self.supervisor.check()
            return
        for name, part in list(self.supervisor.parts.items()):
            process = part.process
            if process is None or process.returncode is None:
                continue
            if part.expect_exit and process.returncode == 0:
                continue
            if process.pid not in self._seen_dead:
                if part.killed and name in self.held_down:
                    self._seen_dead.add(process.pid)  # a cut link: the fault's own record
                    continue
                await self._record_death(part, "outside")
                self._mark_dead(name)
            if name in self.held_down or self.ended_early:
                continue
            if self.plan.restart_parts:
                try:
                    await self.restart_part(name)
                except (PartNotReady, RuntimeError) as exc:
                    self.ended_early = f"{name} could not be restarted: {exc}"
            elif name in ("drone", "sim-vehicle", "sitl"):
                self.ended_early = (
                    f"{name} died and is not restarted (--restart-parts restarts it): the "
                    "mission cannot go on"
                )
        ring = self.config.ring_order if self.config is not None else []
        if ring and self.dead >= set(ring) and not self.ended_early:
            if not (self.plan.restart_parts or self.held_down):
                self.ended_early = "every controller died: the mission cannot go on"

    async def snapshot(self, audit: bool = True) -> Snapshot:
        """Every live controller's status now, then the drone's, and the side effects
        counted. The drone and the effects are read after the controllers: a snapshot
        whose controllers say the missions ended holds every drone call they made
        (read first, a drone's status could be older than a mission that ended meanwhile,
        and its audit miss the calls)."""
        assert self.drone_stub is not None
        absent: dict[str, str] = {}
        for name, part in self.supervisor.parts.items():
            if part.returncode is not None and not part.expect_exit:
                cut = name.startswith("link-") and name in self.held_down
                absent[name] = "cut" if cut else "dead"
            elif part.frozen:
                absent[name] = "stopped"
        controllers: dict[int, ring_pb2.ControllerStatus] = {}
        for cid, stub in self.controller_stubs.items():
            if cid in self.dead or f"controller-{cid}" in absent:
                continue
            controllers[cid] = await stub.GetStatus(
                ring_pb2.GetControllerStatusRequest(), timeout=10
            )
        snapshot = Snapshot(await drone_status(self.drone_stub, audit), controllers, absent=absent)
        snapshot.vehicle_effects, snapshot.camera_effects = await asyncio.to_thread(
            self.counted_effects
        )
        return snapshot

    def counted_effects(self) -> tuple[Effects | None, Effects | None]:
        """What the sim vehicle and the camera counted so far (None: this run's vehicle
        counts nothing: SITL or an autopilot that runs already)."""
        vehicle = (
            read_effects(self.workdir / VEHICLE_EFFECTS_FILE)
            if self.plan.vehicle == "sim"
            else None
        )
        return vehicle, read_effects(self.workdir / CAMERA_EFFECTS_FILE)

    async def run_mission(
        self,
        timeout: float,
        progress: Callable[[Snapshot], None] | None = None,
        period: float = 0.5,
    ) -> Snapshot:
        """Waits until every live mission program has ended (and no fault is still under
        way), firing the plan's faults meanwhile; raises if a part dies (unless the plan
        keeps going) or time runs out. With ``keep_going``, a run that cannot go on
        returns its last snapshot and says why in ``ended_early``."""
        injecting = asyncio.create_task(self.injector.run(self.started_at or time.monotonic()))
        try:
            return await self._follow(timeout, progress, period)
        finally:
            injecting.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await injecting

    async def _follow(
        self, timeout: float, progress: Callable[[Snapshot], None] | None, period: float
    ) -> Snapshot:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        last: Snapshot | None = None
        while True:
            await self.watch_parts()
            if self.ended_early:
                if last is None:
                    raise PartNotReady(self.ended_early)
                return last
            try:
                snapshot = await self.snapshot()
            except grpc.aio.AioRpcError as exc:
                if cancelling():
                    # grpc.aio ends a call whose task is cancelled (Ctrl-C) with
                    # CANCELLED, not CancelledError: the cancellation goes on.
                    raise asyncio.CancelledError from exc
                # A part that stops answering has usually just died: give the
                # child watcher a moment, then say which one.
                await asyncio.sleep(0.5)
                await self.watch_parts()
                if loop.time() > deadline:
                    raise TimeoutError(f"status not available: {exc.details()}") from None
                continue
            last = snapshot
            if progress is not None:
                progress(snapshot)
            if snapshot.missions_ended and not self.injector.in_progress:
                return snapshot
            if loop.time() > deadline:
                states = {
                    cid: (
                        label(ring_pb2.ControllerState, c.state),
                        label(ring_pb2.MissionState, c.mission),
                        c.reqnr,
                    )
                    for cid, c in snapshot.controllers.items()
                }
                raise TimeoutError(
                    f"mission not finished after {timeout:.0f} s; controllers: {states}"
                )
            await asyncio.sleep(period)

    async def stop(self) -> None:
        """Stops every process and closes the status channels: the drone service first,
        so that the controllers stopping after the mission are not a lost link to it (its
        failsafe would return a vehicle the mission left hovering), then the rest."""
        for channel in self._channels:
            await channel.close()
        if "drone" in self.supervisor.parts:
            await self.supervisor.stop_part("drone")
        await self.supervisor.stop_all()

    async def __aenter__(self) -> LocalTestbed:
        try:
            await self.start()
        except BaseException:
            await self.stop()
            raise
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()


def cancelling() -> bool:
    """Whether the running task is being cancelled (``Task.cancelling``)."""
    task = asyncio.current_task()
    return task is not None and task.cancelling() > 0

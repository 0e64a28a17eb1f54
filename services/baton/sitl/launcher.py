"""Running ArduPilot Copter SITL: its command line, its ports, a free instance.

ArduPilot's software-in-the-loop Copter (``arducopter``, built for the
``sitl`` board) is the autopilot the paper flew. No package registry ships
it; the project expects one at ``../shared/sitl/arducopter`` beside a
checkout (``find_binary``), and tests skip where it is absent.

One instance ``-I N`` serves MAVLink on TCP 5760+10N (SERIAL0, the drone
service's), 5762+10N (SERIAL1, free for an independent telemetry monitor)
and 5763+10N (SERIAL2), and binds UDP 5501+10N for RC input; two instances
with one number clash, so ``free_instance`` picks a number whose ports are
free. ``--serial0 tcp:0`` starts the simulation at once instead of waiting
for a client on SERIAL0.
"""

from __future__ import annotations

import socket
from dataclasses import dataclass
from pathlib import Path

# Beside a checkout of this repository (``<repo>/../shared/sitl``).
_REPO = Path(__file__).resolve().parents[3]
DEFAULT_BINARY_PLACES = (
    _REPO.parent / "shared" / "sitl" / "arducopter",
    Path("../shared/sitl/arducopter"),
)
SERIAL0_BASE, SERIAL1_BASE, SERIAL2_BASE, RC_IN_BASE = 5760, 5762, 5763, 5501
MAX_INSTANCE = 50
# What SITL prints once SERIAL0 listens: the simulation runs from then on.
LISTENING_MARK = "SERIAL0 on TCP port"


def find_binary() -> Path | None:
    """The project's SITL binary (``../shared/sitl/arducopter``), if there is one."""
    for place in DEFAULT_BINARY_PLACES:
        if place.is_file():
            return place.resolve()
    return None


@dataclass(frozen=True)
class SitlPorts:
    """The TCP ports of one SITL instance on loopback."""

    instance: int

    @property
    def serial0(self) -> int:
        """The drone service's MAVLink port."""
        return SERIAL0_BASE + 10 * self.instance

    @property
    def serial1(self) -> int:
        """A second MAVLink port: for a telemetry monitor independent of the drone service."""
        return SERIAL1_BASE + 10 * self.instance

    @property
    def serial2(self) -> int:
        """A third MAVLink port."""
        return SERIAL2_BASE + 10 * self.instance

    @property
    def vehicle_url(self) -> str:
        """The MAVSDK URL of SERIAL0."""
        return f"tcpout://127.0.0.1:{self.serial0}"

    @property
    def monitor_address(self) -> str:
        """``HOST:PORT`` of SERIAL1 (pymavlink: ``tcp:HOST:PORT``)."""
        return f"127.0.0.1:{self.serial1}"


@dataclass(frozen=True)
class SitlSettings:
    """How to run one SITL: binary, speed-up, home, parameter defaults."""

    binary: Path
    speedup: float = 1.0
    home: tuple[float, float, float] = (47.397742, 8.545594, 488.0)
    defaults: Path | None = None  # default: copter.parm beside the binary, if any
    heading_deg: float = 0.0

    def defaults_file(self) -> Path | None:
        """The parameter defaults: given, else ``copter.parm`` beside the binary."""
        if self.defaults is not None:
            return self.defaults
        beside = self.binary.parent / "copter.parm"
        return beside if beside.is_file() else None

    def argv(self, instance: int) -> list[str]:
        """The SITL command line for instance ``instance`` (run in its own workdir)."""
        lat, lon, alt = self.home
        argv = [
            str(self.binary),
            "--model",
            "+",
            "--speedup",
            f"{self.speedup:g}",
            "-I",
            str(instance),
            "--home",
            f"{lat},{lon},{alt:g},{self.heading_deg:g}",
            "--serial0",
            "tcp:0",
            # A fresh eeprom: parameters and home from this command line only.
            "--wipe",
        ]
        defaults = self.defaults_file()
        if defaults is not None:
            argv += ["--defaults", str(defaults)]
        return argv


def _port_free(kind: int, port: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


def instance_free(instance: int) -> bool:
    """Whether every port instance ``instance`` binds is free now."""
    ports = SitlPorts(instance)
    tcp = (ports.serial0, ports.serial1, ports.serial2)
    return all(_port_free(socket.SOCK_STREAM, p) for p in tcp) and _port_free(
        socket.SOCK_DGRAM, RC_IN_BASE + 10 * instance
    )


def free_instance(start: int = 0) -> int:
    """The first instance number from ``start`` whose ports are all free."""
    for instance in range(start, MAX_INSTANCE):
        if instance_free(instance):
            return instance
    raise OSError(f"no free ArduPilot SITL instance between {start} and {MAX_INSTANCE - 1}")

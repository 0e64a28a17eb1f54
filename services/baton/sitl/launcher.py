"""Running ArduPilot Copter SITL: its command line, its ports, a free instance.

ArduPilot's software-in-the-loop Copter (``arducopter``, built for the
``sitl`` board) is the autopilot the paper flew. No package registry ships
it: users keep ArduPilot's build where ArduPilot's build puts it
(``build/sitl/bin/arducopter``) or on PATH, and ``find_binary`` looks for it
in one order for every caller (``baton sitl``, ``baton testbed --vehicle
sitl``, the tests): the flag, then ``BATON_SITL_BINARY``, then ``arducopter``
on PATH. The environment is read by the command line, which passes it in.

One instance ``-I N`` serves MAVLink on TCP 5760+10N (SERIAL0, the drone
service's), 5762+10N (SERIAL1, free for an independent telemetry monitor)
and 5763+10N (SERIAL2), and binds UDP 5501+10N for RC input; two instances
with one number clash, so ``free_instance`` picks a number whose ports are
free. ``--serial0 tcp:0`` starts the simulation at once instead of waiting
for a client on SERIAL0.

Parameters of one run beyond the defaults file (a small battery, say) are
written to ``PARAMS_FILE`` in SITL's workdir and named after the defaults:
``--defaults`` takes a comma-separated list of parameter files, applied in
order, so the run's own come last and win.
"""

from __future__ import annotations

import math
import re
import shutil
import socket
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

SERIAL0_BASE, SERIAL1_BASE, SERIAL2_BASE, RC_IN_BASE = 5760, 5762, 5763, 5501
MAX_INSTANCE = 50
# What SITL prints once SERIAL0 listens: the simulation runs from then on.
LISTENING_MARK = "SERIAL0 on TCP port"
# The environment variable that names a SITL build, read by the command line.
BINARY_ENV = "BATON_SITL_BINARY"
# ArduPilot's own instructions for building SITL (``./waf configure --board
# sitl`` then ``./waf copter``, which writes ``build/sitl/bin/arducopter``).
BUILD_INSTRUCTIONS = "https://ardupilot.org/dev/docs/building-setup-linux.html"
HOW_TO_POINT_AT_A_BUILD = (
    "pass --sitl-binary PATH, set BATON_SITL_BINARY=PATH, or put arducopter on PATH "
    "(an ArduPilot build for the sitl board: ./waf configure --board sitl && ./waf copter "
    f"writes build/sitl/bin/arducopter; see {BUILD_INSTRUCTIONS})"
)
NOT_FOUND = f"no ArduPilot Copter SITL binary found: {HOW_TO_POINT_AT_A_BUILD}"
# The run's own parameters (``SitlSettings.params``), in SITL's workdir, where it runs.
PARAMS_FILE = "baton-params.parm"
# An ArduPilot parameter name: capitals, digits and underscores, at most 16 characters.
_PARAM_NAME = re.compile(r"[A-Z][A-Z0-9_]{0,15}")


class SitlParamError(ValueError):
    """A parameter for SITL that is not ``NAME=VALUE`` with an ArduPilot name and a number."""


def parse_param(text: str) -> tuple[str, float]:
    """``NAME=VALUE`` (``BATT_CAPACITY=1000``) as a parameter for SITL; SitlParamError
    says what is wrong and the form expected."""
    name, sep, value = text.partition("=")
    expected = "expected NAME=VALUE, e.g. BATT_CAPACITY=1000"
    if not sep:
        raise SitlParamError(f"{text!r}: {expected}")
    if not _PARAM_NAME.fullmatch(name):
        raise SitlParamError(
            f"{text!r}: {name!r} is no ArduPilot parameter name (capitals, digits and "
            f"underscores, at most 16); {expected}"
        )
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not math.isfinite(number):
        raise SitlParamError(f"{text!r}: {value!r} is not a finite number; {expected}")
    return name, number


class SitlBinaryNotFound(LookupError):
    """No SITL binary where baton looks, or none at the place named: says how to fix it."""


def _named_binary(place: str, where: str) -> Path:
    path = Path(place).expanduser()
    if not path.is_file():
        raise SitlBinaryNotFound(f"{where}: no such file; {HOW_TO_POINT_AT_A_BUILD}")
    if not path.stat().st_mode & 0o111:
        raise SitlBinaryNotFound(f"{where}: not executable (chmod +x {path})")
    return path.resolve()


def find_binary(flag: str | Path | None, env: Mapping[str, str]) -> Path:
    """The ArduCopter SITL binary: ``flag``, then ``env[BATON_SITL_BINARY]``, then
    ``arducopter`` on ``env["PATH"]``; SitlBinaryNotFound says how to point at a build.

    A place that is named (the flag, the variable) and holds no binary is an
    error, not a reason to look further: the user meant that one.
    """
    if flag:
        return _named_binary(str(flag), f"--sitl-binary {flag}")
    named = env.get(BINARY_ENV)
    if named:
        return _named_binary(named, f"{BINARY_ENV}={named}")
    on_path = shutil.which("arducopter", path=env.get("PATH", ""))
    if on_path is not None:
        return Path(on_path).resolve()
    raise SitlBinaryNotFound(NOT_FOUND)


def find_defaults(binary: Path) -> Path | None:
    """The parameter defaults for ``binary``: ``copter.parm`` beside it, else the one
    of the ArduPilot tree it was built in (``Tools/autotest/default_params``)."""
    beside = binary.parent / "copter.parm"
    if beside.is_file():
        return beside
    # build/sitl/bin/arducopter -> the source tree three folders up.
    if len(binary.parents) > 3:
        tree = binary.parents[3] / "Tools" / "autotest" / "default_params" / "copter.parm"
        if tree.is_file():
            return tree
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
    defaults: Path | None = None  # default: find_defaults(binary)
    heading_deg: float = 0.0
    # The run's own parameters over the defaults, (name, value) in order: PARAMS_FILE.
    params: tuple[tuple[str, float], ...] = ()

    def defaults_file(self) -> Path | None:
        """The parameter defaults: given, else ``find_defaults`` of the binary."""
        if self.defaults is not None:
            return self.defaults
        return find_defaults(self.binary)

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
        files = [str(f) for f in (self.defaults_file(),) if f is not None]
        if self.params:
            files.append(PARAMS_FILE)  # written in the workdir by params_text
        if files:
            argv += ["--defaults", ",".join(files)]
        return argv

    def params_text(self) -> str:
        """PARAMS_FILE's text: one ``NAME VALUE`` a line, as ArduPilot's parameter files."""
        return "".join(f"{name} {value:.10g}\n" for name, value in self.params)


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

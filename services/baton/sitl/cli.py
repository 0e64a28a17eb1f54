"""``baton sitl``: ArduPilot Copter SITL as a part baton can start, watch and stop.

A thin, supervised wrapper: it picks a free instance, starts ``arducopter``
in a workdir of its own (it writes ``eeprom.bin`` and ``logs/`` there), waits
until SERIAL0 listens, announces the MAVLink URLs (``--url-file``: the
drone service's URL on the first line, the monitor's ``tcp:HOST:PORT`` on the
second) and passes SITL's output to its own. SIGTERM stops SITL; SITL dies
with this wrapper (the kernel sends it SIGTERM), so a testbed killed outright
leaves no autopilot behind. With ``--mavlink-key`` it installs a MAVLink
signing key first (``signing.install_on_ardupilot``) and announces SERIAL1
and SERIAL2, the ports that then take signed frames only.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import os
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

from baton.lifecycle import announce
from baton.sim_vehicle.cli import DEFAULT_HOME, parse_home
from baton.sitl.launcher import LISTENING_MARK, PARAMS_FILE

# Wall seconds for SITL to open SERIAL0 after it starts (it takes ~0.1 s here).
START_TIMEOUT_S = 20.0
# Instances tried when another SITL took the chosen one between the check and the bind.
START_ATTEMPTS = 3


def _speedup(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number like 10, got {text!r}") from None
    if not 0 < value <= 100:
        raise argparse.ArgumentTypeError(f"must be in (0, 100], got {text!r}")
    return value


def _param(text: str) -> tuple[str, float]:
    from baton.sitl.launcher import SitlParamError, parse_param

    try:
        return parse_param(text)
    except SitlParamError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def register(subparsers: Any) -> None:
    """Adds ``baton sitl``."""
    parser = subparsers.add_parser(
        "sitl",
        help="ArduPilot Copter SITL (the paper's autopilot), supervised",
        description=(
            "Starts ArduPilot's Copter SITL binary on a free instance, waits until its "
            "MAVLink ports listen, and writes the drone service's vehicle URL "
            "(tcpout://127.0.0.1:5760+10N, SERIAL0) and a monitor address (tcp:127.0.0.1:"
            "5762+10N, SERIAL1) to --url-file. SIGTERM stops it."
        ),
    )
    parser.add_argument(
        "--sitl-binary",
        "--binary",
        dest="binary",
        metavar="PATH",
        help="the arducopter SITL binary (default: $BATON_SITL_BINARY, else arducopter on PATH)",
    )
    parser.add_argument(
        "--defaults",
        metavar="FILE",
        help="parameter defaults (default: copter.parm beside the binary, if present)",
    )
    parser.add_argument(
        "--param",
        dest="params",
        action="append",
        type=_param,
        default=[],
        metavar="NAME=VALUE",
        help="a parameter of this run over the defaults (repeatable), e.g. BATT_CAPACITY=1000: "
        f"written to {PARAMS_FILE} in the workdir and given after the defaults",
    )
    parser.add_argument(
        "--instance",
        type=int,
        metavar="N",
        help="SITL instance -I N (ports 5760+10N..); default: the first whose ports are free",
    )
    parser.add_argument(
        "--speedup",
        type=_speedup,
        default=1.0,
        help="physics runs this many times faster than real time (default 1); give the "
        "controllers' clocks the same",
    )
    parser.add_argument(
        "--home",
        type=parse_home,
        default=parse_home(DEFAULT_HOME),
        help=f"home LAT,LON,ALT (degrees, degrees, metres AMSL; default {DEFAULT_HOME})",
    )
    parser.add_argument(
        "--workdir",
        metavar="DIR",
        help="where SITL writes eeprom.bin and logs/ (default: a new temp folder)",
    )
    parser.add_argument(
        "--url-file",
        metavar="PATH",
        help="write the vehicle URL (line 1) and the monitor address (line 2) here once "
        "SITL listens",
    )
    parser.add_argument(
        "--mavlink-key",
        metavar="FILE",
        help="install this MAVLink signing key (baton certs mavlink-key) with SETUP_SIGNING "
        "on SERIAL0 and check that SITL signs with it; the vehicle URL is then SERIAL1 "
        "and the monitor SERIAL2, which accept only signed frames (SERIAL0, a flight "
        "controller's USB port, accepts unsigned ones for good)",
    )
    parser.add_argument(
        "--which",
        action="store_true",
        help="print the binary (line 1) and the parameter defaults (line 2, empty if none) "
        "it would run, and exit: deploy/images.sh stages them for the compose SITL image",
    )
    parser.set_defaults(run=run)


def _die_with_this_process() -> None:
    """In the SITL child before exec: SIGTERM when the wrapper dies (no threads here yet)."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def _start(argv: list[str], workdir: Path) -> tuple[subprocess.Popen[str], list[str]]:
    """Starts SITL; returns it and its output up to the listening line (or its exit)."""
    process = subprocess.Popen(
        argv,
        cwd=workdir,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=_die_with_this_process,  # safe: this wrapper runs no threads
    )
    assert process.stdout is not None
    seen: list[str] = []
    timer = threading.Timer(START_TIMEOUT_S, process.kill)
    timer.start()
    try:
        for line in process.stdout:
            seen.append(line.rstrip("\n"))
            if LISTENING_MARK in line:
                return process, seen
    finally:
        timer.cancel()
    process.wait()
    return process, seen


def run(args: argparse.Namespace) -> int:
    """Runs SITL until SIGTERM or until it exits."""
    from baton.sitl.launcher import (
        SitlBinaryNotFound,
        SitlPorts,
        SitlSettings,
        find_binary,
        find_defaults,
        free_instance,
    )

    try:
        binary = find_binary(args.binary, os.environ)
    except SitlBinaryNotFound as exc:
        print(f"baton sitl: {exc}", file=sys.stderr)
        return 2
    if args.which:
        defaults = Path(args.defaults).resolve() if args.defaults else find_defaults(binary)
        print(binary)
        print(defaults or "")
        return 0
    if args.defaults and not Path(args.defaults).is_file():
        print(f"baton sitl: --defaults {args.defaults}: no such file", file=sys.stderr)
        return 2
    settings = SitlSettings(
        binary=binary.resolve(),
        speedup=args.speedup,
        home=args.home,
        defaults=Path(args.defaults).resolve() if args.defaults else None,
        params=tuple(args.params),
    )
    key = None
    if args.mavlink_key:
        from baton.signing import SigningKeyError, read_key

        try:
            key = read_key(Path(args.mavlink_key))
        except SigningKeyError as exc:
            print(f"baton sitl: --mavlink-key: {exc}", file=sys.stderr)
            return 2
    workdir = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="baton-sitl-"))
    workdir.mkdir(parents=True, exist_ok=True)
    if settings.params:
        (workdir / PARAMS_FILE).write_text(settings.params_text())
    stopping = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        stopping.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    instance = args.instance if args.instance is not None else free_instance()
    for attempt in range(START_ATTEMPTS):
        process, seen = _start(settings.argv(instance), workdir)
        if process.poll() is None:
            break
        print("\n".join(seen), flush=True)
        if args.instance is not None or attempt == START_ATTEMPTS - 1:
            print(
                f"baton sitl: SITL exited with {process.returncode} before it listened "
                f"(instance {instance}, workdir {workdir})",
                file=sys.stderr,
            )
            return 1
        instance = free_instance(instance + 1)  # taken meanwhile: try the next free one
    ports = SitlPorts(instance)
    print("\n".join(seen), flush=True)
    # SITL's output is read from now on: a full pipe would stop its simulation.
    pump = threading.Thread(target=_pump, args=(process,), daemon=True)
    pump.start()
    vehicle_url, monitor = ports.vehicle_url, f"tcp:{ports.monitor_address}"
    if key is not None:
        from baton.signing import SigningKeyError, install_on_ardupilot

        try:
            install_on_ardupilot(
                f"tcp:127.0.0.1:{ports.serial0}", f"tcp:127.0.0.1:{ports.serial2}", key
            )
        except SigningKeyError as exc:
            print(f"baton sitl: --mavlink-key: {exc}", file=sys.stderr)
            process.terminate()
            return 1
        vehicle_url = f"tcpout://127.0.0.1:{ports.serial1}"
        monitor = f"tcp:127.0.0.1:{ports.serial2}"
    listening = {
        "url": vehicle_url,
        "monitor": monitor,
        "signing": key is not None,
        "instance": instance,
        "speedup": settings.speedup,
        "workdir": str(workdir),
    }
    announce(args.url_file, [vehicle_url, monitor], listening)
    while not stopping.is_set() and process.poll() is None:
        stopping.wait(0.2)
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(5)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        return 0
    print(f"baton sitl: SITL exited with {process.returncode}", file=sys.stderr)
    return 1 if process.returncode else 0


def _pump(process: subprocess.Popen[str]) -> None:
    """Passes SITL's output on, so it lands in this part's log."""
    assert process.stdout is not None
    with contextlib.suppress(ValueError, OSError):
        for line in process.stdout:
            sys.stdout.write(line)
            sys.stdout.flush()

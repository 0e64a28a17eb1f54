"""Radio range on a network interface, with tc netem: ``baton radio-netem``.

The compose testbed for users shapes its links with netem inside the
containers (deploy/netem.sh), not with ``baton link``; this is its radio range.
It runs in a controller's network namespace (a sidecar container with
``network_mode: service:controller-N``) and keeps the netem qdisc on the
controller's interface to the drone's network in step with the vehicle:

- vehicle within range: ``netem delay LATENCY rate BANDWIDTH`` (the
  configuration's drone_link), faded towards the edge of range with a fade;
- vehicle out of range, or its position unknown: ``netem loss 100%``, every
  packet the controller sends to the drone's network dropped.

Whether the vehicle is in range and what a fade gives are radio.py's, the one
implementation the local testbed's link emulator (proxy.py) applies too; this
module only turns its answer into tc arguments. Two differences from the
emulator, both netem's: out of range the link is a black hole rather than
refused and reset (TCP and gRPC keepalives find it dead), and the fade shapes
this controller's egress only (the drone's side keeps its own shaping: one
interface for every controller).
"""

from __future__ import annotations

import subprocess
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from baton.config import LinkSpec
from baton.link.radio import Fade, RadioRange, read_position
from baton.logs import BoundLogger, get_logger

# What netem applies out of range: every packet dropped.
OUT_OF_RANGE = ("loss", "100%")
# tc's arguments are rounded to these, so that a fade moving by less changes nothing.
LATENCY_STEP_US = 100
RATE_STEP_KBIT = 1

Runner = Callable[[Sequence[str]], "subprocess.CompletedProcess[str]"]


def netem_args(spec: LinkSpec) -> tuple[str, ...]:
    """What follows ``netem`` for a link shaped like ``spec`` (unlimited: no rate)."""
    delay_us = round(spec.latency * 1e6 / LATENCY_STEP_US) * LATENCY_STEP_US
    args: tuple[str, ...] = ("delay", f"{delay_us}us")
    if spec.bandwidth is not None:
        args += ("rate", f"{max(1, round(spec.bandwidth / 1e3 / RATE_STEP_KBIT))}kbit")
    return args


def radio_netem_args(
    radio: RadioRange, base: LinkSpec, fade: Fade | None, where: tuple[float, float] | None
) -> tuple[str, ...]:
    """What follows ``netem`` for the vehicle at ``where`` (None: not known)."""
    if where is None or not radio.covers(*where):
        return OUT_OF_RANGE
    if fade is None:
        return netem_args(base)
    return netem_args(fade.spec(base, fade.depth(radio.distance_m(*where), radio.range_m)))


def _run(argv: Sequence[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(list(argv), capture_output=True, text=True, timeout=10, check=False)


class NetemError(RuntimeError):
    """``ip`` or ``tc`` refused: the message says what and the likely fix."""


def interface_on(subnet: str, run: Runner = _run) -> str:
    """The interface whose connected route is exactly ``subnet`` (as deploy/netem.sh finds it)."""
    done = run(["ip", "-o", "-4", "route", "show", "to", "exact", subnet])
    words = done.stdout.split()
    if done.returncode != 0 or "dev" not in words[:-1]:
        raise NetemError(
            f"this container has no interface on {subnet}: run in the network namespace of "
            "a container attached to the compose network with that subnet "
            f"(ip said: {done.stderr.strip() or done.stdout.strip() or 'nothing'})"
        )
    return words[words.index("dev") + 1]


@dataclass
class NetemRadio:
    """Keeps ``device``'s root netem qdisc in step with the vehicle's position file."""

    device: str
    radio: RadioRange
    position_file: Path
    base: LinkSpec
    fade: Fade | None = None
    run: Runner = _run
    applied: tuple[str, ...] | None = None
    in_range: bool | None = None
    log: BoundLogger = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.log = get_logger("radio-netem").bind(device=self.device)

    def look(self, reassert: bool = False) -> None:
        """Reads the position and applies what it gives, if that changed (or ``reassert``)."""
        where = read_position(self.position_file)
        args = radio_netem_args(self.radio, self.base, self.fade, where)
        covered = args != OUT_OF_RANGE
        if covered != self.in_range:
            self.in_range = covered
            distance = "position unknown"
            if where is not None:
                distance = f"{self.radio.distance_m(*where):.0f} m"
            self.log.info(
                "vehicle in radio range" if covered else "vehicle out of radio range",
                distance=distance,
                range_m=self.radio.range_m,
            )
        if args == self.applied and not reassert:
            return
        argv = ["tc", "qdisc", "replace", "dev", self.device, "root", "netem", *args]
        done = self.run(argv)
        if done.returncode != 0:
            raise NetemError(
                f"{' '.join(argv)} failed: {done.stderr.strip() or done.returncode}; it needs "
                "cap_add: [NET_ADMIN] and the host's sch_netem module (modprobe sch_netem)"
            )
        if args != self.applied:
            self.log.info("netem", args=" ".join(args))
        self.applied = args

"""``baton link``: run one link emulator in front of a TCP service.

    baton link --listen 127.0.0.1:0 --target 127.0.0.1:7100 --latency 20ms --bandwidth 25Mbit

prints ``{"event": "listening", "address": "127.0.0.1:N"}`` on stdout once it
accepts connections, logs its counters periodically and on exit, and exits
cleanly on SIGTERM or SIGINT.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from baton import lifecycle
from baton.config import LinkSpec, parse_address, parse_duration, parse_rate
from baton.lifecycle import announce, run_until_signalled, until_stopped, write_atomically
from baton.link.radio import parse_fade, parse_radio_range
from baton.logs import BoundLogger

if TYPE_CHECKING:
    from baton.link.proxy import LinkProxy

UNLIMITED = ("unlimited", "none")


def _option_type(parse: Callable[[str], Any], name: str) -> Callable[[str], Any]:
    """An argparse type whose error is the parser's own message (with its example)."""

    def convert(text: str) -> Any:
        try:
            return parse(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    convert.__name__ = name
    return convert


def _parse_bandwidth(text: str) -> float:
    # inf, not None: None means "option not given" (inherit --bandwidth).
    return math.inf if text.strip().lower() in UNLIMITED else parse_rate(text)


_address = _option_type(parse_address, "address")
_duration = _option_type(parse_duration, "duration")
_bandwidth = _option_type(_parse_bandwidth, "bandwidth")


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Adds ``baton link``."""
    parser = subparsers.add_parser(
        "link",
        help="TCP proxy that emulates a link's latency and bandwidth",
        description=(
            "Forwards every connection accepted on --listen to --target, delaying each "
            "direction like a serial line of the given bandwidth followed by the given "
            "latency (a transfer of S bytes takes latency + 8*S/bandwidth). "
            "'up' is client -> target, 'down' is target -> client."
        ),
    )
    parser.add_argument(
        "--listen",
        type=_address,
        default="127.0.0.1:0",
        metavar="HOST:PORT",
        help="address to accept connections on; port 0 picks a free one (default: 127.0.0.1:0)",
    )
    parser.add_argument(
        "--target",
        type=_address,
        required=True,
        metavar="HOST:PORT",
        help="address every connection is forwarded to",
    )
    parser.add_argument(
        "--latency",
        type=_duration,
        default=0.0,
        metavar="DURATION",
        help="one-way delay in both directions, e.g. 20ms (default: 0)",
    )
    parser.add_argument(
        "--bandwidth",
        type=_bandwidth,
        default=None,
        metavar="RATE",
        help="rate in both directions, e.g. 25Mbit, or 'unlimited' (default: unlimited)",
    )
    for direction, what in (("up", "client -> target"), ("down", "target -> client")):
        parser.add_argument(
            f"--{direction}-latency",
            type=_duration,
            default=None,
            metavar="DURATION",
            help=f"one-way delay {what}; overrides --latency",
        )
        parser.add_argument(
            f"--{direction}-bandwidth",
            type=_bandwidth,
            default=None,
            metavar="RATE",
            help=f"rate {what}, or 'unlimited'; overrides --bandwidth",
        )
    parser.add_argument(
        "--off",
        action="store_true",
        help="no emulation: pass bytes straight through (cannot be combined with shaping options)",
    )
    parser.add_argument(
        "--range",
        type=_option_type(parse_radio_range, "radio range"),
        default=None,
        metavar="LAT,LON,METRES",
        help="radio range: carry connections only while the vehicle is within METRES of "
        "LAT,LON (refused out of range, cut when it leaves); needs --position-file",
    )
    parser.add_argument(
        "--fade",
        type=_option_type(parse_fade, "radio fade"),
        default=None,
        metavar="BEGINS,LATENCY,FACTOR",
        help="with --range: from BEGINS (a fraction of the range) to the circle the one-way "
        "latency grows linearly by up to LATENCY and the bandwidth falls linearly to FACTOR "
        "of its own, e.g. 0.8,50ms,0.25 (default: no fade)",
    )
    parser.add_argument(
        "--position-file",
        type=Path,
        default=None,
        metavar="PATH",
        help="where the vehicle is: the file `baton sim-vehicle --position-file` keeps "
        "up to date (for --range)",
    )
    parser.add_argument(
        "--shape-file",
        type=Path,
        default=None,
        metavar="PATH",
        help="on SIGHUP, take the link's latency and bandwidth from this JSON file, e.g. "
        '{"up": {"latency": "400ms"}, "down": {"latency": "400ms", "bandwidth": "1Mbit"}} '
        "(a direction left out keeps its own); open connections follow at once",
    )
    parser.add_argument(
        "--address-file",
        type=Path,
        default=None,
        metavar="PATH",
        help="also write the listening address to this file (atomically) once listening",
    )
    parser.add_argument(
        "--report-interval",
        type=_duration,
        default=10.0,
        metavar="DURATION",
        help="log the counters this often when they changed; 0 logs them only on exit "
        "(default: 10s)",
    )
    parser.set_defaults(run=run, link_parser=parser)
    _register_radio_netem(subparsers)


def _register_radio_netem(
    subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
) -> None:
    """Adds ``baton radio-netem``: the same radio range, applied with tc netem."""
    parser = subparsers.add_parser(
        "radio-netem",
        help="radio range on a network interface with tc netem (the compose testbed's)",
        description=(
            "Keeps the netem qdisc of this network namespace's interface on --subnet in step "
            "with the vehicle's position file: 'netem delay LATENCY rate BANDWIDTH' (faded "
            "towards the edge with --fade) while the vehicle is within --range, 'netem loss "
            "100%%' when it is not or its position is unknown. The same range and fade as "
            "'baton link --range', for containers shaped with netem. Needs NET_ADMIN and "
            "the kernel's sch_netem."
        ),
    )
    parser.add_argument(
        "--subnet",
        required=True,
        metavar="CIDR",
        help="the drone's network: the interface whose connected route is this subnet is shaped",
    )
    parser.add_argument(
        "--latency",
        type=_duration,
        default=0.0,
        metavar="DURATION",
        help="netem delay in range, e.g. 2ms (default: 0)",
    )
    parser.add_argument(
        "--bandwidth",
        type=_bandwidth,
        default=math.inf,
        metavar="RATE",
        help="netem rate in range, e.g. 20Mbit, or 'unlimited' (default)",
    )
    parser.add_argument(
        "--range",
        type=_option_type(parse_radio_range, "radio range"),
        required=True,
        metavar="LAT,LON,METRES",
        help="the station's antenna and range",
    )
    parser.add_argument(
        "--fade",
        type=_option_type(parse_fade, "radio fade"),
        default=None,
        metavar="BEGINS,LATENCY,FACTOR",
        help="as baton link --fade (default: no fade)",
    )
    parser.add_argument(
        "--position-file",
        type=Path,
        required=True,
        metavar="PATH",
        help="where the vehicle is: the file `baton sim-vehicle --position-file` keeps up to date",
    )
    parser.add_argument(
        "--ready-file",
        type=Path,
        default=None,
        metavar="PATH",
        help="write the interface's name here once the first qdisc is applied",
    )
    parser.add_argument(
        "--reassert",
        type=_duration,
        default=1.0,
        metavar="DURATION",
        help="apply the current qdisc again this often even if unchanged, in case "
        "something else replaced it (default: 1s; 0: never)",
    )
    parser.set_defaults(run=run_radio_netem)


def run_radio_netem(args: argparse.Namespace) -> int:
    """Follows the vehicle until SIGTERM or SIGINT."""
    import asyncio
    import time

    from baton.link.netem import NetemError, NetemRadio, interface_on
    from baton.link.radio import POSITION_PERIOD_S

    base = LinkSpec(
        latency=args.latency, bandwidth=None if args.bandwidth == math.inf else args.bandwidth
    )

    async def follow(stop: asyncio.Event) -> int:
        try:
            device = interface_on(args.subnet)
            radio = NetemRadio(device, args.range, args.position_file, base, args.fade)
            radio.look()
        except NetemError as exc:
            print(f"baton radio-netem: {exc}", file=sys.stderr)
            return 1
        if args.ready_file is not None:
            write_atomically(args.ready_file, f"{device}\n")
        asserted = time.monotonic()

        def tick() -> None:
            nonlocal asserted
            now = time.monotonic()
            due = bool(args.reassert) and now - asserted >= args.reassert
            radio.look(reassert=due)
            if due:
                asserted = now

        try:
            await until_stopped(stop, POSITION_PERIOD_S, tick)
        except NetemError as exc:
            print(f"baton radio-netem: {exc}", file=sys.stderr)
            return 1
        return 0

    return lifecycle.run(run_until_signalled(follow))


def link_specs(args: argparse.Namespace) -> tuple[LinkSpec, LinkSpec]:
    """The (up, down) link specs the options describe."""
    shaping = [
        "latency",
        "bandwidth",
        "up_latency",
        "up_bandwidth",
        "down_latency",
        "down_bandwidth",
    ]
    if args.off:
        given = [f"--{name.replace('_', '-')}" for name in shaping if getattr(args, name)]
        if given:
            args.link_parser.error(f"--off passes bytes straight through; drop {', '.join(given)}")
        return LinkSpec(), LinkSpec()
    specs = []
    for direction in ("up", "down"):
        latency = getattr(args, f"{direction}_latency")
        bandwidth = getattr(args, f"{direction}_bandwidth")
        if bandwidth is None:
            bandwidth = args.bandwidth
        specs.append(
            LinkSpec(
                latency=args.latency if latency is None else latency,
                bandwidth=None if bandwidth == math.inf else bandwidth,
            )
        )
    return specs[0], specs[1]


def run(args: argparse.Namespace) -> int:
    """Runs the link until SIGTERM or SIGINT."""
    import asyncio

    from baton.link.proxy import LinkProxy

    up, down = link_specs(args)
    if (args.range is None) != (args.position_file is None):
        args.link_parser.error("--range and --position-file go together: give both or neither")
    if args.fade is not None and args.range is None:
        args.link_parser.error("--fade fades a radio range: give --range and --position-file too")

    async def serve(stop: asyncio.Event) -> int:
        proxy = LinkProxy(
            args.listen, args.target, up, down, args.range, args.position_file, args.fade
        )
        try:
            await proxy.start()
        except OSError as exc:
            proxy.log.error(f"cannot listen on {args.listen}: {exc.strerror or exc}")
            return 1
        if args.shape_file is not None:
            reshape_on_hangup(proxy, args.shape_file, proxy.log)
        announce(args.address_file, [proxy.address], {"address": proxy.address})
        reported = proxy.counters.as_fields()

        def report() -> None:
            nonlocal reported
            if proxy.counters.as_fields() != reported:
                reported = proxy.counters.as_fields()
                proxy.log.info("link counters", **reported)

        try:
            await until_stopped(stop, args.report_interval or None, report)
        finally:
            await proxy.stop()  # logs the final counters
        return 0

    return lifecycle.run(run_until_signalled(serve))


def read_shape(path: Path, up: LinkSpec, down: LinkSpec) -> tuple[LinkSpec, LinkSpec]:
    """The (up, down) specs ``path`` gives (``--shape-file``); ValueError naming the
    file and what is wrong in it."""
    import json

    import pydantic

    try:
        document = json.loads(path.read_text())
    except OSError as exc:
        raise ValueError(f"--shape-file {path}: cannot read it ({exc.strerror})") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"--shape-file {path}: not JSON ({exc})") from None
    if not isinstance(document, dict) or set(document) - {"up", "down"}:
        raise ValueError(
            f"--shape-file {path}: expected an object with 'up' and/or 'down', e.g. "
            '{"up": {"latency": "400ms"}, "down": {"latency": "400ms"}}'
        )
    try:
        return (
            LinkSpec.model_validate(document["up"]) if "up" in document else up,
            LinkSpec.model_validate(document["down"]) if "down" in document else down,
        )
    except pydantic.ValidationError as exc:
        raise ValueError(f"--shape-file {path}: {exc}") from None


def reshape_on_hangup(proxy: LinkProxy, path: Path, log: BoundLogger) -> None:
    """SIGHUP: ``proxy`` takes the specs of ``path``; a bad file is logged, not taken."""
    import asyncio
    import signal

    def hangup() -> None:
        try:
            up, down = read_shape(path, proxy.up, proxy.down)
        except ValueError as exc:
            log.error("link not reshaped", error=str(exc))
            return
        proxy.reshape(up, down)

    asyncio.get_running_loop().add_signal_handler(signal.SIGHUP, hangup)

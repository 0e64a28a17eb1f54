"""``baton certs``: a mission's CA and its parts' certificates (baton/certs/make.py)."""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from baton.rpc.tls import Identity, Tls, TlsError

if TYPE_CHECKING:
    from baton.config import BatonConfig


def _identity(text: str) -> Identity:
    role, _, rest = text.partition("-")
    try:
        if role == "drone":
            return Identity.drone(rest)
        return Identity(role, int(rest)) if rest else Identity(role)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(
            f"{text!r}: {exc}; a part is controller-N, drone, drone-NAME (a fleet's drone) "
            "or operator"
        ) from None


def _ids(text: str) -> list[int]:
    try:
        ids = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: controller ids, e.g. 0,1,2") from None
    if not ids or min(ids) < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: controller ids >= 0, e.g. 0,1,2")
    return ids


def _days(text: str) -> int:
    try:
        days = int(text)
    except ValueError:
        days = 0
    if not 1 <= days <= 3650:
        raise argparse.ArgumentTypeError(f"{text!r}: days of validity, 1 to 3650")
    return days


def add_tls_flags(parser: argparse.ArgumentParser) -> None:
    """``--certs`` and ``--insecure``, the same on every program that serves or calls."""
    parser.add_argument(
        "--certs",
        type=Path,
        metavar="DIR",
        help="folder of ca.crt and this part's NAME.crt/NAME.key (baton certs init) "
        "(default: the config's tls.certs, else ./certs)",
    )
    parser.add_argument(
        "--insecure",
        action="store_true",
        help="plain gRPC, no certificates: anyone on the network may call; debugging only",
    )


def add_renew_flag(parser: argparse.ArgumentParser) -> None:
    """``--renew-from``, on every program that serves (its certificate kept short-lived)."""
    parser.add_argument(
        "--renew-from",
        metavar="ADDRESS",
        help="host:port of the certificate issuer (baton certs issuer): the part asks it for "
        "its next certificate halfway through the one it holds, and takes it without a "
        "restart (default: none; the certificate lives as long as it was issued for)",
    )


def tls_from_flags(
    args: argparse.Namespace, config: BatonConfig | None, identity: Identity
) -> Tls | None:
    """The certificate ``identity`` presents: flags over the configuration file, else
    ./certs; None when insecure (a flag, or the file's tls.insecure)."""
    if args.insecure:
        return None
    if args.certs is not None:
        return Tls.load(args.certs, identity)
    if config is not None:
        return config.tls_for(identity)
    return Tls.load(Path("certs"), identity)


def _hours(text: str) -> int:
    try:
        hours = int(text)
    except ValueError:
        hours = 0
    if not 1 <= hours <= 24 * 90:
        raise argparse.ArgumentTypeError(f"{text!r}: hours of validity, 1 to 2160")
    return hours


def _lifetime(text: str) -> float:
    from baton.config import parse_duration

    try:
        seconds = parse_duration(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{text!r}: {exc}") from None
    if seconds < 10:
        raise argparse.ArgumentTypeError(f"{text!r}: a lifetime of 10s to a day (24h)")
    return seconds


def _folder_and_part(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dir", type=Path, help="a folder made by `baton certs init`")
    parser.add_argument(
        "part", type=_identity, help="controller-N, drone, drone-NAME (a fleet's) or operator"
    )


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Adds ``baton certs init``, ``issue``, ``rotate``, ``revoke`` and ``mavlink-key``."""
    parser = subparsers.add_parser(
        "certs",
        help="make the CA and certificates for mutual TLS",
        description=(
            "Makes a mission's CA and one key and certificate per part (each controller, the "
            "drone, an operator), naming the part's identity (spiffe://baton/controller/1, "
            "spiffe://baton/drone, spiffe://baton/operator). Every part finds its files in "
            "the folder the testbed file's tls.certs names."
        ),
    )
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    init = actions.add_parser("init", help="a new CA and a certificate for every part")
    init.add_argument("dir", type=Path, help="the folder to create")
    init.add_argument("--config", help="testbed YAML whose controllers get certificates")
    init.add_argument(
        "--fleet",
        help="a fleet file (baton testbed --fleet) instead: each station gets its controller "
        "certificate, each drone its own (drone-NAME), and the operator",
    )
    init.add_argument(
        "--controllers",
        type=_ids,
        default=[0, 1, 2],
        help="controller ids when no --config is given (default 0,1,2, the demo's)",
    )
    init.add_argument("--days", type=_days, default=365, help="validity in days (default 365)")
    init.add_argument(
        "--keep-ca",
        action="store_true",
        help="a folder with a CA already keeps it and gets only the certificates it lacks "
        "(the compose testbed's, run again)",
    )
    init.set_defaults(run=_run_init)
    issue = actions.add_parser(
        "issue", help="add or renew one part's certificate, signed by the folder's CA"
    )
    _folder_and_part(issue)
    issue.add_argument("--days", type=_days, default=365, help="validity in days (default 365)")
    issue.set_defaults(run=_run_issue)
    rotate = actions.add_parser(
        "rotate",
        help="a new short-lived key and certificate for a running part, taken without a restart",
        description=(
            "Replaces a part's key and certificate with new ones valid for --hours (24 by "
            "default). A running part presents the new certificate from its next connection "
            "on, without a restart; connections it holds keep the old one until they end. "
            "The old certificate stays valid until it expires: revoke it (baton certs "
            "revoke) to end it at once. Run it again before --hours pass (a timer on the "
            "machine that holds ca.key), in the spirit of SPIFFE's short-lived SVIDs."
        ),
    )
    _folder_and_part(rotate)
    rotate.add_argument("--hours", type=_hours, default=24, help="validity in hours (default 24)")
    rotate.set_defaults(run=_run_rotate)
    revoke = actions.add_parser(
        "revoke",
        help="refuse a certificate on every part, from now on, without re-keying the others",
        description=(
            "Adds a certificate to the folder's revocation list (revoked.crl, signed by its "
            "CA). Every part that reads this folder refuses it within seconds, on new calls "
            "and on the streams it holds, without a restart. Give a part (its current "
            "certificate: a stolen station) or the serial `baton certs issue` printed "
            "(a certificate it replaced)."
        ),
    )
    revoke.add_argument("dir", type=Path, help="a folder made by `baton certs init`")
    revoke.add_argument(
        "what", help="controller-N, drone or operator, or a certificate's serial (hexadecimal)"
    )
    revoke.set_defaults(run=_run_revoke)
    issuer = actions.add_parser(
        "issuer",
        help="serve short-lived certificates to running parts (--renew-from)",
        description=(
            "Serves baton.v1.Issuer under mutual TLS on the machine that holds the folder's "
            "ca.key: a part started with --renew-from ADDRESS asks it for its next "
            "certificate halfway through the one it holds, over a key it has just made, and "
            "gets one naming the identity it called with, valid for --lifetime. A revoked "
            "certificate (baton certs revoke) renews nothing. In the spirit of SPIFFE's "
            "short-lived SVIDs."
        ),
    )
    issuer.add_argument("dir", type=Path, help="a folder made by `baton certs init` (with ca.key)")
    issuer.add_argument(
        "--listen", default="127.0.0.1:8471", help="host:port to serve on (default 127.0.0.1:8471)"
    )
    issuer.add_argument(
        "--lifetime",
        type=_lifetime,
        default=3600.0,
        help="how long each certificate it issues is valid, e.g. 1h, 30min "
        "(default 1h; 10s to 24h)",
    )
    issuer.add_argument(
        "--address-file", type=Path, help="write the address it listens on here, once it does"
    )
    issuer.set_defaults(run=_run_issuer)
    key = actions.add_parser(
        "mavlink-key",
        help="a new random MAVLink 2 signing key, for the drone and its autopilot",
        description=(
            "Writes a new 32-byte MAVLink signing key as 64 hexadecimal digits (mode 0600). "
            "Give it to the drone (--mavlink-key, or drone.mavlink_key in the testbed file) "
            "and install the same key on the autopilot (ArduPilot: SETUP_SIGNING, e.g. "
            "MAVProxy's `signing key`, or `baton sitl --mavlink-key`). Refuses to replace a key."
        ),
    )
    key.add_argument("file", type=Path, help="the key file to create")
    key.set_defaults(run=_run_mavlink_key)


def _run_init(args: argparse.Namespace) -> int:
    from baton.certs.make import ensure, init
    from baton.config import ConfigError, load_config
    from baton.rpc.tls import DRONE, OPERATOR
    from baton.testbed.fleet import fleet_identities, load_fleet

    if args.config and args.fleet:
        print("baton certs: --config or --fleet, not both", file=sys.stderr)
        return 2
    ids = args.controllers
    try:
        if args.config:
            ids = load_config(args.config).ring_order
        fleet = load_fleet(Path(args.fleet)) if args.fleet else None
    except ConfigError as exc:
        print(f"baton certs: {exc}", file=sys.stderr)
        return 2
    if fleet is not None:
        parts = fleet_identities(fleet)
    else:
        parts = [*(Identity.controller(cid) for cid in ids), DRONE, OPERATOR]
    if args.keep_ca:
        ensure(args.dir, parts, args.days)
    else:
        init(args.dir, parts, args.days)
    print(f"{args.dir}: CA and certificates for {', '.join(p.name for p in parts)}")
    return 0


def _run_issuer(args: argparse.Namespace) -> int:
    import datetime

    from baton import lifecycle
    from baton.certs.issuer import issuer_server
    from baton.logs import get_logger

    async def serve(stop: asyncio.Event) -> int:
        try:
            server, service = issuer_server(
                args.dir, args.listen, datetime.timedelta(seconds=args.lifetime)
            )
        except (TlsError, OSError) as exc:
            print(f"baton certs issuer: {exc}", file=sys.stderr)
            return 2
        log = get_logger("issuer", lifetime_s=args.lifetime)
        await server.start()
        lifecycle.announce(args.address_file, [server.address], {"address": server.address})
        log.info("issuing certificates", address=server.address, folder=str(args.dir))
        try:
            await stop.wait()
        finally:
            await server.stop()
            log.info("issuer stopped", issued=service.issued)
        return 0

    return lifecycle.run(lifecycle.run_until_signalled(serve))


def _run_mavlink_key(args: argparse.Namespace) -> int:
    from baton.signing import SigningKeyError, write_key

    try:
        write_key(args.file)
    except (SigningKeyError, OSError) as exc:
        print(f"baton certs mavlink-key: {exc}", file=sys.stderr)
        return 2
    print(f"{args.file}: a new MAVLink signing key")
    return 0


def _run_issue(args: argparse.Namespace) -> int:
    from baton.certs.make import issue

    replaced, serial = issue(args.dir, args.part, args.days)
    _say_issued(args, serial, replaced)
    return 0


def _run_rotate(args: argparse.Namespace) -> int:
    import datetime

    from baton.certs.make import issue

    valid_for = datetime.timedelta(hours=args.hours)
    replaced, serial = issue(args.dir, args.part, valid_for=valid_for)
    _say_issued(args, serial, replaced)
    print(f"valid for {args.hours} h: rotate again before then; a running part takes it")
    return 0


def _say_issued(args: argparse.Namespace, serial: int, replaced: int | None) -> None:
    print(f"{args.dir}: certificate for {args.part.name} ({args.part.uri}), serial {serial:x}")
    if replaced is not None:
        print(
            f"it replaces serial {replaced:x}, valid until it expires or is revoked: "
            f"baton certs revoke {args.dir} {replaced:x}"
        )


def _run_revoke(args: argparse.Namespace) -> int:
    from baton.certs.make import revoke, serial_of

    try:
        part: Identity | None = _identity(args.what)
    except argparse.ArgumentTypeError:
        part = None
    if part is not None:
        serial = serial_of(args.dir / f"{part.name}.crt")
        if serial is None:
            print(
                f"baton certs revoke: {args.dir / (part.name + '.crt')}: no certificate",
                file=sys.stderr,
            )
            return 2
    else:
        try:
            serial = int(args.what.replace(":", ""), 16)
        except ValueError:
            print(
                f"baton certs revoke: {args.what!r}: neither a part (controller-N, drone, "
                "operator) nor a serial in hexadecimal (as `baton certs issue` prints it)",
                file=sys.stderr,
            )
            return 2
    try:
        revoked = revoke(args.dir, serial)
    except TlsError as exc:
        print(f"baton certs revoke: {exc}", file=sys.stderr)
        return 2
    print(f"{args.dir}: serial {serial:x} revoked ({len(revoked)} in revoked.crl)")
    return 0

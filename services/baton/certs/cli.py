"""``baton certs``: a mission's CA and its parts' certificates (baton/certs/make.py)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from baton.rpc.tls import Identity


def _identity(text: str) -> Identity:
    role, _, number = text.partition("-")
    try:
        return Identity(role, int(number)) if number else Identity(role)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(
            f"{text!r}: {exc}; a part is controller-N, drone or operator"
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


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Adds ``baton certs init`` and ``baton certs issue``."""
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
        "--controllers",
        type=_ids,
        default=[0, 1, 2],
        help="controller ids when no --config is given (default 0,1,2, the demo's)",
    )
    init.add_argument("--days", type=_days, default=365, help="validity in days (default 365)")
    init.set_defaults(run=_run_init)
    issue = actions.add_parser(
        "issue", help="add or renew one part's certificate, signed by the folder's CA"
    )
    issue.add_argument("dir", type=Path, help="a folder made by `baton certs init`")
    issue.add_argument("part", type=_identity, help="controller-N, drone or operator")
    issue.add_argument("--days", type=_days, default=365, help="validity in days (default 365)")
    issue.set_defaults(run=_run_issue)


def _run_init(args: argparse.Namespace) -> int:
    from baton.certs.make import init
    from baton.config import ConfigError, load_config
    from baton.rpc.tls import DRONE, OPERATOR

    ids = args.controllers
    if args.config:
        try:
            ids = load_config(args.config).ring_order
        except ConfigError as exc:
            print(f"baton certs: {exc}", file=sys.stderr)
            return 2
    parts = [*(Identity.controller(cid) for cid in ids), DRONE, OPERATOR]
    init(args.dir, parts, args.days)
    print(f"{args.dir}: CA and certificates for {', '.join(p.name for p in parts)}")
    return 0


def _run_issue(args: argparse.Namespace) -> int:
    from baton.certs.make import issue

    issue(args.dir, args.part, args.days)
    print(f"{args.dir}: certificate for {args.part.name} ({args.part.uri})")
    return 0

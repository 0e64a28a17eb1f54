"""The compose files under deploy/, read as compose reads them: their variables at
their defaults, and each service's command as an argv."""

from __future__ import annotations

import re
import shlex
from pathlib import Path
from typing import Any

import pytest
import yaml

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def expand(text: str) -> str:
    """Compose's ``${VAR:-default}`` interpolation, with every variable unset."""
    return re.sub(r"\$\{[A-Za-z_][A-Za-z0-9_]*:?-([^}]*)\}", r"\1", text)


def load_compose(name: str) -> dict[str, Any]:
    """deploy/NAME, its variables at their defaults."""
    loaded: dict[str, Any] = yaml.safe_load(expand((DEPLOY / name).read_text()))
    return loaded


def argv(value: str | list[str] | None) -> list[str]:
    """A service's ``command`` (a string or a list) as an argv."""
    if value is None:
        return []
    return shlex.split(value) if isinstance(value, str) else [str(v) for v in value]


def option(args: list[str], name: str) -> str:
    """The value after ``name`` in ``args``; fails the test if it is missing."""
    assert name in args, f"{name} missing from {args}"
    return args[args.index(name) + 1]


def parsed(args: list[str], service: str = "") -> Any:
    """``baton ARGS`` (``args[0]`` is ``baton``) parsed by baton's own parser; fails the
    test, naming the service, if it does not parse (argparse printed why on stderr)."""
    from baton.cli import build_parser

    assert args[:1] == ["baton"], args
    try:
        return build_parser().parse_args(args[1:])
    except SystemExit as exc:
        where = f"{service}: " if service else ""
        pytest.fail(f"{where}`baton {shlex.join(args[1:])}` does not parse (exit {exc.code})")

"""The compose files under deploy/, read as compose reads them: their variables at
their defaults, and each service's command as an argv."""

from __future__ import annotations

import re
import shlex
from pathlib import Path
from typing import Any

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

"""Runs a mission file against a controller: ``python -m baton.sdk.run FILE ADDRESS [k=v ...]``.

A mission file defines ``mission(drone, **params)``: a plain function gets a
blocking ``baton.sdk.Drone``, an ``async def`` one a ``baton.sdk.aio.Drone``
(run in its own event loop). Parameters given as
``key=value`` are passed by name, converted to the type of the function's
default for that parameter. The process exits 0 when the mission returns, 1
with the error when it raises, and always tells the controller it ended.
"""

from __future__ import annotations

import argparse
import asyncio
import importlib.util
import inspect
import sys
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from baton.lifecycle import die_with_parent
from baton.sdk import aio
from baton.sdk.drone import connect


class MissionLoadError(SystemExit):
    """A mission file that does not load, said in a line or two a mission author can act
    on: the file, the line, the cause (no traceback). A SystemExit, so that a program
    that loads one exits with the message."""


def describe_load_error(path: str, exc: BaseException) -> str:
    """``FILE, line N: Error: message`` and the line's source, for an exception raised
    while ``path`` was executed: a SyntaxError where it is, anything else at the deepest
    line of the mission file that led to it (and where it was raised, if elsewhere)."""
    cause = f"{type(exc).__name__}: {exc}"
    if isinstance(exc, SyntaxError):
        where = exc.filename or path
        cause = f"{type(exc).__name__}: {exc.msg}"
        source = (exc.text or "").strip()
        shown = f"{where}, line {exc.lineno}: {cause}"
        return f"{shown}\n    {source}" if source else shown
    frames = traceback.extract_tb(exc.__traceback__)
    mine = Path(path).resolve()
    in_file = [f for f in frames if Path(f.filename).resolve() == mine]
    if not in_file:
        return f"{path}: {cause}"
    frame = in_file[-1]
    shown = f"{path}, line {frame.lineno}: {cause}"
    last = frames[-1]
    if last is not frame and not last.filename.startswith("<"):
        shown += f" (raised in {last.filename}, line {last.lineno})"
    return f"{shown}\n    {frame.line}" if frame.line else shown


def load_mission(path: str) -> Callable[..., Any]:
    """The ``mission`` function of a mission file; MissionLoadError says why not."""
    file = Path(path)
    spec = importlib.util.spec_from_file_location(f"baton_mission_{file.stem}", file)
    if spec is None or spec.loader is None or not file.is_file():
        raise MissionLoadError(f"{path}: not a readable Python file")
    module = importlib.util.module_from_spec(spec)
    # Registered as imported modules are: dataclasses (and pickle) look a class's module up.
    sys.modules[spec.name] = module
    try:
        spec.loader.exec_module(module)
    except Exception as exc:  # anything a module's top level raises: the author's to fix
        raise MissionLoadError(describe_load_error(path, exc)) from None
    mission = getattr(module, "mission", None)
    if not callable(mission):
        raise MissionLoadError(f"{path}: defines no function `mission(drone, **params)`")
    return mission


def add_mission_arg(parser: argparse.ArgumentParser, help_text: str = "") -> None:
    """``--mission-arg KEY=VALUE``, repeatable: the pairs ``parse_params`` reads."""
    parser.add_argument(
        "--mission-arg",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=help_text or "a parameter of the mission function; repeatable",
    )


def parse_params(mission: Callable[..., Any], pairs: list[str]) -> dict[str, Any]:
    """``key=value`` strings, typed like the defaults of ``mission``'s parameters."""
    signature = inspect.signature(mission)
    params: dict[str, Any] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or key not in signature.parameters or key == "drone":
            known = [name for name in signature.parameters if name != "drone"]
            raise SystemExit(f"mission parameter {pair!r}: expected key=value with key in {known}")
        default = signature.parameters[key].default
        kind = type(default) if default is not inspect.Parameter.empty else str
        try:
            params[key] = kind(value) if kind is not bool else value.lower() in ("1", "true", "yes")
        except ValueError:
            raise SystemExit(
                f"mission parameter {key}: {value!r} is not a {kind.__name__}"
            ) from None
    return params


def run(path: str, address: str, pairs: list[str]) -> int:
    """Runs the mission; returns the process exit code."""
    mission = load_mission(path)
    params = parse_params(mission, pairs)
    if inspect.iscoroutinefunction(mission):
        return asyncio.run(_run_async(mission, address, params))
    drone = connect(address)
    try:
        mission(drone, **params)
    except Exception as exc:
        traceback.print_exc()
        drone.close(error=failure(exc))
        return 1
    drone.close()
    return 0


async def _run_async(mission: Callable[..., Any], address: str, params: dict[str, Any]) -> int:
    drone = aio.connect(address)
    try:
        await mission(drone, **params)
    except Exception as exc:
        traceback.print_exc()
        await drone.close(error=failure(exc))
        return 1
    await drone.close()
    return 0


def failure(exc: BaseException) -> str:
    """How a mission program's exception is told to its controller."""
    return f"{type(exc).__name__}: {exc}"


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("mission", help="the mission file (defines mission(drone, **params))")
    parser.add_argument("controller", help="the local controller, host:port")
    parser.add_argument("params", nargs="*", help="mission parameters as key=value")
    parser.add_argument(
        "--die-with-parent",
        type=int,
        metavar="PID",
        help="exit when the parent process PID (the controller) dies",
    )
    args = parser.parse_args(argv)
    if args.die_with_parent is not None:
        die_with_parent(args.die_with_parent)
    return run(args.mission, args.controller, args.params)


if __name__ == "__main__":
    sys.exit(main())

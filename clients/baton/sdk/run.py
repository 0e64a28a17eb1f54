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


def load_mission(path: str) -> Callable[..., Any]:
    """The ``mission`` function of a mission file."""
    file = Path(path)
    spec = importlib.util.spec_from_file_location(f"baton_mission_{file.stem}", file)
    if spec is None or spec.loader is None or not file.is_file():
        raise SystemExit(f"{path}: not a readable Python file")
    module = importlib.util.module_from_spec(spec)
    # Registered as imported modules are: dataclasses (and pickle) look a class's module up.
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    mission = getattr(module, "mission", None)
    if not callable(mission):
        raise SystemExit(f"{path}: defines no function `mission(drone, **params)`")
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

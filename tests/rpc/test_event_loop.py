"""``lifecycle.run``: every serving part's event loop, uvloop's unless the environment
says ``BATON_EVENT_LOOP=asyncio``; any other value is a clear error."""

from __future__ import annotations

import asyncio

import pytest
import uvloop

from baton.lifecycle import EVENT_LOOP_ENV, run


async def _loop_type() -> type:
    return type(asyncio.get_running_loop())


def test_the_parts_run_on_uvloop_by_default(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(EVENT_LOOP_ENV, raising=False)
    assert run(_loop_type()) is uvloop.Loop


def test_the_standard_loop_on_request(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(EVENT_LOOP_ENV, "asyncio")
    assert not issubclass(run(_loop_type()), uvloop.Loop)


def test_an_unknown_loop_is_refused_naming_the_variable_and_the_choices(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv(EVENT_LOOP_ENV, "trio")
    with pytest.raises(SystemExit) as exited:
        run(_loop_type())
    assert str(exited.value) == (
        "BATON_EVENT_LOOP='trio' in the environment: say one of uvloop, asyncio"
    )

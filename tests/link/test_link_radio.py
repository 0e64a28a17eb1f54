"""Radio range: the link carries connections only while the vehicle is within range."""

from __future__ import annotations

import asyncio
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers.links import RADIO, STATION, baton_link, place
from link_endpoints import Echo, connect

from baton.config import LinkSpec
from baton.link.proxy import LinkProxy
from baton.link.radio import Fade, RadioRange, parse_fade, parse_radio_range


async def echoes(address: str) -> bool:
    """Whether a new connection through the link carries a byte there and back (a link
    that refuses may reset it while it is being made, or after)."""
    try:
        reader, writer = await connect(address)
    except ConnectionError:
        return False
    try:
        writer.write(b"x")
        return await asyncio.wait_for(reader.read(1), 5) == b"x"
    except ConnectionError:
        return False
    finally:
        writer.close()


async def until(check, what: str, timeout_s: float = 10.0) -> None:  # type: ignore[no-untyped-def]
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while not await check():
        assert loop.time() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.02)


async def test_out_of_range_refuses_and_cuts_and_in_range_carries_again(
    echo: Echo, tmp_path: Path
) -> None:
    position = tmp_path / "vehicle-position.json"
    place(position, 300.0)
    proxy = LinkProxy("127.0.0.1:0", echo.address, LinkSpec(), LinkSpec(), RADIO, position)
    await proxy.start()
    try:
        assert proxy.in_range and await echoes(proxy.address)
        reader, writer = await connect(proxy.address)
        writer.write(b"y")
        assert await reader.read(1) == b"y"
        place(position, 501.0)  # just beyond the circle
        with pytest.raises(ConnectionResetError):
            # The open connection is cut: a reset, not a quiet end.
            assert await asyncio.wait_for(reader.read(1), 5) != b""
        writer.close()
        assert not proxy.in_range and proxy.counters.cut == 1
        assert not await echoes(proxy.address)
        assert proxy.counters.refused >= 1
        place(position, 500.0 - 1e-6)  # on the circle, to a micrometre: in range
        await until(lambda: echoes(proxy.address), "the link to carry again")
        assert proxy.in_range
    finally:
        await proxy.stop()


async def test_no_position_file_is_out_of_range(echo: Echo, tmp_path: Path) -> None:
    proxy = LinkProxy(
        "127.0.0.1:0", echo.address, LinkSpec(), LinkSpec(), RADIO, tmp_path / "nowhere.json"
    )
    await proxy.start()
    try:
        assert not proxy.in_range and not await echoes(proxy.address)
    finally:
        await proxy.stop()


def test_radio_range_options_are_checked() -> None:
    assert parse_radio_range("47.1,8.2,500") == RadioRange(47.1, 8.2, 500.0)
    with pytest.raises(ValueError, match="expected LAT,LON,METRES"):
        parse_radio_range("47.1,8.2")
    with pytest.raises(ValueError, match="range must be > 0"):
        parse_radio_range("47.1,8.2,0")
    result = subprocess.run(
        [sys.executable, "-m", "baton.cli", "link", "--target", "127.0.0.1:1", "--range", "4,8,5"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode == 2
    assert "--range and --position-file go together" in result.stderr


async def test_baton_link_follows_the_position_file(echo: Echo, tmp_path: Path) -> None:
    position = tmp_path / "vehicle-position.json"
    place(position, -200.0)
    radio = f"{STATION.latitude_deg},{STATION.longitude_deg},500"
    async with baton_link(
        echo.address, "--off", "--range", radio, "--position-file", str(position)
    ) as link:
        assert await echoes(link.address)
        place(position, -800.0)

        async def refused() -> bool:
            return not await echoes(link.address)

        await until(refused, "the link to refuse")
        # The first failure may be a connection it accepted and then cut, as it learnt
        # the vehicle had left (CI); once it knows, a new one is refused.
        assert await refused()
        _, lines = await link.terminate()
    left = [line for line in lines if line.get("msg") == "vehicle out of radio range"]
    assert left and left[0]["distance"] == "800 m"
    stopped = next(line for line in lines if line.get("msg") == "link stopped")
    assert stopped["refused"] >= 1


def test_a_fade_degrades_linearly_over_the_last_part_of_the_range() -> None:
    fade = Fade(begins=0.8, latency_s=0.05, bandwidth_factor=0.25)
    assert [fade.depth(d, 500.0) for d in (0.0, 400.0, 450.0, 500.0, 600.0)] == [
        0.0,
        0.0,
        pytest.approx(0.5),
        1.0,
        1.0,
    ]
    base = LinkSpec(latency=0.02, bandwidth=20e6)
    assert fade.spec(base, 0.0) == base
    half = fade.spec(base, 0.5)
    assert half.latency == pytest.approx(0.045) and half.bandwidth == pytest.approx(12.5e6)
    edge = fade.spec(base, 1.0)
    assert edge.latency == pytest.approx(0.07) and edge.bandwidth == pytest.approx(5e6)
    assert fade.spec(LinkSpec(), 1.0).bandwidth is None  # unlimited stays unlimited
    assert parse_fade("0.8,50ms,0.25") == fade
    expected = re.escape("expected BEGINS,LATENCY,FACTOR like '0.8,50ms,0.25'")
    with pytest.raises(ValueError, match=expected):
        parse_fade("0.8,50ms")
    with pytest.raises(ValueError, match=re.escape("bandwidth factor must be in (0, 1], got 0.0")):
        parse_fade("0.8,50ms,0")
    with pytest.raises(ValueError, match=re.escape("begins at a fraction of the range in [0, 1)")):
        parse_fade("1,50ms,0.5")
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "baton.cli",
            "link",
            "--target",
            "127.0.0.1:1",
            "--fade",
            "0.8,1s,1",
        ],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode == 2 and "--fade fades a radio range" in result.stderr


async def round_trip_s(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> float:
    started = time.monotonic()
    writer.write(b"z")
    assert await asyncio.wait_for(reader.read(1), 10) == b"z"
    return time.monotonic() - started


async def test_an_open_connection_slows_as_the_vehicle_nears_the_edge(
    echo: Echo, tmp_path: Path
) -> None:
    position = tmp_path / "vehicle-position.json"
    place(position, 100.0)
    fade = Fade(begins=0.5, latency_s=0.2, bandwidth_factor=0.25)
    spec = LinkSpec(bandwidth=8e6)
    proxy = LinkProxy("127.0.0.1:0", echo.address, spec, spec, RADIO, position, fade)
    await proxy.start()
    try:
        reader, writer = await connect(proxy.address)
        near = await round_trip_s(reader, writer)
        # At the circle: 200 ms more each way, a quarter of the bandwidth, on the
        # connection already open.
        place(position, 499.9)

        async def faded() -> bool:
            return proxy.depth > 0.999

        await until(faded, "the link to fade")
        [up, down] = sorted(proxy._directions, key=lambda d: d.upward)
        assert up.line.bandwidth == down.line.bandwidth == pytest.approx(2e6, rel=2e-3)
        far = await round_trip_s(reader, writer)
        assert far >= 0.399 > near, (near, far)
        # Back near the station: as fast as before.
        place(position, 100.0)

        async def clear() -> bool:
            return proxy.depth == 0.0

        await until(clear, "the fade to clear")
        assert await round_trip_s(reader, writer) < 0.4
        writer.close()
    finally:
        await proxy.stop()

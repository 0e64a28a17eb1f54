"""Radio range with tc netem (``baton radio-netem``): radio.py's answer as tc arguments.

The pure part (what netem gets for a position) is checked directly; the command
runs for real with stand-ins for ``ip`` and ``tc`` that record what they are
asked, while a test moves the vehicle by rewriting its position file.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import pytest
from helpers.links import RADIO, STATION, place
from waiting import STEP_TIMEOUT_S

from baton.config import LinkSpec
from baton.link.netem import (
    OUT_OF_RANGE,
    NetemError,
    NetemRadio,
    interface_on,
    netem_args,
    radio_netem_args,
)
from baton.link.radio import Fade
from baton.sdk import offset

WIFI = LinkSpec(latency=0.002, bandwidth=20e6)
FADE = Fade(0.8, 0.05, 0.25)


def where(east_m: float) -> tuple[float, float]:
    point = offset(STATION, 0.0, east_m)
    return point.latitude_deg, point.longitude_deg


def test_netem_args_are_the_link_spec_in_tc_units() -> None:
    assert netem_args(WIFI) == ("delay", "2000us", "rate", "20000kbit")
    assert netem_args(LinkSpec(latency=0.02)) == ("delay", "20000us")  # unlimited: no rate
    # Rounded to 100 us and 1 kbit/s: a fade moving by less leaves tc alone.
    assert netem_args(LinkSpec(latency=0.00204, bandwidth=20_000_400)) == netem_args(WIFI)


def test_in_range_the_drone_link_out_of_range_everything_dropped() -> None:
    assert radio_netem_args(RADIO, WIFI, None, where(0)) == netem_args(WIFI)
    assert radio_netem_args(RADIO, WIFI, None, where(499.9)) == netem_args(WIFI)
    assert radio_netem_args(RADIO, WIFI, None, where(500.1)) == OUT_OF_RANGE
    assert radio_netem_args(RADIO, WIFI, None, None) == OUT_OF_RANGE  # position unknown
    assert OUT_OF_RANGE == ("loss", "100%")


def test_the_fade_is_radio_py_s() -> None:
    # Before the fade begins: the plain link; on the circle: the fade's full depth.
    assert radio_netem_args(RADIO, WIFI, FADE, where(399)) == netem_args(WIFI)
    edge = radio_netem_args(RADIO, WIFI, FADE, where(499.99))
    assert edge[0::2] == ("delay", "rate")
    assert int(edge[1].removesuffix("us")) == 52000  # 2 ms + 50 ms
    assert int(edge[3].removesuffix("kbit")) == pytest.approx(5000, abs=5)  # a quarter
    halfway = radio_netem_args(RADIO, WIFI, FADE, where(450))
    assert halfway == netem_args(FADE.spec(WIFI, FADE.depth(450, 500)))
    assert halfway == ("delay", "27000us", "rate", "12500kbit")


class FakeTools:
    """``ip`` and ``tc`` answered in-process: one route, tc calls recorded."""

    def __init__(self, tc_fails: bool = False) -> None:
        self.calls: list[list[str]] = []
        self.tc_fails = tc_fails

    def __call__(self, argv: Sequence[str]) -> subprocess.CompletedProcess[str]:
        argv = list(argv)
        self.calls.append(argv)
        if argv[0] == "ip":
            out = "172.28.2.0/24 dev eth1 proto kernel scope link src 172.28.2.3\n"
            found = argv[-1] == "172.28.2.0/24"
            return subprocess.CompletedProcess(argv, 0, out if found else "", "")
        if self.tc_fails:
            return subprocess.CompletedProcess(
                argv, 2, "", "Error: Specified qdisc kind is unknown."
            )
        return subprocess.CompletedProcess(argv, 0, "", "")


def test_interface_on_finds_the_subnet_s_device_or_says_what_is_wrong() -> None:
    assert interface_on("172.28.2.0/24", FakeTools()) == "eth1"
    with pytest.raises(NetemError, match=r"no interface on 10\.1\.2\.0/24"):
        interface_on("10.1.2.0/24", FakeTools())


def test_netem_radio_applies_only_changes_and_reasserts_on_demand(tmp_path: Path) -> None:
    position = tmp_path / "position.json"
    tools = FakeTools()
    radio = NetemRadio("eth1", RADIO, position, WIFI, None, run=tools)
    radio.look()  # no file yet: position unknown
    place(position, 100)
    radio.look()
    radio.look()  # unchanged: no tc
    radio.look(reassert=True)
    place(position, 600)
    radio.look()
    base = ["tc", "qdisc", "replace", "dev", "eth1", "root", "netem"]
    assert tools.calls == [
        [*base, "loss", "100%"],
        [*base, *netem_args(WIFI)],
        [*base, *netem_args(WIFI)],
        [*base, "loss", "100%"],
    ]
    assert radio.in_range is False


def test_netem_radio_says_what_tc_needs_when_it_fails(tmp_path: Path) -> None:
    radio = NetemRadio("eth1", RADIO, tmp_path / "none.json", WIFI, run=FakeTools(tc_fails=True))
    with pytest.raises(NetemError, match=r"NET_ADMIN.*sch_netem"):
        radio.look()


# -- the command, for real ----------------------------------------------------------------


def _stand_ins(bin_dir: Path, log: Path) -> dict[str, str]:
    bin_dir.mkdir()
    (bin_dir / "ip").write_text(
        '#!/bin/sh\nfor last; do :; done\n[ "$last" = 172.28.2.0/24 ] && '
        'echo "172.28.2.0/24 dev eth7 proto kernel scope link"\nexit 0\n'
    )
    (bin_dir / "tc").write_text(f'#!/bin/sh\necho "$*" >> "{log}"\n')
    for tool in ("ip", "tc"):
        (bin_dir / tool).chmod(0o755)
    return {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}"}


def _baton(*argv: str) -> list[str]:
    return [sys.executable, "-m", "baton.cli", *argv]


def _wait_for_line(log: Path, line: str, times: int = 1) -> list[str]:
    deadline = time.monotonic() + STEP_TIMEOUT_S
    lines: list[str] = []
    while time.monotonic() < deadline:
        lines = log.read_text().splitlines() if log.exists() else []
        if lines.count(line) >= times:
            return lines
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for tc {line!r}; tc was asked: {lines}")


def test_radio_netem_follows_the_vehicle_in_and_out_of_range(tmp_path: Path) -> None:
    log, position, ready = tmp_path / "tc.log", tmp_path / "position.json", tmp_path / "ready"
    env = _stand_ins(tmp_path / "bin", log)
    station = f"{RADIO.latitude_deg},{RADIO.longitude_deg},{RADIO.range_m:g}"
    place(position, 600)
    process = subprocess.Popen(
        _baton(
            "radio-netem",
            "--subnet",
            "172.28.2.0/24",
            "--latency",
            "2ms",
            "--bandwidth",
            "20Mbit",
            "--range",
            station,
            "--fade",
            "0.8,50ms,0.25",
            "--position-file",
            str(position),
            "--ready-file",
            str(ready),
            "--reassert",
            "0",
        ),
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        dropped = "qdisc replace dev eth7 root netem loss 100%"
        assert _wait_for_line(log, dropped) == [dropped]
        # Written once the first qdisc is in place, before the loop begins.
        deadline = time.monotonic() + STEP_TIMEOUT_S
        while not ready.exists() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert ready.read_text() == "eth7\n"
        place(position, 100)
        _wait_for_line(log, "qdisc replace dev eth7 root netem delay 2000us rate 20000kbit")
        place(position, 450)
        _wait_for_line(log, "qdisc replace dev eth7 root netem delay 27000us rate 12500kbit")
        place(position, 700)
        _wait_for_line(log, dropped, times=2)
    finally:
        process.terminate()
        _, stderr = process.communicate(timeout=STEP_TIMEOUT_S)
    assert process.returncode == 0, stderr
    assert "vehicle in radio range" in stderr and "vehicle out of radio range" in stderr


def test_radio_netem_refuses_a_subnet_it_is_not_on(tmp_path: Path) -> None:
    log = tmp_path / "tc.log"
    env = _stand_ins(tmp_path / "bin", log)
    done = subprocess.run(
        _baton(
            "radio-netem",
            "--subnet",
            "10.9.9.0/24",
            "--range",
            "47.3977,8.5456,500",
            "--position-file",
            str(tmp_path / "p.json"),
        ),
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 1
    assert "no interface on 10.9.9.0/24" in done.stderr
    assert not log.exists()

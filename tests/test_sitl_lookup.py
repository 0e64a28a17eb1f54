"""Where baton finds ArduPilot SITL: the flag, then BATON_SITL_BINARY, then arducopter
on PATH; where there is none, every caller says how to point baton at a build."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from autopilots import SKIP_REASON

from baton.sitl.launcher import (
    BUILD_INSTRUCTIONS,
    HOW_TO_POINT_AT_A_BUILD,
    NOT_FOUND,
    PARAMS_FILE,
    SitlBinaryNotFound,
    SitlParamError,
    SitlSettings,
    find_binary,
    find_defaults,
    parse_param,
)
from baton.testbed.local import LocalTestbed, TestbedPlan


def fake_build(root: Path) -> Path:
    """An ArduPilot tree with a SITL "build": an executable arducopter, copter.parm."""
    binary = root / "build" / "sitl" / "bin" / "arducopter"
    binary.parent.mkdir(parents=True)
    binary.write_text("#!/bin/sh\necho fake arducopter\n")
    binary.chmod(0o755)
    params = root / "Tools" / "autotest" / "default_params" / "copter.parm"
    params.parent.mkdir(parents=True)
    params.write_text("FRAME_TYPE 0\n")
    return binary


def test_the_variable_names_the_binary(tmp_path: Path) -> None:
    binary = fake_build(tmp_path / "ardupilot")
    env = {"BATON_SITL_BINARY": str(binary), "PATH": ""}
    assert find_binary(None, env) == binary.resolve()


def test_the_flag_comes_before_the_variable(tmp_path: Path) -> None:
    first = fake_build(tmp_path / "a")
    second = fake_build(tmp_path / "b")
    assert find_binary(first, {"BATON_SITL_BINARY": str(second)}) == first.resolve()


def test_the_variable_comes_before_path(tmp_path: Path) -> None:
    named = fake_build(tmp_path / "a")
    on_path = fake_build(tmp_path / "b")
    env = {"BATON_SITL_BINARY": str(named), "PATH": str(on_path.parent)}
    assert find_binary(None, env) == named.resolve()


def test_arducopter_on_path_is_found(tmp_path: Path) -> None:
    binary = fake_build(tmp_path / "ardupilot")
    assert find_binary(None, {"PATH": f"/nonexistent:{binary.parent}"}) == binary.resolve()


def test_a_named_place_without_a_binary_is_an_error_not_a_fallback(tmp_path: Path) -> None:
    on_path = fake_build(tmp_path / "b")
    env = {"BATON_SITL_BINARY": str(tmp_path / "nope"), "PATH": str(on_path.parent)}
    with pytest.raises(SitlBinaryNotFound, match=r"BATON_SITL_BINARY=.*nope: no such file"):
        find_binary(None, env)
    with pytest.raises(SitlBinaryNotFound, match=r"--sitl-binary .*nope: no such file"):
        find_binary(tmp_path / "nope", {})


def test_none_found_says_how_to_point_baton_at_a_build() -> None:
    with pytest.raises(SitlBinaryNotFound) as caught:
        find_binary(None, {"PATH": ""})
    message = str(caught.value)
    assert message == NOT_FOUND
    for how in ("--sitl-binary PATH", "BATON_SITL_BINARY=PATH", "arducopter on PATH"):
        assert how in message
    assert BUILD_INSTRUCTIONS in message
    assert BUILD_INSTRUCTIONS.startswith("https://ardupilot.org/")


def test_the_tests_skip_message_says_the_same() -> None:
    assert HOW_TO_POINT_AT_A_BUILD in SKIP_REASON


def test_the_parameters_of_the_build_tree_are_found(tmp_path: Path) -> None:
    binary = fake_build(tmp_path / "ardupilot")
    expected = tmp_path / "ardupilot" / "Tools" / "autotest" / "default_params" / "copter.parm"
    assert find_defaults(binary) == expected
    beside = binary.parent / "copter.parm"
    beside.write_text("")
    assert find_defaults(binary) == beside


def run_baton(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "baton.cli", *args],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "PATH": "", **env},
    )


def test_baton_sitl_finds_the_variables_binary(tmp_path: Path) -> None:
    binary = fake_build(tmp_path / "ardupilot")
    done = run_baton({"BATON_SITL_BINARY": str(binary)}, "sitl", "--which")
    assert done.returncode == 0, done.stderr
    found, params = done.stdout.splitlines()
    assert Path(found) == binary.resolve()
    assert Path(params).name == "copter.parm"


@pytest.mark.parametrize(
    "argv", [("sitl", "--which"), ("testbed", "--vehicle", "sitl")], ids=["sitl", "testbed"]
)
def test_the_command_line_without_a_binary_says_how_to_point_at_one(argv: tuple[str]) -> None:
    env = {k: "" for k in ("BATON_SITL_BINARY",)}
    done = run_baton(env, *argv)
    assert done.returncode == 2
    assert NOT_FOUND in done.stderr, done.stderr
    assert "Traceback" not in done.stderr


def test_a_runs_own_parameters_follow_the_defaults(tmp_path: Path) -> None:
    """SitlSettings.params: a parameter file of the run, named after the defaults in
    --defaults' comma-separated list (ArduPilot applies them in order: the run's win)."""
    binary = fake_build(tmp_path / "ardupilot")
    settings = SitlSettings(binary, params=(("BATT_CAPACITY", 1000.0), ("SIM_BATT_CAP_AH", 1.5)))
    argv = settings.argv(3)
    defaults = argv[argv.index("--defaults") + 1]
    assert defaults == f"{find_defaults(binary)},{PARAMS_FILE}"
    assert settings.params_text() == "BATT_CAPACITY 1000\nSIM_BATT_CAP_AH 1.5\n"
    # None of the run's own: the defaults alone, as before.
    plain = SitlSettings(binary).argv(3)
    assert plain[plain.index("--defaults") + 1] == str(find_defaults(binary))
    (binary.parents[3] / "Tools" / "autotest" / "default_params" / "copter.parm").unlink()
    assert settings.argv(3)[-2:] == ["--defaults", PARAMS_FILE]


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("BATT_CAPACITY", "expected NAME=VALUE, e.g. BATT_CAPACITY=1000"),
        ("batt_capacity=1000", "'batt_capacity' is no ArduPilot parameter name"),
        ("A_NAME_OF_17_CHARS=1", "at most 16"),
        ("BATT_CAPACITY=lots", "'lots' is not a finite number"),
        ("BATT_CAPACITY=nan", "'nan' is not a finite number"),
    ],
)
def test_a_bad_parameter_says_what_is_wrong(text: str, says: str) -> None:
    with pytest.raises(SitlParamError, match=re.escape(says)):
        parse_param(text)
    assert parse_param("FS_GCS_TIMEOUT=2.5") == ("FS_GCS_TIMEOUT", 2.5)


def test_baton_sitl_writes_the_runs_parameters_where_sitl_runs(tmp_path: Path) -> None:
    """``baton sitl --param`` with a stand-in binary that says what it was given, prints
    SITL's listening line and waits: the file is in the workdir, named in --defaults."""
    binary = fake_build(tmp_path / "ardupilot")
    binary.write_text(
        '#!/bin/sh\necho "$@" > argv.txt\necho "SERIAL0 on TCP port 5760"\nexec sleep 60\n'
    )
    workdir, url_file = tmp_path / "run", tmp_path / "sitl.url"
    params = ["--param", "BATT_CAPACITY=1000", "--param", "BATT_LOW_MAH=0"]
    where = ["--workdir", str(workdir), "--url-file", str(url_file), "--instance", "41"]
    process = subprocess.Popen(
        [sys.executable, "-m", "baton.cli", "sitl", "--sitl-binary", str(binary), *params, *where],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 30
        while not url_file.exists():
            assert process.poll() is None, process.communicate()[1]
            assert time.monotonic() < deadline, "baton sitl did not announce its ports"
            time.sleep(0.05)
    finally:
        process.terminate()
        process.wait(10)
    assert (workdir / PARAMS_FILE).read_text() == "BATT_CAPACITY 1000\nBATT_LOW_MAH 0\n"
    given = (workdir / "argv.txt").read_text().split()
    assert given[given.index("--defaults") + 1].endswith(f"copter.parm,{PARAMS_FILE}")


def test_a_bad_parameter_on_the_command_line_names_the_option() -> None:
    done = run_baton({}, "sitl", "--param", "BATT_CAPACITY")
    assert done.returncode == 2
    assert "argument --param: 'BATT_CAPACITY': expected NAME=VALUE" in done.stderr


def test_the_testbed_gives_sitl_the_plans_parameters(tmp_path: Path) -> None:
    plan = TestbedPlan(vehicle="sitl", sitl_params=(("BATT_CAPACITY", 1000.0),))
    part = LocalTestbed(plan, tmp_path)._vehicle_part()
    assert part is not None
    name, argv, _ = part
    assert name == "sitl" and argv[argv.index("--param") + 1] == "BATT_CAPACITY=1000"

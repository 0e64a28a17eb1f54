"""A mission file that does not load says which file, which line and why, in a line or
two, with no traceback: wherever it is loaded (the testbed, the controller's program
runner, baton replay)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from baton.sdk.run import MissionLoadError, load_mission

BROKEN = {
    "missing_module": (
        "import baton_no_such_module\n",
        "line 1: ModuleNotFoundError: No module named 'baton_no_such_module'",
    ),
    "syntax": (
        "def mission(drone):\n    x = (\n",
        "line 2: SyntaxError: '(' was never closed",
    ),
    "bad_config": (
        "ALTITUDE_M = float('ten')\n\ndef mission(drone):\n    pass\n",
        "line 1: ValueError: could not convert string to float: 'ten'",
    ),
}


def write(tmp_path: Path, name: str) -> Path:
    source, _ = BROKEN[name]
    path = tmp_path / f"{name}.py"
    path.write_text(source)
    return path


@pytest.mark.parametrize("name", sorted(BROKEN))
def test_load_mission_names_the_file_the_line_and_the_cause(tmp_path: Path, name: str) -> None:
    path = write(tmp_path, name)
    with pytest.raises(MissionLoadError) as caught:
        load_mission(str(path))
    message = str(caught.value)
    first = message.splitlines()[0]
    assert first == f"{path}, line {BROKEN[name][1].partition('line ')[2]}"
    assert len(message.splitlines()) <= 2
    assert "Traceback" not in message


def test_an_error_raised_elsewhere_points_at_the_mission_files_line(tmp_path: Path) -> None:
    (tmp_path / "helper_cfg.py").write_text("def load():\n    raise ValueError('no altitude')\n")
    path = tmp_path / "uses_helper.py"
    path.write_text("import helper_cfg\n\nhelper_cfg.load()\n")
    sys.path.insert(0, str(tmp_path))
    try:
        with pytest.raises(MissionLoadError) as caught:
            load_mission(str(path))
    finally:
        sys.path.remove(str(tmp_path))
    first = str(caught.value).splitlines()[0]
    assert first.startswith(f"{path}, line 3: ValueError: no altitude (raised in ")
    assert "helper_cfg.py, line 2)" in first


def baton(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "baton.cli", *args],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "BATON_SITL_BINARY": ""},
    )


@pytest.mark.parametrize("name", sorted(BROKEN))
def test_the_testbed_refuses_it_in_two_lines(tmp_path: Path, name: str) -> None:
    path = write(tmp_path, name)
    done = baton("testbed", "--mission", str(path), "--workdir", str(tmp_path / "run"))
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert "Traceback" not in done.stderr
    assert len(lines) <= 2, done.stderr
    assert lines[0] == f"baton testbed: --mission: {path}, {BROKEN[name][1]}"


def test_the_program_runner_exits_with_it(tmp_path: Path) -> None:
    path = write(tmp_path, "missing_module")
    done = subprocess.run(
        [sys.executable, "-m", "baton.sdk.run", str(path), "127.0.0.1:9"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 1
    assert "Traceback" not in done.stderr
    assert done.stderr.splitlines()[0] == f"{path}, {BROKEN['missing_module'][1]}"

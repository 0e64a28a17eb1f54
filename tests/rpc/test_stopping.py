"""A service asked to stop exits within STOP_DEADLINE_S even when its clean-up hangs.

CI saw a controller still running 10 s after its testbed was killed with
SIGKILL (each part gets SIGTERM then, ``lifecycle.die_with_parent``): its
clean exit waited on calls to peers that were dying with it, on a loaded
machine. Here a service's clean-up hangs outright.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

from baton.lifecycle import STOP_DEADLINE_S

HANGS_WHEN_STOPPED = """
import asyncio, pathlib, sys
from baton.lifecycle import run_until_signalled

async def main(stop):
    pathlib.Path(sys.argv[1]).write_text("up")
    await stop.wait()
    await asyncio.Event().wait()  # clean-up that never ends
    return 0

sys.exit(asyncio.run(run_until_signalled(main)))
"""

STOPS_CLEANLY = HANGS_WHEN_STOPPED.replace("await asyncio.Event().wait()", "pass")


def _start(source: str, tmp_path: Path) -> subprocess.Popen[str]:
    ready = tmp_path / "up"
    process = subprocess.Popen(
        [sys.executable, "-c", source, str(ready)], stderr=subprocess.PIPE, text=True
    )
    deadline = time.monotonic() + 20
    while not ready.exists():
        assert process.poll() is None, process.stderr.read() if process.stderr else ""
        assert time.monotonic() < deadline, "the service never came up"
        time.sleep(0.02)
    return process


def test_a_hung_clean_up_is_cut_off_at_the_deadline_and_says_so(tmp_path: Path) -> None:
    process = _start(HANGS_WHEN_STOPPED, tmp_path)
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=STOP_DEADLINE_S + 15)
    assert process.returncode == 1
    assert f"still stopping {STOP_DEADLINE_S:g} s after SIGTERM; exiting now" in err


def test_a_clean_stop_exits_with_its_own_code_and_no_word(tmp_path: Path) -> None:
    process = _start(STOPS_CLEANLY, tmp_path)
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=15)
    assert process.returncode == 0
    assert "still stopping" not in err

"""``baton testbed`` as a process, and the report it writes."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path


def baton(*args: str) -> list[str]:
    """The argv of ``baton ARGS`` in this interpreter."""
    return [sys.executable, "-m", "baton.cli", *args]


def run_testbed(tmp_path: Path, *args: str) -> dict:  # type: ignore[type-arg]
    """Runs `baton testbed ARGS` to the end; expects success and returns its report."""
    report_path = tmp_path / "report.json"
    result = subprocess.run(
        baton("testbed", *args, "--report", str(report_path), "--workdir", str(tmp_path / "w")),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "mission COMPLETED" in result.stdout
    report: dict = json.loads(report_path.read_text())  # type: ignore[type-arg]
    report["stdout"] = result.stdout
    return report


def baton_run(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    """Runs ``baton ARGS`` to the end, its output captured."""
    return subprocess.run(baton(*args), capture_output=True, text=True, timeout=timeout)


def fly_plan(tmp_path: Path, plan: Path, handovers: Sequence[str], *args: str) -> dict:  # type: ignore[type-arg]
    """`baton testbed --mission PLAN` at 20x with the ``REQNR:ID`` handovers, to the end;
    its report (with ``stdout``)."""
    flags = [arg for h in handovers for arg in ("--handover", h)]
    return run_testbed(tmp_path, "--mission", str(plan), "--speedup", "20", *flags, *args)

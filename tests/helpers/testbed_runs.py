"""``baton testbed`` as a process, and the report it writes."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import yaml

from baton.testbed.local import free_port

CORRIDOR = Path(__file__).parents[2] / "examples" / "corridor.yaml"


def baton(*args: str) -> list[str]:
    """The argv of ``baton ARGS`` in this interpreter."""
    return [sys.executable, "-m", "baton.cli", *args]


def baton_process(*args: str) -> subprocess.Popen[str]:
    """``baton ARGS`` started in this interpreter, its output piped (text)."""
    return subprocess.Popen(baton(*args), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


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


def corridor_on_free_ports(
    tmp_path: Path,
    policy: str,
    max_rtt: str | None = None,
    prepare_timeout: str | None = None,
    lead: str | None = None,
) -> Path:
    """examples/corridor.yaml on free ports with the handover ``policy`` and the given
    thresholds, written in ``tmp_path``; its path."""
    document = yaml.safe_load(CORRIDOR.read_text())
    document["drone"]["address"] = f"127.0.0.1:{free_port()}"
    for controller in document["controllers"]:
        controller["address"] = f"127.0.0.1:{free_port()}"
    document["handover_policy"]["name"] = policy
    if max_rtt is not None:
        document["handover_policy"]["max_rtt"] = max_rtt
    if lead is not None:
        document["handover_policy"]["lead"] = lead
    if prepare_timeout is not None:
        document["prepare_timeout"] = prepare_timeout
    config = tmp_path / "corridor.yaml"
    config.write_text(yaml.safe_dump(document))
    return config

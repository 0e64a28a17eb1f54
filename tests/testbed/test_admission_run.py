"""``baton testbed --admit`` across real processes: the ring and the first master
come from mission admission over the corridor's stations, and a route no station
covers is refused before anything starts."""

from __future__ import annotations

from pathlib import Path

import yaml
from helpers.testbed_runs import baton_run, corridor_on_free_ports, run_testbed


def test_a_covered_route_flies_with_the_admitted_ring(tmp_path: Path) -> None:
    # The file says ring 3, 2, 1, 0 from master 3: admission, not the file, decides.
    config = corridor_on_free_ports(tmp_path, "nearest")
    document = yaml.safe_load(config.read_text())
    document["ring"], document["initial_master"] = [3, 2, 1, 0], 3
    config.write_text(yaml.safe_dump(document))

    # 400 m east: station 0 holds take-off, station 1 is entered 3 m out; 2 and 3 never.
    report = run_testbed(
        tmp_path,
        *("--config", str(config), "--admit", "--mission", "corridor"),
        *("--length", "400", "--spacing", "100"),
    )
    assert (
        "admission: ring 0 (from 0 m), 1 (from 3 m) of a 400 m route; first master 0, the "
        "nearest to take-off; controller(s) 2, 3 cover none of it: not started"
    ) in report["stdout"]
    setup = report["setup"]
    assert setup["controllers"] == 2 and setup["ring"] == [0, 1] and setup["initial_master"] == 0
    assert report["completed"] and report["replicas_consistent"] and report["exactly_once"]
    assert report["side_effects"]["pictures_taken"] == 5
    # Flown by the admitted ring: from station 0 over to station 1 by the range policy.
    assert report["masters"] == [0, 1]
    logs = {p.name for p in (tmp_path / "w" / "logs").iterdir()}
    assert {"controller-0.log", "controller-1.log"} <= logs
    assert not {n for n in logs if n.startswith(("controller-2", "controller-3"))}, logs


def test_an_uncovered_route_is_refused_naming_the_stretch_and_nothing_starts(
    tmp_path: Path,
) -> None:
    config = corridor_on_free_ports(tmp_path, "nearest")
    workdir, report = tmp_path / "w", tmp_path / "report.json"
    result = baton_run(
        "testbed",
        *("--config", str(config), "--admit", "--mission", "corridor", "--length", "2500"),
        *("--workdir", str(workdir), "--report", str(report)),
        timeout=60,
    )
    assert result.returncode == 2, result.stdout + result.stderr
    assert (
        "--admit: the mission is refused: route: a stretch no station covers: from "
        "(47.397742, 8.572103) at 1997 m along the route to (47.397742, 8.578771) at "
        "2500 m (503 m)"
    ) in result.stderr
    # Refused before anything started: no workdir, no part's log, no report.
    assert not workdir.exists() and not report.exists()
    assert "logs in" not in result.stdout

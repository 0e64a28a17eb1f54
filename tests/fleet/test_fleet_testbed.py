"""``baton testbed --fleet FILE``: drones over stations on one machine, each mission
exactly once at its vehicle and camera, with consistent replicas."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from helpers.testbed_runs import baton_run

from baton.cli import main

EXAMPLES = Path(__file__).parents[2] / "examples"
FLEET, FLEET_SIX = EXAMPLES / "fleet.yaml", EXAMPLES / "fleet-six.yaml"


# On demand (pytest -m slow): 30-40 s; tests/fleet/test_stations.py flies two missions
# over shared station processes in CI.
@pytest.mark.slow
def test_the_example_fleet_flies_every_mission_exactly_once_over_shared_stations(
    tmp_path: Path,
) -> None:
    report = tmp_path / "fleet.json"
    result = baton_run(
        "testbed", "--fleet", str(FLEET), "--workdir", str(tmp_path), "--report", str(report)
    )
    assert result.returncode == 0, result.stdout + result.stderr
    lines = {line.split()[0]: line.split() for line in result.stdout.splitlines() if line}
    # d1 crosses all three stations and hands over on the way; d2 shares two of them.
    assert lines["d1"][2] == "1,2,3" and "->" in lines["d1"][3], result.stdout
    assert lines["d2"][2] == "2,3", result.stdout
    for drone in ("d1", "d2"):
        assert lines[drone][-2:] == ["True", "consistent"], result.stdout
    assert "fleet: 2/2 missions completed exactly once" in result.stdout
    assert json.loads(report.read_text())["summary"] == {"missions": 2, "ok": 2}


@pytest.mark.slow
def test_six_drones_over_four_stations_each_exactly_once(tmp_path: Path) -> None:
    """About 2 minutes on 2 cores: the stations host up to five missions each."""
    result = baton_run(
        "testbed",
        "--fleet",
        str(FLEET_SIX),
        "--workdir",
        str(tmp_path),
        "--report",
        str(tmp_path / "fleet.json"),
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "fleet: 6/6 missions completed exactly once" in result.stdout


def test_a_fleet_with_an_uncovered_route_or_a_bad_field_starts_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fleet = yaml.safe_load(FLEET.read_text())
    fleet["drones"][1]["mission"]["length_m"] = 3000  # far past station 3
    too_far = tmp_path / "too-far.yaml"
    too_far.write_text(yaml.safe_dump(fleet))
    assert main(["testbed", "--fleet", str(too_far), "--workdir", str(tmp_path / "w")]) == 2
    err = capsys.readouterr().err
    assert "drone d2's mission is refused" in err and "a stretch no station covers" in err
    assert not (tmp_path / "w" / "parts").exists()

    fleet["drones"][1]["name"] = "d1"
    twice = tmp_path / "twice.yaml"
    twice.write_text(yaml.safe_dump(fleet))
    assert main(["testbed", "--fleet", str(twice)]) == 2
    assert f"{twice}: (top level): drones[].name: d1 twice" in capsys.readouterr().err


def test_external_parts_need_a_fleet_and_must_name_its_parts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    parts = tmp_path / "parts.yaml"
    parts.write_text(yaml.safe_dump({"certs": "c", "stations": {1: "127.0.0.1:1"}, "drones": {}}))
    assert main(["testbed", "--external", str(parts)]) == 2
    assert "give --fleet FILE too" in capsys.readouterr().err
    assert main(["testbed", "--fleet", str(FLEET), "--external", str(parts)]) == 2
    assert f"{parts}: drones: needs at least 1 entry; add one" in capsys.readouterr().err
    parts.write_text(
        yaml.safe_dump({"certs": "c", "stations": {1: "h:1"}, "drones": {"d1": "h:2"}})
    )
    assert main(["testbed", "--fleet", str(FLEET), "--external", str(parts)]) == 2
    assert f"{parts}: stations: no address for 2, 3; add where each runs" in (
        capsys.readouterr().err
    )


def test_a_corridor_flies_its_bearing_and_the_six_drone_example_crosses() -> None:
    """A corridor's ``bearing_deg`` turns its waypoints and reaches its program; in
    examples/fleet-six.yaml two corridors cross the line the others fly and each other."""
    from baton.testbed.fleet import FleetFile
    from baton.testbed.local import MissionPlan

    west = MissionPlan(kind="corridor", length_m=200, spacing_m=100, bearing_deg=270)
    assert [(round(n, 6), round(e, 6)) for n, e in west.targets()] == [
        (0, 0),
        (0, -100),
        (0, -200),
    ]
    assert (
        "bearing_deg=270" in west.args() and west.describe() == "corridor of 200 m toward 270 deg"
    )
    fleet = FleetFile.model_validate(yaml.safe_load(FLEET_SIX.read_text()))
    bearings = {d.name: d.mission.bearing_deg for d in fleet.drones if d.mission.kind == "corridor"}
    assert sorted(set(bearings.values())) == [60.0, 90.0, 215.0], bearings
    with pytest.raises(ValueError, match="bearing_deg"):
        FleetFile.model_validate(
            {
                "stations": [
                    {"id": 1, "location": {"latitude_deg": 47, "longitude_deg": 8}, "range_m": 5}
                ],
                "drones": [
                    {
                        "name": "d1",
                        "home": {"latitude_deg": 47, "longitude_deg": 8},
                        "mission": {"bearing_deg": 360},
                    }
                ],
            }
        )

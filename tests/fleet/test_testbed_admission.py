"""A testbed file's controllers as stations, and the file admission makes of it."""

from __future__ import annotations

import pytest
from helpers.testbed_runs import CORRIDOR

from baton.cli import main
from baton.config import ConfigError, load_config, parse_config
from baton.fleet.routes import survey_route
from baton.fleet.stations import stations_of
from baton.sdk import Position
from baton.testbed.admission import admitted_config, describe

GRID_PROGRAM = CORRIDOR.parent / "grid_mission.py"


def test_a_controller_without_a_place_is_named_with_the_fix() -> None:
    config = parse_config(
        {
            "controllers": [
                {
                    "id": 0,
                    "address": "127.0.0.1:0",
                    "location": {"latitude_deg": 47.4, "longitude_deg": 8.5},
                    "range_m": 100,
                },
                {
                    "id": 4,
                    "address": "127.0.0.1:0",
                    "location": {"latitude_deg": 47.4, "longitude_deg": 8.5},
                },
            ]
        }
    )
    with pytest.raises(
        ConfigError,
        match=r"^f.yaml: controllers\[1\].range_m: controller 4 is a station only with its "
        r"location and range_m; add them$",
    ):
        stations_of(config, "f.yaml")


def test_the_admitted_file_holds_the_ring_alone_from_the_nearest_to_take_off() -> None:
    config = load_config(CORRIDOR)
    home = Position(config.drone.home.latitude_deg, config.drone.home.longitude_deg)
    # Flown west then back: only station 0's range, from take-off to 400 m west.
    route = survey_route(home, [(0.0, -400.0), (0.0, 0.0)])
    admitted, decision = admitted_config(config, route, str(CORRIDOR))
    assert [c.id for c in admitted.controllers] == [0] and admitted.ring_order == [0]
    assert admitted.master_id == 0 and decision.length_m == pytest.approx(800, abs=0.01)
    line = describe(admitted, config, decision)
    assert line.endswith("controller(s) 1, 2, 3 cover none of it: not started"), line
    # Everything else as the file says.
    assert admitted.handover_policy == config.handover_policy and admitted.radio_range
    with pytest.raises(ValueError, match=r"--admit: the mission is refused: route: a stretch"):
        admitted_config(config, survey_route(home, [(0.0, -600.0)]), str(CORRIDOR))


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--admit",), "--admit needs --config FILE: its controllers' locations and ranges"),
        (
            ("--config", str(CORRIDOR), "--admit", "--mission", str(GRID_PROGRAM)),
            "--admit needs the mission's route before it flies",
        ),
        (
            ("report", "--config", str(CORRIDOR), "--admit"),
            "--admit is for a local run: 'report' follows the ring the file started",
        ),
    ],
)
def test_testbed_admit_without_a_route_or_stations_is_one_clear_line(
    capsys: pytest.CaptureFixture[str], args: tuple[str, ...], message: str
) -> None:
    assert main(["testbed", *args]) == 2
    out, err = capsys.readouterr()
    assert message in err and "admission: ring" not in out, err

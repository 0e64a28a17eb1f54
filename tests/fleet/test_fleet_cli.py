"""``baton fleet``: stations, admission, missions and cancel, as an operator types them.

Each command opens the registry file afresh and closes it, as separate runs do."""

from __future__ import annotations

from pathlib import Path

import pytest

from baton.cli import main

CORRIDOR = Path(__file__).parents[2] / "examples" / "corridor.yaml"
SURVEY = Path(__file__).parents[2] / "examples" / "survey.plan"
TAKE_OFF = "47.397742,8.545594"


def fleet(capsys: pytest.CaptureFixture[str], registry: Path, *args: str) -> tuple[int, str, str]:
    status = main(["fleet", *args, "--registry", str(registry)])
    out, err = capsys.readouterr()
    return status, out, err


def test_the_corridor_stations_admit_a_route_and_refuse_one_beyond_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    db = tmp_path / "fleet.sqlite"
    status, out, _ = fleet(capsys, db, "stations", "add", "--from-config", str(CORRIDOR))
    assert status == 0 and out.count("added") == 4
    status, out, _ = fleet(capsys, db, "stations", "list")
    assert [line.split()[1] for line in out.splitlines()[1:]] == [
        f"controller-{k}" for k in range(4)
    ]

    # 1 km east: stations 0 and 1 from take-off, 2 from 503 m; 3 never reached.
    status, out, _ = fleet(
        capsys, db, "admit", "--drone", "d1", "--route", TAKE_OFF, "47.397742,8.558816"
    )
    assert status == 0, out
    assert "mission 1 admitted for drone d1" in out
    assert "ring: controller-0 (id 0, from 0 m) -> controller-1 (id 1, from 3 m) -> " in out
    assert "controller-2 (id 2, from 503 m)\n" in out
    assert "first master: controller-0 (id 0), the nearest to take-off" in out

    # 3.3 km east: beyond station 3's range from 1997 m on.
    status, out, err = fleet(
        capsys, db, "admit", "--drone", "d2", "--route", TAKE_OFF, "47.397742,8.59"
    )
    assert status == 1 and out == ""
    assert (
        "refused: route: a stretch no station covers: from (47.397742, 8.572103) at 1997 m" in err
    )
    assert "to (47.397742, 8.590000) at 3346 m (1349 m)" in err

    # A plan from its planned home: the survey's 161 m, within stations 0 and 1.
    status, out, _ = fleet(capsys, db, "admit", "--drone", "d3", "--plan", str(SURVEY))
    assert status == 0 and "ring: controller-0 (id 0, from 0 m) -> controller-1" in out

    status, _, err = fleet(capsys, db, "admit", "--drone", "d1", "--plan", str(SURVEY))
    assert status == 1 and "refused: drone: 'd1' already flies mission 1; cancel it first" in err

    status, out, _ = fleet(capsys, db, "missions")
    rows = [line.split()[:3] for line in out.splitlines()[1:]]
    assert rows == [["1", "d1", "admitted"], ["2", "d3", "admitted"]]
    status, out, _ = fleet(capsys, db, "cancel", "1")
    assert status == 0 and "mission 1 of drone d1 cancelled" in out
    status, _, err = fleet(capsys, db, "cancel", "1")
    assert status == 2 and "mission 1: already cancelled" in err
    status, out, _ = fleet(capsys, db, "admit", "--drone", "d1", "--route", TAKE_OFF)
    assert status == 0 and "mission 3 admitted" in out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ("stations", "add", "s0", "--id", "0", "--at", "95,8", "--range", "5"),
            "--at 95.0: must be",
        ),
        (
            ("stations", "add", "s0", "--id", "0", "--at", "45,8", "--range", "0"),
            "--range 0.0: must be > 0",
        ),
        (("stations", "add", "s0", "--id", "0", "--at", "45,8"), "--range: missing"),
        (("stations", "add", "s0", "--from-config", str(CORRIDOR)), "NAME: not with --from-config"),
        (("admit", "--drone", "d1", "--route", TAKE_OFF), "stations: none registered"),
        (
            ("admit", "--drone", "", "--route", TAKE_OFF),
            "refused: drone: '': give the drone's name",
        ),
        (("admit", "--drone", "d1", "--route", TAKE_OFF, "91,8"), "route[1].latitude_deg: 91.0"),
        (
            ("admit", "--drone", "d1", "--route", TAKE_OFF, "--home", TAKE_OFF),
            "--home: only with a plan",
        ),
        (
            ("admit", "--drone", "d1", "--route", TAKE_OFF, "--start"),
            "--config: missing; --start needs --config and --mission",
        ),
        (
            ("admit", "--drone", "d1", "--route", TAKE_OFF, "--mission", "grid.py"),
            "--mission: only with --start",
        ),
        (
            ("admit", "--drone", "d1", "--route", TAKE_OFF, "--drone-config", "d1.json"),
            "--drone-config: only with --start",
        ),
        (("cancel", "4"), "mission 4: no such mission"),
        (("serve", "--listen", "8470", "--insecure"), "--listen '8470': expected host:port"),
        (("serve", "--certs", "/nonexistent"), "/nonexistent"),
    ],
)
def test_a_bad_request_says_which_flag_or_field_and_the_fix(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: tuple[str, ...], message: str
) -> None:
    status, _, err = fleet(capsys, tmp_path / "fleet.sqlite", *args)
    assert status in (1, 2) and message in err, err


def test_a_plan_without_a_home_needs_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plan = tmp_path / "bare.waypoints"
    plan.write_text("QGC WPL 110\n1\t0\t3\t16\t0\t0\t0\t0\t47.3980\t8.5460\t10\t1\n")
    status, _, err = fleet(
        capsys, tmp_path / "fleet.sqlite", "admit", "--drone", "d1", "--plan", str(plan)
    )
    assert (
        status == 2
        and f"--home: missing: plan {plan} has no planned home position; give the take-off" in err
    )


def test_a_drain_names_what_is_missing_or_unknown(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    db = tmp_path / "fleet.sqlite"
    fleet(capsys, db, "stations", "add", "--from-config", str(CORRIDOR))
    status, _, err = fleet(capsys, db, "drain", "controller-1")
    assert status == 2 and "baton fleet drain: --config: missing; the network's file" in err
    status, _, err = fleet(capsys, db, "drain", "7", "--config", str(CORRIDOR), "--insecure")
    assert status == 2
    assert "station '7': no station by that name or id; the stations: controller-0 (id 0)" in err
    status, _, err = fleet(capsys, db, "undrain", "nosuch")
    assert status == 2 and "station 'nosuch': no station by that name or id" in err
    # A drained station with no mission in flight is drained at once.
    status, out, _ = fleet(capsys, db, "drain", "3", "--config", str(CORRIDOR), "--insecure")
    assert status == 0 and out == "station 3 drained: admitted into no new ring\n"
    status, out, _ = fleet(capsys, db, "stations", "list")
    assert out.splitlines()[4].endswith("drained")


def test_the_view_refuses_bad_flags_naming_each_and_the_fix(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    db = tmp_path / "fleet.sqlite"
    status, _, err = fleet(capsys, db, "view")
    assert status == 2 and "baton fleet view: --config: missing" in err
    args = ("view", "--config", str(CORRIDOR))
    status, _, err = fleet(capsys, db, *args, "--listen", "8470")
    assert status == 2 and "--listen '8470': expected host:port" in err
    status, _, err = fleet(capsys, db, *args, "--poll", "0")
    assert status == 2 and "--poll 0.0: a number of seconds above 0" in err
    status, _, err = fleet(capsys, db, *args)
    assert status == 2 and f"--registry {db}: no such file" in err
    fleet(capsys, db, "stations", "list")  # makes the registry
    status, _, err = fleet(capsys, db, *args, "--certs", str(tmp_path / "none"))
    assert status == 2 and str(tmp_path / "none") in err

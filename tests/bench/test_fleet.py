"""``baton bench fleet``'s pure corners: its options, the probe's script, the round
trips read from a drone's audit, and its table. The end-to-end quick run is in
test_bench_quick.py (slow)."""

from __future__ import annotations

import argparse
from typing import Any

import pytest

from baton.bench.cli import register
from baton.bench.fleet import (
    OTHER,
    STATION,
    FleetSettings,
    background_script,
    parse_missions,
    per_mission,
    probe_plan,
    round_trips,
    table,
)
from baton.bench.script import GET_POSITION
from baton.v1 import drone_pb2


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="baton")
    register(parser.add_subparsers())
    return parser


def test_the_mission_counts_are_parsed_and_rise() -> None:
    assert parse_missions("1,5,10,25,50") == (1, 5, 10, 25, 50)
    assert parse_missions(" 3 ") == (3,)
    args = _parser().parse_args(["bench", "fleet", "--missions", "2,4", "--quick"])
    assert args.missions == (2, 4) and args.quick and callable(args.run)
    assert _parser().parse_args(["bench", "fleet"]).missions is None


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("0", "must be >= 1, got 0"),
        ("1,-5", "must be >= 1, got -5"),
        ("x", "'x' is not a comma-separated list of mission counts"),
        ("1,,5", "is not a comma-separated list"),
        ("5,1", "must rise"),
        ("5,5", "must rise"),
    ],
)
def test_bad_mission_counts_are_refused_naming_the_option(
    text: str, says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit:
        _parser().parse_args(["bench", "fleet", "--missions", text])
    assert exit.value.code == 2
    error = capsys.readouterr().err
    assert "argument --missions:" in error and says in error, error


def test_the_settings_refuse_what_cannot_be_measured() -> None:
    with pytest.raises(ValueError, match="must rise"):
        FleetSettings(missions=(5, 1))
    with pytest.raises(ValueError, match="one each way"):
        FleetSettings(handovers=1)
    assert FleetSettings.quick().with_missions((1,)).missions == (1,)


def test_the_probe_hands_over_to_the_measured_station_and_back_between_reads() -> None:
    settings = FleetSettings(warm_up=10, handovers=4, reads_between=5)
    script, handovers = probe_plan(settings)
    assert handovers == [(15, STATION), (20, OTHER), (25, STATION), (30, OTHER)]
    # Reads only: every step one reqnr, a read after the last handover too.
    assert script == "p*35"
    assert background_script(0.5, duration_s=2) == "p,s0.5,p,s0.5,p,s0.5,p,s0.5"


def _entry(reqnr: int, at: float, method: str = GET_POSITION) -> drone_pb2.AuditEntry:
    return drone_pb2.AuditEntry(reqnr=reqnr, method=method, received_at=at)


def test_round_trips_are_back_to_back_reads_past_the_warm_up_and_not_across_a_handover() -> None:
    audit = [_entry(r, 100 + r * 0.01) for r in range(1, 9)]
    audit[5] = _entry(6, 100.5)  # the handover after reqnr 5: the new master's first read
    audit.append(_entry(9, 101.0, "/baton.v1.Camera/TakePicture"))
    trips = round_trips(audit, after=3, handover_points=[5])
    # 3->4, 4->5; not 5->6 (the handover), 6->7 would go back in time, 7->8; not 8->9.
    assert trips == pytest.approx([0.01, 0.01, 0.01])


def _window(cpu: float, rss: float, program_pss: float | None = None) -> dict[str, Any]:
    return {
        "station_cpu": cpu,
        "other_station_cpu": 0.1,
        "programs_cpu": 0.2,
        "station_rss_mb": rss,
        "station_pss_mb": rss,
        "program_rss_mb": None if program_pss is None else program_pss + 20,
        "program_pss_mb": program_pss,
        "programs": 0,
        "drones_cpu": 0.3,
        "vehicles_cpu": 0.4,
        "all_programs_cpu": 0.25,
        "bench_cpu": 0.5,
        "others_cpu": 0.5,
        "cores_busy": 0.5,
        "load": 3.0,
    }


def test_the_figures_per_mission_and_the_table() -> None:
    empty = _window(0.01, 80.0)
    lone = {"handover_p50_ms": 10.0, "handover_max_ms": 20.0, "round_trip_p50_ms": 2.0}
    probe = {"handover_p50_ms": 15.0, "handover_max_ms": 50.0, "round_trip_p50_ms": 3.0}
    as_master, as_replica = _window(0.21, 100.0, 20.0), _window(0.11, 100.0, 20.0)
    figures = per_mission(10, empty, as_master, as_replica, lone, probe)
    assert figures == {
        "master_cpu_ms_per_s": 20.0,
        "replica_cpu_ms_per_s": 10.0,
        "station_mb_per_mission": 2.0,
        "replica_mb": 22.0,
        "replica_rss_mb": 42.0,
        "handover_ratio": 1.5,
        "handover_max_ratio": 2.5,
        "round_trip_ratio": 1.5,
    }
    level = {
        "missions": 10,
        "move_masters_to_station_s": 0.4,
        "move_masters_away_s": 0.5,
        "as_master": as_master,
        "as_replica": as_replica,
        "probe": probe,
        **figures,
    }
    result = {
        "empty_station": empty,
        "lone": {**lone},
        "levels": [level],
        "stopped": {"missions": 25, "error": "m13-drone not ready after 180 s"},
    }
    text = table(result)
    assert "| lone | 0.010 (idle) |" in text
    assert "| 10 | 0.210 / 0.110 | 20.0 / 10.0 | 100 | 2.0 + 20.0 (40.0) |" in text
    # Where the master window's CPU went: stations, programs, drones, vehicles, the rest.
    assert "| 0.31 / 0.25 / 0.30 / 0.40 / 0.50 |" in text
    assert text.endswith("Stopped at 25 missions: m13-drone not ready after 180 s\n")

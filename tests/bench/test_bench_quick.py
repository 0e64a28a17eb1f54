"""The quick variant of every benchmark runs end to end and writes complete results.

Only the shape is checked (files, every point measured, finite ratios), not
the timings: those depend on the machine and are what the benchmarks report.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from baton.bench import failover
from baton.bench.cli import register
from baton.bench.failover import FailoverSettings, KillPoint, kill_points, run_failover
from baton.bench.micro import MicroSettings, run_micro
from baton.bench.timeline import TimelineSettings, run_timeline
from baton.bench.worst_case import WorstCaseSettings, run_worst_case


def _png(path: Path) -> bool:
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# On demand (pytest -m slow): 90 s of CI's 25 minutes.
@pytest.mark.slow
async def test_worst_case_quick(tmp_path: Path) -> None:
    settings = WorstCaseSettings.quick()
    result = await run_worst_case(settings, tmp_path)
    for name in ("worst_case.json", "worst_case.md", "worst_case.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert _png(tmp_path / "worst_case.png")
    saved = json.loads((tmp_path / "worst_case.json").read_text())
    rows = saved["summary"]
    # Both forwarding modes in one run: the paper's and cut-through.
    assert {(r["forwarding"], r["flush_limit"], r["hops"]) for r in rows} == {
        (mode, f, h)
        for mode in ("store-and-forward", "cut-through")
        for f in settings.flush_limits
        for h in settings.hops
    }
    for row in rows:
        assert row["n"] == settings.repeat
        assert row["mean_s"] > 0 and math.isfinite(row["ratio"])
        assert 0 < row["limit_s"] < row["model_s"] and math.isfinite(row["limit_ratio"])
        assert row["all_placed_after_flush"], row
        assert row["cores_busy"] is not None and 0 < row["cores_busy"] <= 1, row
    assert result["summary"] == rows
    assert "| forwarding | flush (MB) |" in (tmp_path / "worst_case.md").read_text()


# On demand (pytest -m slow): 70-80 s of CI's 25 minutes; the failover quick run keeps
# the benchmark drivers exercised in CI.
@pytest.mark.slow
async def test_timeline_quick(tmp_path: Path) -> None:
    result = await run_timeline(TimelineSettings.quick(), tmp_path)
    for name in ("timeline.json", "timeline.csv", "timeline.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert _png(tmp_path / "timeline.png")
    lines = (tmp_path / "timeline.csv").read_text().splitlines()
    assert lines[0].startswith("reqnr,method,controller,received_at,inter_arrival_s")
    assert len(lines) - 1 == result["requests"]
    # The same handovers prepared, on the cut-through ring: each one carried out was caught
    # up, or forced at its (short) timeout; the quick mission keeps the link busy with
    # pictures, so which is a matter of timing (the full run's are all caught up).
    prepared = result["prepared_handovers"]
    assert 1 <= len(prepared) <= 3, prepared
    for h in prepared:
        assert h["prepare_s"] > 0, h
        assert h["kind"] == "prepared" or (h["kind"] == "cooperative" and h["prepare_timed_out"])
    assert (tmp_path / "timeline-prepared.png").stat().st_size > 0
    handovers = result["handovers"]
    assert len(handovers) == 3
    assert all(h["delay_s"] > 0 for h in handovers)
    assert [h["after_reqnr"] for h in handovers] == sorted(h["after_reqnr"] for h in handovers)


# On demand (pytest -m slow): 70-80 s of CI's 25 minutes; the failover quick run keeps
# the benchmark drivers exercised in CI.
@pytest.mark.slow
async def test_micro_quick(tmp_path: Path) -> None:
    result = await run_micro(MicroSettings.quick(), tmp_path)
    assert (tmp_path / "micro.json").stat().st_size > 0
    assert "proxy overhead at p50" in (tmp_path / "micro.md").read_text()
    assert (
        "mutual TLS (above) against the same testbed --insecure"
        in (tmp_path / "micro.md").read_text()
    )
    assert set(result["tls_overhead_p50_ms"]) == {"proxy", "direct"}
    assert result["proxy_insecure"]["proxy_get_position"]["n"] == MicroSettings.quick().calls
    proxy = result["proxy"]
    assert proxy["proxy_get_position"]["n"] == MicroSettings.quick().calls
    # The proxied calls are a running mission's: logged, not flushed one by one.
    assert proxy["flushes_during_proxy_calls"] == 0
    assert result["proxy_insecure"]["flushes_during_proxy_calls"] == 0
    # Interleaved call by call with the proxied calls (the SDK's stream and unary), on a
    # drone beside it (unary and on a stream).
    for path in ("proxy_unary", "direct", "direct_stream"):
        assert proxy[f"{path}_get_position"]["n"] == MicroSettings.quick().calls
        assert proxy[f"{path}_get_position"]["calls_per_s"] > 0
    for overhead in ("proxy_overhead", "proxy_overhead_vs_stream", "proxy_unary_overhead"):
        assert math.isfinite(proxy[f"{overhead}_p50_ms"])
    assert all(r["calls_per_s"] > 0 for r in result["replay"])
    # The protocol and the node alone per log size, then a program end to end.
    levels = [r["level"] for r in result["replay"]]
    assert levels == ["protocol", "node"] * len(MicroSettings.quick().replay_entries) + [
        "end to end"
    ]
    assert result["replay"][-1]["n"] == MicroSettings.quick().calls
    for run in (proxy, result["proxy_insecure"]):
        relay = run["relay"]
        assert relay["relay_get_position"]["n"] == relay["direct_get_position"]["n"]
        assert math.isfinite(relay["relay_overhead_p50_ms"])
    # One link, then two controllers passing the message on cut-through, per link.
    assert [(r["relays"], r["bandwidth_bit_s"]) for r in result["ring"]] == [
        (0, 25e6),
        (2, 25e6),
        (0, None),
        (2, None),
    ]
    assert all(math.isfinite(r["throughput_bit_s"]) for r in result["ring"])
    for r in result["ring"]:
        assert r["relayed"] == 2 * r["relays"]  # the warm-up message and the big one
        assert 0 < r["relay_peak_bytes"] <= 2 * r["relay_window_bytes"] or not r["relays"]


async def test_failover_quick(tmp_path: Path) -> None:
    """Two kills of the master (one right after a scripted handover's decision): each run
    completes exactly once, counted at the vehicle and camera, with every time measured."""
    settings = FailoverSettings.quick()
    result = await run_failover(settings, tmp_path)
    for name in ("failover.json", "failover.md", "failover.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert _png(tmp_path / "failover.png")
    runs = result["runs"]
    assert [r["ok"] for r in runs] == [True, True], [r["problems"] for r in runs]
    assert [r["in_handover"] for r in runs] == [p.in_handover for p in kill_points(settings)]
    for run in runs:
        assert run["detection_s"] >= result["takeover_time_s"]
        assert math.isfinite(run["beyond_detection_over_physical"])
        assert run["catch_up_s"] > 0 and run["connect_s"] >= run["t_conn_s"] > 0
        assert run["physical_s"] > run["t_conn_s"]


async def test_a_kill_that_came_after_its_handover_was_done_is_run_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On a loaded machine the old master sent its handover message before the kill
    meant for "in the handover" landed: no takeover, and test_failover_quick failed.
    Such a run is made again (at most three runs), and the result says how many."""
    made: list[Path] = []

    async def run_kill(
        settings: FailoverSettings, controllers: int, point: KillPoint, workdir: Path
    ) -> dict[str, object]:
        made.append(workdir)
        late = len(made) < 3
        return {"ok": not late, "problems": [], "kill_too_late": late}

    monkeypatch.setattr(failover, "run_kill", run_kill)
    point = KillPoint(20, True)
    result = await failover._run_point(FailoverSettings.quick(), 3, point, tmp_path, 1)
    assert (result["ok"], result["attempts"]) == (True, 3)
    assert len(set(made)) == 3  # each run in a directory of its own
    made.clear()
    monkeypatch.setattr(failover, "LATE_KILL_ATTEMPTS", 2)
    result = await failover._run_point(FailoverSettings.quick(), 3, point, tmp_path, 2)
    assert (result["ok"], result["kill_too_late"], result["attempts"]) == (False, True, 2)


def test_failover_kill_points_are_seeded_and_one_in_five_is_in_a_handover() -> None:
    settings = FailoverSettings(kills=10)
    points = kill_points(settings)
    assert points == kill_points(settings)
    assert [p.in_handover for p in points] == [k % 5 == 1 for k in range(10)]
    random = [p for p in points if not p.in_handover]
    assert all(settings.first_kill <= p.reqnr <= settings.last_kill for p in random)


def test_cli_registers_three_benchmarks() -> None:
    import argparse

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["bench", "worst-case", "--quick", "--out", "x"])
    assert args.quick and args.out == Path("x") and callable(args.run)
    assert parser.parse_args(["bench", "timeline"]).speedup is None
    assert parser.parse_args(["bench", "micro"]).out == Path("out/bench")
    failover = parser.parse_args(["bench", "failover", "--kills", "4", "--controllers", "3"])
    assert (failover.kills, failover.controllers) == (4, "3")


# On demand (pytest -m slow): about 2 minutes on the loaded 2 cores (the lone probe,
# then 1 and 5 missions, each with its windows and its probe).
@pytest.mark.slow
async def test_fleet_quick(tmp_path: Path) -> None:
    from baton.bench.fleet import FleetSettings, run_fleet_bench

    settings = FleetSettings.quick()
    result = await run_fleet_bench(settings, tmp_path)
    assert result["stopped"] is None, result["stopped"]
    assert _png(tmp_path / "fleet.png")
    saved = json.loads((tmp_path / "fleet.json").read_text())
    assert [level["missions"] for level in saved["levels"]] == list(settings.missions)
    assert len(result["lone"]["handovers"]) == settings.handovers
    for level in saved["levels"]:
        n = level["missions"]
        # The station's programs: one per background mission (the probe's are stopped).
        assert level["as_master"]["programs"] == n and level["as_replica"]["programs"] == n
        assert level["as_master"]["station_cpu"] > 0 and level["replica_mb"] > 0
        assert len(level["probe"]["handovers"]) == settings.handovers
        assert {h["new_master"] for h in level["probe"]["handovers"]} == {0, 1}
        assert math.isfinite(level["handover_ratio"]) and level["round_trip_ratio"] > 0
    assert "| lone |" in (tmp_path / "fleet.md").read_text()


def test_the_proof_cost_bench_takes_its_message_and_prints_the_figure() -> None:
    """``python -m baton.bench.proof_cost``, small: the replica takes the signed message
    (a refused one ends the run) and the figure is printed."""
    done = subprocess.run(
        [sys.executable, "-m", "baton.bench.proof_cost", "--passes", "2", "--replies", "3"],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    assert done.stdout.startswith("after  CPU per 3 MB message: min "), done.stdout

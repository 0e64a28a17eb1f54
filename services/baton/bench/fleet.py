"""``baton bench fleet``: what one station costs per mission it hosts, and whether its
missions still hand over and call their drones as fast as a lone mission's.

Every part is a real process, started as the fleet testbed starts them
(``testbed/fleet.py``): two ``baton station`` processes, the measured one
(``STATION``) and a second one (``OTHER``) that holds every mission's other
replica, and for each mission its sim vehicle, its drone service and, on each
station, its session and mission program. Each mission's ring is the two
stations; its program is the bench mission polling its drone's position
once a second (``poll_s``), a light mission that keeps a session, a program,
a drone stream and a log flush per call busy without flying.

The levels (``--missions``) are reached one after the other on the same
station process: the missions of a level are added to those already running.
At each level, the measured station is master of every background mission
for one window (its masters moved there by the drones' Handover RPC), then
replica of every one for another: its CPU (seconds of CPU per second of
wall, from ``/proc``), its RSS and its mission programs' CPU and RSS are
read at both ends of each window. Then a probe mission is added (the N+1th):
back-to-back position reads with handovers scripted at the drone, alternately
to the measured station and away from it. The probe's handover delays (the
drone's decision to the new master's first request, as ``worst-case`` and
``timeline`` measure it) and its proxy round trip (the interval between two
back-to-back reads arriving at the drone: the program's call through its
master, the drone, and the reply back) are set against the same probe run
first, before any background mission: the lone mission.
"""

from __future__ import annotations

import asyncio
import os
import statistics
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc

from baton.bench.cpu import SAMPLE_S, CpuSampler, ProcessUsage, child_pids, process_usage
from baton.bench.runner import machine, markdown_table, say, write_json
from baton.bench.script import BENCH_MISSION, GET_POSITION, bench_mission_args
from baton.config import BatonConfig
from baton.drone.measure import percentile
from baton.fleet.sessions import start_sessions, stop_sessions
from baton.fleet.stations import ring_config
from baton.rpc.tls import DRONE, OPERATOR, Identity, Tls
from baton.testbed.fleet import (
    MissionDrone,
    StationPart,
    mission_ended,
    poll_until,
    start_mission_drone,
    start_stations,
)
from baton.testbed.supervisor import Supervisor
from baton.v1 import drone_pb2, ring_pb2

# The measured station and the one holding every mission's other replica.
STATION, OTHER = 0, 1
RING = (STATION, OTHER)
MB = 1024 * 1024
CORES = os.cpu_count() or 1
# The targets.
HANDOVER_RATIO_TARGET = 1.5
REPLICA_MB_TARGET = 40.0
# A background mission polls for this long at most (its script is written out).
BACKGROUND_S = 4 * 3600
# Parts started at once while a level's missions are added.
START_BATCH = 3
READY_S = 180.0


@dataclass(frozen=True)
class FleetSettings:
    """What to measure."""

    missions: tuple[int, ...] = (1, 5, 10, 25, 50)
    # Each CPU window (station master of all, then replica of all), wall seconds.
    window_s: float = 15.0
    # The probe: reads before its first handover, handovers, reads between handovers.
    warm_up: int = 30
    handovers: int = 10
    reads_between: int = 25
    # A background mission's position poll period, mission seconds (speed-up 1).
    poll_s: float = 1.0

    def __post_init__(self) -> None:
        check_missions(self.missions)
        if self.handovers < 2:
            raise ValueError("handovers must be >= 2 (one each way)")

    @classmethod
    def quick(cls) -> FleetSettings:
        """One and five missions, short windows, two handovers each way."""
        return cls(missions=(1, 5), window_s=4.0, warm_up=20, handovers=4, reads_between=15)

    def with_missions(self, missions: tuple[int, ...] | None) -> FleetSettings:
        if missions is None:
            return self
        return FleetSettings(
            missions, self.window_s, self.warm_up, self.handovers, self.reads_between, self.poll_s
        )


def check_missions(missions: Sequence[int]) -> None:
    """Mission counts must be >= 1 and rising: each level adds to the one before."""
    if not missions:
        raise ValueError("give at least one mission count")
    low = [n for n in missions if n < 1]
    if low:
        raise ValueError(f"mission counts must be >= 1, got {low[0]}")
    if list(missions) != sorted(set(missions)):
        raise ValueError(
            f"mission counts must rise (each level adds missions to the one before), "
            f"got {','.join(map(str, missions))}"
        )


def parse_missions(text: str) -> tuple[int, ...]:
    """``1,5,10`` as (1, 5, 10); ValueError saying what was wrong."""
    parts = [p.strip() for p in text.split(",")]
    try:
        missions = tuple(int(p) for p in parts)
    except ValueError:
        raise ValueError(
            f"{text!r} is not a comma-separated list of mission counts, e.g. 1,5,10,25,50"
        ) from None
    check_missions(missions)
    return missions


def probe_plan(settings: FleetSettings) -> tuple[str, list[tuple[int, int]]]:
    """The probe's bench script and its handovers (after reqnr, new master): every
    read one reqnr; the probe starts on ``OTHER``, so the odd handovers go to the
    measured station and the even ones away from it. Each handover follows a read
    and is followed by one at once, so its delay is the handover's alone."""
    handovers = [
        (settings.warm_up + k * settings.reads_between, STATION if k % 2 else OTHER)
        for k in range(1, settings.handovers + 1)
    ]
    reads = settings.warm_up + (settings.handovers + 1) * settings.reads_between
    return f"p*{reads}", handovers


def background_script(poll_s: float, duration_s: float = BACKGROUND_S) -> str:
    """A read every ``poll_s`` mission seconds for ``duration_s`` at most."""
    return ",".join([f"p,s{poll_s:g}"] * max(1, round(duration_s / poll_s)))


def round_trips(
    audit: Sequence[drone_pb2.AuditEntry], after: int, handover_points: Sequence[int]
) -> list[float]:
    """The intervals between back-to-back reads arriving at the drone, from reqnr
    ``after`` on, none across a handover: the program's call, through its master,
    the drone and back, once each."""
    at = {a.reqnr: a.received_at for a in audit if a.method == GET_POSITION}
    skip = set(handover_points)
    return [
        at[r + 1] - at[r]
        for r in sorted(at)
        if r >= after and r + 1 in at and r not in skip and at[r + 1] > at[r]
    ]


@dataclass
class Network:
    """The running stations, the configuration a mission over them flies with, and
    the operator's credentials."""

    supervisor: Supervisor
    stations: dict[int, StationPart]
    config: BatonConfig
    operator: Tls

    def pid(self, sid: int) -> int:
        process = self.supervisor.parts[f"station-{sid}"].process
        assert process is not None
        return process.pid

    def running(self, kind: str) -> list[int]:
        """The running missions' parts of ``kind`` ("drone", "vehicle"): their pids."""
        return [
            part.process.pid
            for name, part in self.supervisor.parts.items()
            if name.endswith(f"-{kind}") and part.process is not None and part.returncode is None
        ]


@dataclass
class Mission:
    """A running mission: its id, its drone, its configuration, its master now."""

    mission_id: str
    drone: MissionDrone
    config: BatonConfig
    master: int


async def start_mission(
    network: Network,
    mission_id: str,
    first_master: int,
    script: str,
    handovers: Sequence[tuple[int, int]] = (),
) -> Mission:
    """A mission over the two stations: its vehicle and drone, then its sessions."""
    config = ring_config(network.config, RING, first_master)
    at_home = config.drone.model_copy(update={"address": "127.0.0.1:0"})
    drone = await start_mission_drone(
        network.supervisor,
        mission_id,
        config.model_copy(update={"drone": at_home}),
        handovers,
        READY_S,
    )
    at = at_home.model_copy(update={"address": drone.address})
    config = config.model_copy(update={"drone": at})
    await poll_until(drone.ready, f"mission {mission_id}'s vehicle ready", READY_S)
    await asyncio.to_thread(
        start_sessions,
        config,
        mission_id,
        str(BENCH_MISSION),
        bench_mission_args(script),
        network.operator,
    )
    return Mission(mission_id, drone, config, first_master)


async def stop_mission(network: Network, mission: Mission) -> None:
    """Its sessions, then its drone and vehicle."""
    problems = await asyncio.to_thread(
        stop_sessions, mission.config, mission.mission_id, network.operator
    )
    if problems:
        raise RuntimeError(f"mission {mission.mission_id} not stopped: {'; '.join(problems)}")
    await mission.drone.channel.close()
    for part in ("drone", "vehicle"):
        await network.supervisor.stop_part(f"{mission.mission_id}-{part}")


async def move_masters(missions: Sequence[Mission], to: int) -> float:
    """Every mission's master moved to station ``to`` (the drones' Handover RPC, all at
    once); the wall time until the last moved."""
    moving = [m for m in missions if m.master != to]
    started = time.monotonic()

    async def move(mission: Mission) -> None:
        await mission.drone.stub.Handover(drone_pb2.HandoverRequest(new_master=to), timeout=120)
        mission.master = to

    await asyncio.gather(*(move(m) for m in moving))
    return time.monotonic() - started


async def count_takeovers(missions: Sequence[Mission]) -> int:
    """How many times the missions' drones took over a master they had lost sight of
    (``takeover_after``): a station too slow to keep its drone streams alive."""
    lost = drone_pb2.HANDOVER_TRIGGER_LOST
    statuses = [await m.drone.status() for m in missions]
    return sum(h.trigger == lost for s in statuses for h in s.handovers)


def _usage(pids: Sequence[int]) -> dict[int, ProcessUsage]:
    found = {pid: process_usage(pid) for pid in pids}
    return {pid: u for pid, u in found.items() if u is not None}


def mean_mb(sizes: Sequence[int]) -> float | None:
    return round(statistics.fmean(sizes) / MB, 2) if sizes else None


async def measure_window(network: Network, seconds: float) -> dict[str, Any]:
    """The measured station's and its programs' CPU (s per s of wall) and RSS over
    ``seconds``; the CPU of the second station, of the drones and of the vehicles;
    and how busy the machine's cores were, the share of the bench's processes
    taken out (``others_cpu``: what else runs on the machine)."""
    station, other = network.pid(STATION), network.pid(OTHER)
    programs = child_pids(station)
    other_programs = child_pids(other)
    drones, vehicles = network.running("drone"), network.running("vehicle")
    bench = os.getpid()
    everything = [station, other, bench, *programs, *other_programs, *drones, *vehicles]
    with CpuSampler() as cores:
        start = time.time()
        before = _usage(everything)
        # A measurement window: the processes run on while their counters advance.
        await asyncio.sleep(seconds)
        after = _usage(everything)
        end = time.time()
        # The sampler's next sample closes the window.
        await asyncio.sleep(3 * SAMPLE_S)
    wall = end - start

    def cpu(pids: Sequence[int]) -> float:
        common = [p for p in pids if p in before and p in after]
        return sum(after[p].cpu_s - before[p].cpu_s for p in common) / wall

    measured = [p for p in programs if p in after]
    busy = cores.busy(start, end)
    ours = cpu(everything)
    return {
        "station_cpu": round(cpu([station]), 4),
        "other_station_cpu": round(cpu([other]), 4),
        "programs_cpu": round(cpu(programs), 4),
        "station_rss_mb": round(after[station].rss_bytes / MB, 2),
        "station_pss_mb": round(after[station].pss_bytes / MB, 2),
        "program_rss_mb": mean_mb([after[p].rss_bytes for p in measured]),
        "program_pss_mb": mean_mb([after[p].pss_bytes for p in measured]),
        "programs": len(measured),
        "drones_cpu": round(cpu(drones), 4),
        "vehicles_cpu": round(cpu(vehicles), 4),
        "all_programs_cpu": round(cpu([*programs, *other_programs]), 4),
        "bench_cpu": round(ours, 4),
        "others_cpu": None if busy is None else round(busy * CORES - ours, 4),
        "cores_busy": busy,
        "load": round(os.getloadavg()[0], 2),
    }


async def run_probe(network: Network, settings: FleetSettings, label: str) -> dict[str, Any]:
    """The probe mission, added and removed: its handovers and its round trips."""
    script, handovers = probe_plan(settings)
    mission_id = f"probe-{label}"
    say(f"fleet: probe {mission_id}: {len(handovers)} handovers")
    probe = await start_mission(network, mission_id, OTHER, script, handovers)
    try:
        statuses = await poll_until(
            lambda: mission_ended(network.stations, probe.drone, mission_id, RING),
            f"probe {mission_id} ended",
            READY_S,
        )
        failed = {
            sid: s.mission_error
            for sid, s in statuses.items()
            if s.mission != ring_pb2.MISSION_STATE_DONE
        }
        if failed:
            raise RuntimeError(f"probe {mission_id} failed on stations {failed}")
        status = await probe.drone.status(audit=True)
    finally:
        await stop_mission(network, probe)
    records: list[dict[str, Any]] = [
        {
            "after_reqnr": h.after_reqnr,
            "old_master": h.old_master,
            "new_master": h.new_master,
            "delay_ms": round(h.delay_s * 1e3, 2),
            "trigger": drone_pb2.HandoverTrigger.Name(h.trigger),
        }
        for h in status.handovers
    ]
    unscripted = [r for r in records if r["trigger"] != "HANDOVER_TRIGGER_SCRIPT"]
    records = [r for r in records if r["trigger"] == "HANDOVER_TRIGGER_SCRIPT"]
    if len(records) != len(handovers) or any(r["delay_ms"] <= 0 for r in records):
        raise RuntimeError(
            f"probe {mission_id}: scripted handovers {handovers}, carried out {records}, "
            f"others {unscripted}"
        )
    trips = round_trips(status.audit, settings.warm_up, [after for after, _ in handovers])
    to_station = [r["delay_ms"] for r in records if r["new_master"] == STATION]
    from_station = [r["delay_ms"] for r in records if r["new_master"] == OTHER]
    delays = [r["delay_ms"] for r in records]
    return {
        "handovers": records,
        "unscripted_handovers": unscripted,
        "handover_p50_ms": round(statistics.median(delays), 2),
        "handover_max_ms": max(delays),
        "to_station_p50_ms": round(statistics.median(to_station), 2),
        "from_station_p50_ms": round(statistics.median(from_station), 2),
        "round_trip_p50_ms": round(percentile(trips, 50) * 1e3, 3),
        "round_trip_p90_ms": round(percentile(trips, 90) * 1e3, 3),
        "round_trips": len(trips),
    }


async def start_network(workdir: Path) -> tuple[Supervisor, Network]:
    """The two stations with their certificates, and the configuration of the network."""
    from baton.certs.make import init

    certs = workdir / "certs"
    init(certs, [*(Identity.controller(i) for i in RING), DRONE, OPERATOR])
    supervisor = Supervisor(workdir / "parts")
    stations = await start_stations(supervisor, list(RING), certs)
    config = BatonConfig.model_validate(
        {
            "controllers": [{"id": sid, "address": stations[sid].address} for sid in RING],
            "speedup": 1.0,
            "flush_limit": 0,
            "tls": {"certs": str(certs)},
        }
    )
    return supervisor, Network(supervisor, stations, config, Tls.load(certs, OPERATOR))


async def run_fleet_bench(settings: FleetSettings, out: Path) -> dict[str, Any]:
    """Every level in one run; writes fleet.json, fleet.md and fleet.png under ``out``
    after each level. A level that cannot be reached (a part not ready, a probe that
    failed) ends the run there: ``stopped`` says which and why, the levels before stay."""
    out.mkdir(parents=True, exist_ok=True)
    workdir = out / "fleet-runs"
    started = time.monotonic()
    say(f"fleet: starting two stations in {workdir} (load {os.getloadavg()[0]:.2f})")
    supervisor, network = await start_network(workdir)
    background: list[Mission] = []
    result: dict[str, Any] = {
        "settings": {
            "missions": list(settings.missions),
            "window_s": settings.window_s,
            "poll_s": settings.poll_s,
            "probe_handovers": settings.handovers,
            "probe_reads_between": settings.reads_between,
        },
        "machine": machine(),
        "load_at_start": [round(x, 2) for x in os.getloadavg()],
        "levels": [],
        "stopped": None,
    }
    async with supervisor:
        result["empty_station"] = empty = await measure_window(network, settings.window_s)
        result["lone"] = lone = await run_probe(network, settings, "lone")
        say(
            f"fleet: lone mission: handover p50 {lone['handover_p50_ms']} ms, "
            f"round trip p50 {lone['round_trip_p50_ms']} ms"
        )
        for n in settings.missions:
            try:
                level = await run_level(network, settings, background, n, empty, lone)
            except (RuntimeError, TimeoutError, grpc.aio.AioRpcError) as exc:
                say(f"fleet: {n} missions not reached: {exc}")
                result["stopped"] = {"missions": n, "error": str(exc)}
                break
            result["levels"].append(level)
            say(f"fleet: {n} missions: " + level_line(level))
            result["duration_s"] = round(time.monotonic() - started, 1)
            result["load_at_end"] = [round(x, 2) for x in os.getloadavg()]
            write_results(result, out)
        for m in background:
            await m.drone.channel.close()
        for part in network.stations.values():
            await part.channel.close()
    write_results(result, out)
    return result


async def run_level(
    network: Network,
    settings: FleetSettings,
    background: list[Mission],
    n: int,
    empty: dict[str, Any],
    lone: dict[str, Any],
) -> dict[str, Any]:
    """Adds missions to ``background`` up to ``n``, then measures: the station master
    of all, replica of all, and the probe."""
    adding = [f"m{k}" for k in range(len(background) + 1, n + 1)]
    say(f"fleet: {n} missions: adding {len(adding)} (load {os.getloadavg()[0]:.2f})")
    added = time.monotonic()
    script = background_script(settings.poll_s)
    # One wave: the level's drones and vehicles stop together at the end of the run.
    with network.supervisor.together():
        for first in range(0, len(adding), START_BATCH):
            batch = adding[first : first + START_BATCH]
            background += await asyncio.gather(
                *(start_mission(network, mid, STATION, script) for mid in batch)
            )
    for m in background:
        await poll_until(lambda m=m: m.drone.served(2), f"mission {m.mission_id} polling", READY_S)
    add_s = time.monotonic() - added
    to_station_s = await move_masters(background, STATION)
    as_master = await measure_window(network, settings.window_s)
    away_s = await move_masters(background, OTHER)
    as_replica = await measure_window(network, settings.window_s)
    probe = await run_probe(network, settings, str(n))
    return {
        "missions": n,
        "start_s": round(add_s, 1),
        "move_masters_to_station_s": round(to_station_s, 3),
        "move_masters_away_s": round(away_s, 3),
        "as_master": as_master,
        "as_replica": as_replica,
        "probe": probe,
        "takeovers": await count_takeovers(background),
        **per_mission(n, empty, as_master, as_replica, lone, probe),
    }


def write_results(result: dict[str, Any], out: Path) -> None:
    """fleet.json, fleet.md and fleet.png from the levels measured so far."""
    from baton.bench.plots import plot_fleet

    write_json(out / "fleet.json", result)
    (out / "fleet.md").write_text(table(result))
    if result["levels"]:
        plot_fleet(result, out / "fleet.png")


def per_mission(
    n: int,
    empty: dict[str, Any],
    as_master: dict[str, Any],
    as_replica: dict[str, Any],
    lone: dict[str, Any],
    probe: dict[str, Any],
) -> dict[str, Any]:
    """A level's figures per hosted mission and against the lone mission. A hosted
    replica's memory is the station's growth per mission plus one mission program
    (by its PSS: the interpreter's pages its programs share counted once)."""
    station_mb = (as_replica["station_rss_mb"] - empty["station_rss_mb"]) / n
    return {
        "master_cpu_ms_per_s": round(
            (as_master["station_cpu"] - empty["station_cpu"]) / n * 1e3, 2
        ),
        "replica_cpu_ms_per_s": round(
            (as_replica["station_cpu"] - empty["station_cpu"]) / n * 1e3, 2
        ),
        "station_mb_per_mission": round(station_mb, 2),
        "replica_mb": round(station_mb + (as_replica["program_pss_mb"] or 0.0), 2),
        "replica_rss_mb": round(station_mb + (as_replica["program_rss_mb"] or 0.0), 2),
        "handover_ratio": round(probe["handover_p50_ms"] / lone["handover_p50_ms"], 2),
        "handover_max_ratio": round(probe["handover_max_ms"] / lone["handover_max_ms"], 2),
        "round_trip_ratio": round(probe["round_trip_p50_ms"] / lone["round_trip_p50_ms"], 2),
    }


def level_line(level: dict[str, Any]) -> str:
    master, replica, probe = level["as_master"], level["as_replica"], level["probe"]
    return (
        f"station CPU {master['station_cpu']:.2f} s/s as master, "
        f"{replica['station_cpu']:.2f} as replica; RSS {replica['station_rss_mb']:.0f} MB; "
        f"handover p50 {probe['handover_p50_ms']} ms (x{level['handover_ratio']}), "
        f"round trip p50 {probe['round_trip_p50_ms']} ms (x{level['round_trip_ratio']})"
    )


def _busy(window: dict[str, Any]) -> str:
    busy = window["cores_busy"]
    return "-" if busy is None else f"{busy:.0%}"


def cores_line(window: dict[str, Any]) -> str:
    """Where a window's CPU went: both stations, all programs, the drones, the
    vehicles, and everything else on the machine."""
    stations = window["station_cpu"] + window["other_station_cpu"]
    parts = [stations, window["all_programs_cpu"], window["drones_cpu"], window["vehicles_cpu"]]
    rest = window["others_cpu"]
    return " / ".join(f"{x:.2f}" for x in parts) + (" / -" if rest is None else f" / {rest:.2f}")


def table(result: dict[str, Any]) -> str:
    """The summary table, markdown, with the lone mission's row first."""
    lone, empty = result["lone"], result["empty_station"]
    header = [
        "missions",
        "station CPU, master / replica (s/s)",
        "per mission (ms/s)",
        "station RSS (MB)",
        "per replica: station + program PSS (RSS) (MB)",
        "all masters moved to / away (s)",
        "handover p50 / max (ms)",
        "x lone",
        "round trip p50 (ms)",
        "x lone",
        "the cores' time, master window: stations, programs, drones, vehicles, else (s/s)",
        "cores busy",
        "load",
    ]
    rows: list[list[object]] = [
        [
            "lone",
            f"{empty['station_cpu']:.3f} (idle)",
            "",
            f"{empty['station_rss_mb']:.0f}",
            "",
            "",
            f"{lone['handover_p50_ms']:.1f} / {lone['handover_max_ms']:.1f}",
            "1.00",
            f"{lone['round_trip_p50_ms']:.2f}",
            "1.00",
            cores_line(empty),
            _busy(empty),
            empty["load"],
        ]
    ]
    for level in result["levels"]:
        master, replica, probe = level["as_master"], level["as_replica"], level["probe"]
        rows.append(
            [
                level["missions"],
                f"{master['station_cpu']:.3f} / {replica['station_cpu']:.3f}",
                f"{level['master_cpu_ms_per_s']:.1f} / {level['replica_cpu_ms_per_s']:.1f}",
                f"{replica['station_rss_mb']:.0f}",
                f"{level['station_mb_per_mission']:.1f} + {replica['program_pss_mb'] or 0:.1f} "
                f"({replica['program_rss_mb'] or 0:.1f})",
                f"{level['move_masters_to_station_s']:.2f} / {level['move_masters_away_s']:.2f}",
                f"{probe['handover_p50_ms']:.1f} / {probe['handover_max_ms']:.1f}",
                f"{level['handover_ratio']:.2f}",
                f"{probe['round_trip_p50_ms']:.2f}",
                f"{level['round_trip_ratio']:.2f}",
                cores_line(master),
                f"{_busy(master)} / {_busy(replica)}",
                f"{master['load']} / {replica['load']}",
            ]
        )
    stopped = result.get("stopped")
    after = f"\nStopped at {stopped['missions']} missions: {stopped['error']}\n" if stopped else ""
    return markdown_table(header, rows) + after

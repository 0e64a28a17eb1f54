"""The compose fleet (deploy/compose.ci.fleet.yml, compose-test.sh's run ``fleet``),
checked without Docker: its services against examples/fleet.yaml and
deploy/fleet.ci.yaml, every command against the real parser, and its commands run
as processes on this machine in the order compose starts them, the fleet job
flying both missions exactly once."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
import yaml
from helpers.compose import DEPLOY, argv, load_compose, option, parsed
from helpers.testbed_runs import baton
from waiting import until

from baton.config import ConfigError
from baton.testbed.fleet import (
    CAMERA_EFFECTS,
    DRONE_CONFIG,
    NETWORK_FILE,
    VEHICLE_EFFECTS,
    load_fleet,
)
from baton.testbed.fleet_external import load_external

REPO = DEPLOY.parent
SOURCE_IN_CONTAINER = "/opt/baton"  # the image's WORKDIR: relative paths start there
COMPOSE = load_compose("compose.ci.fleet.yml")
SERVICES: dict[str, dict[str, Any]] = COMPOSE["services"]
PARTS_IN_CONTAINER = "/etc/baton/fleet.ci.yaml"
FLEET_JOB = argv(SERVICES["fleet"]["command"])
FLEET = load_fleet(REPO / option(FLEET_JOB, "--fleet"))
PARTS = load_external(DEPLOY / "fleet.ci.yaml", FLEET)
WORKDIR = option(FLEET_JOB, "--workdir")
STATIONS = {f"station-{s.id}": s.id for s in FLEET.stations}
VEHICLES = {f"vehicle-{d.name}": d for d in FLEET.drones}
DRONES = {f"drone-{d.name}": d for d in FLEET.drones}


def command(service: str) -> list[str]:
    return argv(SERVICES[service]["command"])


def depends(service: str) -> dict[str, str]:
    return {s: c["condition"] for s, c in SERVICES[service].get("depends_on", {}).items()}


def test_one_service_a_station_a_vehicle_a_drone_and_the_jobs() -> None:
    assert set(SERVICES) == {"certs", "fleet", *STATIONS, *VEHICLES, *DRONES}
    for name, service in SERVICES.items():
        assert service["image"] == "baton-testbed:dev", name
        assert service["working_dir"] == SOURCE_IN_CONTAINER, name
        assert service["network_mode"] == ("none" if name == "certs" else "host"), name


@pytest.mark.parametrize("service", sorted(SERVICES))
def test_every_command_parses(service: str) -> None:
    parsed(command(service), service)


def test_the_certificates_are_the_fleet_s_and_every_part_reads_them() -> None:
    certs = command("certs")
    assert certs[1:4] == ["certs", "init", str(PARTS.certs)]
    assert option(certs, "--fleet") == option(FLEET_JOB, "--fleet")
    assert f"certs:{PARTS.certs}" in SERVICES["certs"]["volumes"]
    for name in (*STATIONS, *DRONES, "fleet"):
        assert f"certs:{PARTS.certs}:ro" in SERVICES[name]["volumes"], name
    for name in STATIONS:
        assert option(command(name), "--certs") == str(PARTS.certs)
        assert depends(name) == {"certs": "service_completed_successfully"}


def test_each_station_listens_where_the_parts_file_says() -> None:
    for name, sid in STATIONS.items():
        args = command(name)
        assert int(option(args, "--id")) == sid
        assert option(args, "--address") == PARTS.stations[sid]
        # Its sessions' history files where the job looks for them (the local layout).
        assert option(args, "--state-dir") == f"{WORKDIR}/station-{sid}"
        ready = option(args, "--address-file")
        assert SERVICES[name]["healthcheck"]["test"] == ["CMD", "test", "-s", ready]


def test_each_drone_reads_its_admitted_configuration_and_counts_where_the_job_reads() -> None:
    for d in FLEET.drones:
        folder = f"{WORKDIR}/{d.name}"
        drone, vehicle = command(f"drone-{d.name}"), command(f"vehicle-{d.name}")
        assert option(drone, "--config") == f"{folder}/{DRONE_CONFIG}"
        assert option(drone, "--address") == PARTS.drones[d.name]
        assert option(drone, "--camera-effects-file") == f"{folder}/{CAMERA_EFFECTS}"
        assert option(drone, "--state").startswith(f"{folder}/")
        assert option(vehicle, "--effects-file") == f"{folder}/{VEHICLE_EFFECTS}"
        url = urlsplit(option(drone, "--vehicle-url"))
        assert (url.hostname, url.port) == (
            option(vehicle, "--host"),
            int(option(vehicle, "--port")),
        )
        home = d.home
        assert (
            option(vehicle, "--home")
            == f"{home.latitude_deg},{home.longitude_deg},{home.altitude_m}"
        )
        assert float(option(vehicle, "--speedup")) == FLEET.speedup
        for name in (f"drone-{d.name}", f"vehicle-{d.name}"):
            assert f"fleet:{WORKDIR}" in SERVICES[name]["volumes"], name
            assert depends(name)["fleet"] == "service_healthy", name
        assert depends(f"drone-{d.name}")[f"vehicle-{d.name}"] == "service_started"


def test_the_fleet_job_starts_on_ready_stations_and_is_healthy_once_the_configs_are_written() -> (
    None
):
    assert depends("fleet") == {name: "service_healthy" for name in STATIONS}
    assert option(FLEET_JOB, "--external") == PARTS_IN_CONTAINER
    assert f"./fleet.ci.yaml:{PARTS_IN_CONTAINER}:ro" in SERVICES["fleet"]["volumes"]
    assert f"fleet:{WORKDIR}" in SERVICES["fleet"]["volumes"]
    assert SERVICES["fleet"]["healthcheck"]["test"] == [
        "CMD",
        "test",
        "-s",
        f"{WORKDIR}/{NETWORK_FILE}",
    ]
    report = option(FLEET_JOB, "--report")
    assert f"../reports:{Path(report).parent}" in SERVICES["fleet"]["volumes"]
    assert option(FLEET_JOB, "--timeout").isdigit()


def test_every_part_has_its_own_loopback_address() -> None:
    addresses = [*PARTS.stations.values(), *PARTS.drones.values()]
    for name in VEHICLES:
        args = command(name)
        addresses.append(f"{option(args, '--host')}:{option(args, '--port')}")
    assert all(a.startswith("127.") for a in addresses), addresses
    hosts = [a.rsplit(":", 1)[0] for a in addresses]
    assert len(set(hosts)) == len(hosts), "one loopback address per part"
    others = (DEPLOY / "testbed.ci.yaml").read_text() + (DEPLOY / "compose.ci.yml").read_text()
    assert not any(host in others for host in hosts), "none shared with the other runs"


def test_compose_test_runs_the_fleet_and_checks_every_mission(tmp_path: Path) -> None:
    text = (DEPLOY / "compose-test.sh").read_text()
    assert "RUNS=${BATON_COMPOSE_RUNS:-grid radio fleet}" in text
    report = Path(option(FLEET_JOB, "--report")).name
    assert f"run_mission fleet reports/{report} fleet -f deploy/compose.ci.fleet.yml" in text
    # Its argument checks: a run it does not know, and the fleet on ArduPilot, are refused.
    for env, says in (
        ({"BATON_COMPOSE_RUNS": "grid flock"}, "not 'flock'"),
        ({"BATON_COMPOSE_RUNS": "fleet", "BATON_COMPOSE_VEHICLE": "ardupilot"}, "fleet run"),
    ):
        done = subprocess.run(
            ["bash", str(DEPLOY / "compose-test.sh")],
            env={"PATH": "/usr/bin:/bin", **env},
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        )
        assert done.returncode == 2 and says in done.stderr, (env, done.stderr)


def test_the_parts_file_names_every_station_and_drone_once(tmp_path: Path) -> None:
    text = yaml.safe_load((DEPLOY / "fleet.ci.yaml").read_text())
    del text["drones"]["d2"]
    short = tmp_path / "short.yaml"
    short.write_text(yaml.safe_dump(text))
    with pytest.raises(ConfigError, match=r"short.yaml: drones: no address for d2; add"):
        load_external(short, FLEET)
    text["drones"]["d2"] = text["drones"]["d1"]
    twice = tmp_path / "twice.yaml"
    twice.write_text(yaml.safe_dump(text))
    with pytest.raises(ConfigError, match=r"two parts at one address"):
        load_external(twice, FLEET)


# -- the compose file's commands as processes, in compose's order -------------------


def _on_this_machine(args: list[str], paths: dict[str, Path]) -> list[str]:
    """``args`` with each container path replaced by its folder here."""
    out = []
    for arg in args:
        for inside, here in paths.items():
            if arg == inside or arg.startswith(inside + "/"):
                arg = str(here) + arg[len(inside) :]
                break
        out.append(arg)
    return out


# On demand (pytest -m slow), about 34 s: CI's compose run (deploy/compose-test.sh, the
# fleet run) flies these very commands in their containers.
@pytest.mark.slow
def test_the_compose_fleet_s_commands_fly_every_mission_exactly_once(tmp_path: Path) -> None:
    parts = yaml.safe_load((DEPLOY / "fleet.ci.yaml").read_text())
    parts["certs"] = str(tmp_path / "certs")
    (tmp_path / "parts.yaml").write_text(yaml.safe_dump(parts))
    paths = {
        str(PARTS.certs): tmp_path / "certs",
        WORKDIR: tmp_path / "fleet",
        PARTS_IN_CONTAINER: tmp_path / "parts.yaml",
        "/reports": tmp_path / "reports",
    }
    started: dict[str, subprocess.Popen[str]] = {}

    def start(service: str, **more: Path) -> subprocess.Popen[str]:
        args = _on_this_machine(command(service), {**paths, **{k: v for k, v in more.items()}})
        log = (tmp_path / f"{service}.log").open("w")
        started[service] = subprocess.Popen(
            baton(*args[1:]), cwd=REPO, stdout=log, stderr=subprocess.STDOUT, text=True
        )
        return started[service]

    try:
        assert start("certs").wait(timeout=60) == 0
        for name in STATIONS:
            start(name, **{"/tmp/station.address": tmp_path / f"{name}.address"})
        for name in STATIONS:
            address = tmp_path / f"{name}.address"
            until(address.exists, f"{name} listening")
        job = start("fleet")
        until(lambda: (tmp_path / "fleet" / NETWORK_FILE).exists(), "the drones' configs", 30)
        for name in (*VEHICLES, *DRONES):
            start(name)
        assert job.wait(timeout=240) == 0, (tmp_path / "fleet.log").read_text()
    finally:
        for process in started.values():
            if process.poll() is None:
                process.terminate()
        for process in started.values():
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()
    report = json.loads(
        (tmp_path / "reports" / Path(option(FLEET_JOB, "--report")).name).read_text()
    )
    assert report["summary"] == {"missions": 2, "ok": 2}
    rings = {m["drone"]: m["ring"] for m in report["missions"]}
    assert rings == {"d1": [1, 2, 3], "d2": [2, 3]}
    assert all(m["exactly_once"] and m["replicas_consistent"] for m in report["missions"])

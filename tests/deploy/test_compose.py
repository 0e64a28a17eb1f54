"""The compose testbed, checked without Docker.

The compose file, the testbed configuration its containers mount, the netem
entrypoint, the Dockerfile and the Makefile must agree with each other and with
the real ``baton`` command line: these tests parse all of them and compare.
``netem.sh`` itself runs here with stand-ins for ``ip`` and ``tc``.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
from pathlib import Path
from typing import Any
from urllib.parse import SplitResult, urlsplit

import pytest
import yaml
from autopilots import SKIP_REASON, sitl_binary
from helpers.compose import argv as _argv
from helpers.compose import expand as _expand
from helpers.compose import option as _option
from helpers.compose import parsed as _parsed

from baton.cli import build_parser
from baton.config import BatonConfig, LinkSpec, load_config, parse_duration, parse_rate
from baton.drone.master import parse_handover_script
from baton.link.radio import RadioRange
from baton.sdk import Position, offset

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
CONFIG_IN_CONTAINER = "/etc/baton/testbed.yaml"
HANDOVERS_IN_CONTAINER = "/etc/baton/handovers.txt"
SOURCE_IN_CONTAINER = "/opt/baton"  # the Dockerfile's WORKDIR, where it copies the repository
CONTROLLER_SERVICES = ["controller-0", "controller-1", "controller-2"]


def _load_compose() -> dict[str, Any]:
    return yaml.safe_load(_expand((DEPLOY / "docker-compose.yml").read_text()))


COMPOSE = _load_compose()
SERVICES: dict[str, dict[str, Any]] = COMPOSE["services"]
CONFIG: BatonConfig = load_config(DEPLOY / "testbed.yaml")
# The SITL autopilots, each in its own profile: profile -> service.
SITL_PROFILES = {"px4": "px4-sitl", "ardupilot": "ardupilot-sitl"}
# Where deploy/images.sh stages the SITL build it finds (the compose file's context `sitl`).
STAGED_SITL = REPO / "build" / "sitl"


def _command(service: str) -> list[str]:
    return _argv(SERVICES[service].get("command"))


def _host_port(address: str) -> tuple[str, int]:
    host, _, port = address.rpartition(":")
    return host, int(port)


def _names_of(service: str) -> set[str]:
    """Every name a service answers to: its own and its network aliases."""
    names = {service}
    networks = SERVICES[service].get("networks") or {}
    if isinstance(networks, dict):
        for spec in networks.values():
            names.update((spec or {}).get("aliases", []))
    return names


def _networks_of(service: str) -> set[str]:
    return set(SERVICES[service].get("networks") or [])


def _networks_resolving(service: str, name: str) -> list[str]:
    """The networks on which ``name`` resolves to ``service`` (a service name: all of them)."""
    networks = SERVICES[service]["networks"]
    return sorted(
        str(network)
        for network, spec in networks.items()
        if name == service or name in (spec or {}).get("aliases", [])
    )


def _subnet(network: str) -> str:
    return str(COMPOSE["networks"][network]["ipam"]["config"][0]["subnet"])


def _shaping(service: str) -> dict[str, tuple[str, str]]:
    """``--shape SUBNET DELAY RATE`` of a service's netem.sh entrypoint, by subnet."""
    entry = _argv(SERVICES[service].get("entrypoint"))
    assert entry and entry[0].endswith("/deploy/netem.sh"), f"{service}: entrypoint {entry}"
    assert entry[-1] == "--", f"{service}: the entrypoint must end with '--' before the command"
    shapes = {}
    for i, arg in enumerate(entry):
        if arg == "--shape":
            subnet, delay, rate = entry[i + 1 : i + 4]
            shapes[subnet] = (delay, rate)
    return shapes


def _assert_shaped_like(service: str, network: str, spec: LinkSpec, what: str) -> None:
    shapes = _shaping(service)
    subnet = _subnet(network)
    assert subnet in shapes, f"{service} does not shape the {network} network ({subnet})"
    delay, rate = shapes[subnet]
    assert parse_duration(delay) == pytest.approx(spec.latency), (
        f"{service}: netem delay {delay} on {network}, but testbed.yaml's {what}.latency "
        f"is {spec.latency} s"
    )
    expected = "unlimited" if spec.bandwidth is None else spec.bandwidth
    got = "unlimited" if rate == "unlimited" else parse_rate(rate)
    assert got == expected, f"{service}: netem rate {rate}, but {what}.bandwidth is {expected}"
    assert "NET_ADMIN" in SERVICES[service].get("cap_add", []), f"{service}: tc needs NET_ADMIN"


# -- the compose file -----------------------------------------------------------------


def test_services_are_all_there() -> None:
    assert set(SERVICES) >= {
        "sim-vehicle",
        "drone",
        "report",
        *CONTROLLER_SERVICES,
        *SITL_PROFILES.values(),
    }


def test_each_sitl_service_has_a_profile_of_its_own() -> None:
    for profile, service in SITL_PROFILES.items():
        assert SERVICES[service].get("profiles") == [profile], f"{service} runs in {profile!r} only"
    always = [s for s in SERVICES if s not in SITL_PROFILES.values()]
    for service in always:
        assert not SERVICES[service].get("profiles"), f"{service} must run in every profile"


@pytest.mark.parametrize("service", sorted(SERVICES))
def test_service_has_an_image_or_a_build_and_known_dependencies(service: str) -> None:
    spec = SERVICES[service]
    assert "image" in spec or "build" in spec
    depends = spec.get("depends_on") or []
    unknown = set(depends) - set(SERVICES)
    assert not unknown, f"{service} depends on unknown services {unknown}"
    for network in _networks_of(service):
        assert network in COMPOSE["networks"], f"{service}: unknown network {network}"


BATON_SERVICES = sorted(s for s in SERVICES if _command(s)[:1] == ["baton"])


@pytest.mark.parametrize("service", BATON_SERVICES)
def test_baton_command_parses(service: str) -> None:
    _parsed(_command(service), service)


@pytest.mark.parametrize("service", BATON_SERVICES)
def test_baton_services_mount_the_testbed_config(service: str) -> None:
    argv = _command(service)
    if "--config" in argv:
        assert _option(argv, "--config") == CONFIG_IN_CONTAINER
        mounts = SERVICES[service]["volumes"]
        assert f"./testbed.yaml:{CONFIG_IN_CONTAINER}:ro" in mounts
    if "--handover-file" in argv:
        assert _option(argv, "--handover-file") == HANDOVERS_IN_CONTAINER
        assert f"./handovers.txt:{HANDOVERS_IN_CONTAINER}:ro" in SERVICES[service]["volumes"]


def test_drone_and_report_share_a_valid_handover_script() -> None:
    assert _option(_command("drone"), "--handover-file") == HANDOVERS_IN_CONTAINER
    assert _option(_command("report"), "--handover-file") == HANDOVERS_IN_CONTAINER
    script = (DEPLOY / "handovers.txt").read_text()
    handovers = parse_handover_script(script, "deploy/handovers.txt", CONFIG.ring_order)
    assert handovers, "the compose testbed should hand over"


def test_report_follows_the_mission_the_controllers_run() -> None:
    grids = {_option(_command(s), "--mission-arg") for s in CONTROLLER_SERVICES}
    assert grids == {f"grid={_option(_command('report'), '--grid')}"}


# -- the testbed configuration against the services -----------------------------------


def test_every_controller_has_a_service_with_its_id() -> None:
    ids = {int(_option(_command(s), "--id")): s for s in CONTROLLER_SERVICES}
    assert sorted(ids) == sorted(CONFIG.ring_order)
    for cid, service in ids.items():
        assert service == f"controller-{cid}"


@pytest.mark.parametrize("service", CONTROLLER_SERVICES)
def test_controller_addresses_agree_with_compose(service: str) -> None:
    argv = _command(service)
    controller = CONFIG.controller(int(_option(argv, "--id")))
    host, port = _host_port(controller.address)
    # The controller binds `address`: all interfaces, or a name of its own container.
    assert host == "0.0.0.0" or host in _names_of(service)
    reach_host, reach_port = _host_port(controller.reach)
    assert reach_host in _names_of(service), f"peers reach {service} at {controller.reach}"
    assert reach_port == port
    # Ring traffic must take the ring network, the one shaped like controller_link: the
    # service name would resolve on the wifi network too, so peers use the ring alias.
    assert _networks_resolving(service, reach_host) == ["ring"], (
        f"peers reach {service} as {reach_host!r}, which is not a name only on the ring network"
    )
    drone_host, _ = _host_port(CONFIG.drone_address_for(controller.id))
    assert drone_host in _names_of("drone")
    assert _networks_of(service) >= {"ring", "wifi"}


@pytest.mark.parametrize("service", CONTROLLER_SERVICES)
def test_controller_runs_the_grid_mission(service: str) -> None:
    argv = _command(service)
    mission = Path(_option(argv, "--mission"))
    workdir = Path(SERVICES[service]["working_dir"])
    assert workdir == Path(SOURCE_IN_CONTAINER)
    assert (REPO / mission).is_file(), f"{mission} is not in the repository"
    assert mission.name == "grid_mission.py"


def test_drone_address_agrees_with_compose() -> None:
    argv = _command("drone")
    host, port = _host_port(CONFIG.drone.address)
    assert host in _names_of("drone"), "controllers reach the drone by its service name"
    bind_host, bind_port = _host_port(_option(argv, "--address"))
    assert (bind_host, bind_port) == ("0.0.0.0", port)
    assert _networks_of("drone") >= {"wifi", "autopilot"}
    health = SERVICES["drone"]["healthcheck"]["test"]
    assert health[-1] == f"127.0.0.1:{port}"


def test_vehicle_url_points_at_the_sim_vehicle() -> None:
    sim = _command("sim-vehicle")
    assert _option(sim, "--host") == "0.0.0.0"
    url = urlsplit(CONFIG.drone.vehicle_url)
    assert url.scheme == "udpout"
    assert url.hostname == "sim-vehicle" and url.port == int(_option(sim, "--port"))
    # Compose passes the same URL unless BATON_VEHICLE_URL selects a SITL profile.
    assert _option(_command("drone"), "--vehicle-url") == CONFIG.drone.vehicle_url
    assert float(_option(sim, "--speedup")) == CONFIG.speedup
    assert _networks_of("sim-vehicle") & _networks_of("drone")


# -- the SITL profiles ----------------------------------------------------------------

_DOCUMENTED_RUN = re.compile(
    r"BATON_VEHICLE_URL=(\S+) docker compose -f deploy/docker-compose\.yml --profile (\S+) up"
)


def _documented_vehicle_urls(text: str) -> dict[str, set[str]]:
    """``--profile P`` -> the BATON_VEHICLE_URLs a text sets on the same command line."""
    urls: dict[str, set[str]] = {}
    for url, profile in _DOCUMENTED_RUN.findall(text):
        urls.setdefault(profile, set()).add(url)
    return urls


README_URLS = _documented_vehicle_urls((DEPLOY / "README.md").read_text())


def _vehicle_url(profile: str) -> SplitResult:
    """The vehicle URL deploy/README.md gives for ``--profile profile``, parsed."""
    assert profile in README_URLS, f"deploy/README.md shows no command line for --profile {profile}"
    (url,) = README_URLS[profile]
    parsed = urlsplit(url)
    assert parsed.scheme in {"udpin", "udpout", "tcpin", "tcpout"}, f"not a MAVSDK URL: {url}"
    assert parsed.hostname and parsed.port, f"{url}: host and port, please"
    return parsed


def test_each_sitl_profile_documents_one_vehicle_url() -> None:
    assert set(README_URLS) == set(SITL_PROFILES), "one command line per SITL profile"
    for profile, urls in README_URLS.items():
        assert len(urls) == 1, f"--profile {profile}: deploy/README.md sets {sorted(urls)}"
    # The compose file's comments show the same command lines.
    in_compose = _documented_vehicle_urls((DEPLOY / "docker-compose.yml").read_text())
    assert in_compose == README_URLS


def test_drone_takes_its_vehicle_url_from_baton_vehicle_url() -> None:
    raw = yaml.safe_load((DEPLOY / "docker-compose.yml").read_text())
    argv = _argv(raw["services"]["drone"]["command"])
    expected = f"${{BATON_VEHICLE_URL:-{CONFIG.drone.vehicle_url}}}"
    assert _option(argv, "--vehicle-url") == expected
    for profile in SITL_PROFILES:
        url = _vehicle_url(profile).geturl()
        args = build_parser().parse_args([url if a == expected else a for a in argv[1:]])
        assert args.vehicle_url == url


@pytest.mark.parametrize("service", sorted(SITL_PROFILES.values()))
def test_sitl_is_on_the_autopilot_network_with_the_drone(service: str) -> None:
    # Companion computer to flight controller: unshaped, and not on WiFi or the ring.
    assert _networks_of(service) == {"autopilot"}
    assert "autopilot" in _networks_of("drone")


def test_px4_image_is_a_pinned_release() -> None:
    image = SERVICES["px4-sitl"]["image"]
    # The image's CI tags each v* release of the repository without the "v".
    assert re.fullmatch(r"jonasvautherin/px4-gazebo-headless:\d+\.\d+\.\d+", image), image


def test_px4_sitl_sends_mavlink_to_the_drone() -> None:
    sitl = SERVICES["px4-sitl"]
    # The entrypoint takes [HOST_QGC HOST_API]: PX4 sends to HOST_API on UDP 14540.
    hosts = _argv(sitl["command"])
    assert 1 <= len(hosts) <= 2
    assert set(hosts) <= _names_of("drone")
    assert "drone" in sitl["depends_on"], "the entrypoint resolves the drone's name at start"
    url = _vehicle_url("px4")
    assert (url.scheme, url.hostname, url.port) == ("udpin", "0.0.0.0", 14540)
    home = CONFIG.drone.home
    env = sitl["environment"]
    assert float(env["PX4_HOME_LAT"]) == home.latitude_deg
    assert float(env["PX4_HOME_LON"]) == home.longitude_deg
    assert float(env["PX4_HOME_ALT"]) == home.altitude_m


# ArduPilot SITL's options (``arducopter --help``): the short spellings mapped to the long.
_ARDUCOPTER_ALIASES = {"-M": "--model", "-s": "--speedup", "-O": "--home", "-I": "--instance"}
_ARDUCOPTER_FLAGS = {"--wipe": "--wipe", "-w": "--wipe"}
SERIAL_BASE_PORT = 5760  # TCP port of `tcp:0` for instance 0; +10 per instance


def _arducopter_options(argv: list[str]) -> dict[str, str]:
    """``arducopter`` arguments by long option name (flags map to ``""``)."""
    options: dict[str, str] = {}
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg in _ARDUCOPTER_FLAGS:
            options[_ARDUCOPTER_FLAGS[arg]] = ""
            i += 1
        elif arg.startswith("-I") and len(arg) > 2:  # -I0
            options["--instance"] = arg[2:]
            i += 1
        else:
            assert arg.startswith("-") and i + 1 < len(argv), f"unexpected SITL argument {arg!r}"
            options[_ARDUCOPTER_ALIASES.get(arg, arg)] = argv[i + 1]
            i += 2
    return options


ARDUPILOT_ARGS = _arducopter_options(_command("ardupilot-sitl"))


def _serial_tcp_port(serial: int, default_offset: int) -> int:
    """The TCP port SERIALn listens on: base + offset of ``tcp:OFFSET`` + 10 x instance."""
    instance = int(ARDUPILOT_ARGS.get("--instance", "0"))
    spec = ARDUPILOT_ARGS.get(f"--serial{serial}", f"tcp:{default_offset}")
    kind, offset, *_ = spec.split(":")
    assert kind == "tcp", f"SERIAL{serial} is {spec!r}, not a TCP port"
    return SERIAL_BASE_PORT + int(offset) + 10 * instance


def _dockerfile_sitl() -> str:
    return (DEPLOY / "Dockerfile.sitl").read_text().replace("\\\n", " ")


def _sitl_copies() -> dict[str, str]:
    """What Dockerfile.sitl copies from the build context ``sitl``: source -> destination."""
    copies = re.findall(r"^COPY --from=sitl (\S+) (\S+)\s*$", _dockerfile_sitl(), re.M)
    return dict(copies)


def test_ardupilot_sitl_image_is_built_from_dockerfile_sitl() -> None:
    spec = SERVICES["ardupilot-sitl"]
    build = spec["build"]
    assert (DEPLOY / build["context"] / build["dockerfile"]) == DEPLOY / "Dockerfile.sitl"
    assert ":" in spec["image"] and "/" not in spec["image"], "a local tag, nothing to pull"
    # The build context `sitl`: by default the folder images.sh stages the build in.
    contexts = build["additional_contexts"]
    assert set(contexts) == {"sitl"}
    assert (DEPLOY / contexts["sitl"]).resolve() == STAGED_SITL.resolve()
    assert "sitl_dir=build/sitl " in (DEPLOY / "images.sh").read_text()
    dockerfile = _dockerfile_sitl()
    # The base: a pinned public image by default, a build argument for machines
    # without a registry; the files' stage `sitl` is replaced by the named context.
    args = _build_args(dockerfile)
    assert re.fullmatch(r"[\w./-]+:[\w.-]+", args["BASE"]), "pin the base image"
    assert re.search(r"^FROM \$\{SITL_FILES\} AS sitl\s*$", dockerfile, re.M)
    assert re.search(r"^FROM \$\{BASE\}\s*$", dockerfile, re.M)
    build = _images_sh_builds("Dockerfile.sitl")
    assert '--build-arg BASE="$from_sitl"' in build
    assert "--build-arg SITL_FILES=baton-sitl-files:dev" in build
    assert build.endswith(f"-t {spec['image']} deploy >/dev/null")
    copies = _sitl_copies()
    assert set(copies) == {"arducopter", "copter.parm"}
    entrypoint = re.search(r"^ENTRYPOINT (\[.*\])\s*$", dockerfile, re.M)
    assert entrypoint and yaml.safe_load(entrypoint.group(1)) == [copies["arducopter"]]
    assert f"RUN {copies['arducopter']} --help" in dockerfile, "the build tries the binary"
    assert ARDUPILOT_ARGS["--defaults"] == copies["copter.parm"]


def _commented_commands(path: Path, start: str) -> list[str]:
    """Command lines starting with ``start``, without comment signs and "\\" continuations."""
    lines = [line.lstrip("#").strip() for line in path.read_text().splitlines()]
    commands = []
    for i, line in enumerate(lines):
        if line.startswith(start):
            parts = [line]
            while parts[-1].endswith("\\"):
                parts[-1] = parts[-1][:-1]
                i += 1
                parts.append(lines[i])
            commands.append(" ".join(" ".join(parts).split()))
    return commands


def test_manual_sitl_build_is_documented_the_same_way() -> None:
    start = "docker build -f deploy/Dockerfile.sitl"
    in_readme = _commented_commands(DEPLOY / "README.md", start)
    assert len(in_readme) == 1
    assert _commented_commands(DEPLOY / "Dockerfile.sitl", start) == in_readme
    argv = shlex.split(in_readme[0])
    assert _option(argv, "--build-context").startswith("sitl=")
    assert argv[-1] == "deploy", "the compose file builds with deploy/ as context too"


def test_readme_shows_the_sitl_command_line_compose_runs() -> None:
    binary = _sitl_copies()["arducopter"]
    (shown,) = _commented_commands(DEPLOY / "README.md", f"{binary} ")
    assert shlex.split(shown) == [binary, *_command("ardupilot-sitl")]


def test_images_sh_stages_what_dockerfile_sitl_copies() -> None:
    """images.sh finds the build with ``baton sitl --which`` (the one lookup) and copies
    it and its parameters under the names Dockerfile.sitl copies from the context."""
    images = (DEPLOY / "images.sh").read_text()
    assert "-m baton.cli sitl --which" in images
    for name in _sitl_copies():
        assert f'"$sitl_dir/{name}"' in images, f"images.sh does not stage {name}"


def test_ardupilot_sitl_runs_like_the_local_testbed() -> None:
    args = ARDUPILOT_ARGS
    assert args["--model"] == "+"
    lat, lon, alt, heading = (float(x) for x in args["--home"].split(","))
    home = CONFIG.drone.home
    assert (lat, lon, alt) == (home.latitude_deg, home.longitude_deg, home.altitude_m)
    assert 0 <= heading < 360
    # SITL's physics and the controllers' mission clocks run at one speed-up.
    assert float(args["--speedup"]) == CONFIG.speedup
    # Simulate at once (no ":wait" for a client on SERIAL0), from a fresh eeprom.
    assert args["--serial0"].startswith("tcp:") and not args["--serial0"].endswith(":wait")
    assert "--wipe" in args


def test_ardupilot_sitl_ports_agree_with_the_vehicle_url() -> None:
    spec = SERVICES["ardupilot-sitl"]
    url = _vehicle_url("ardupilot")
    assert url.scheme == "tcpout", "SITL listens, the drone connects"
    assert url.hostname in _names_of("ardupilot-sitl")
    serial0, serial1 = _serial_tcp_port(0, 0), _serial_tcp_port(1, 2)
    assert url.port == serial0, f"the drone must hold SERIAL0 ({serial0})"
    exposed = {int(str(port)) for port in spec["expose"]}
    assert {serial0, serial1} <= exposed
    # SERIAL1 is published for an independent telemetry monitor (one client per port).
    published = [str(p).rsplit(":", 2) for p in spec["ports"]]
    assert [(host, int(target)) for host, _, target in published] == [("127.0.0.1", serial1)]
    assert serial1 != url.port


def test_ardupilot_sitl_arguments_are_known_to_the_binary() -> None:
    binary = sitl_binary()
    if binary is None:
        pytest.skip(SKIP_REASON)
    done = subprocess.run(
        [str(binary), "--help"], capture_output=True, text=True, timeout=30, check=False
    )
    assert done.returncode == 0, done.stderr
    for option in ARDUPILOT_ARGS:
        assert re.search(rf"{re.escape(option)}\b", done.stdout), f"arducopter has no {option}"


# -- netem ------------------------------------------------------------------------------


@pytest.mark.parametrize("service", CONTROLLER_SERVICES)
def test_controller_links_are_shaped_like_the_config(service: str) -> None:
    _assert_shaped_like(service, "ring", CONFIG.controller_link, "controller_link")
    _assert_shaped_like(service, "wifi", CONFIG.drone_link, "drone_link")


def test_drone_link_is_shaped_like_the_config() -> None:
    _assert_shaped_like("drone", "wifi", CONFIG.drone_link, "drone_link")
    assert _subnet("autopilot") not in _shaping("drone"), "the autopilot link is not WiFi"


def _fake_tools(bin_dir: Path, log: Path) -> None:
    """``ip`` answers with one route per subnet; ``tc`` records its arguments."""
    bin_dir.mkdir()
    routes = "".join(
        f'  {_subnet(n)}) echo "{_subnet(n)} dev eth{i} proto kernel scope link" ;;\n'
        for i, n in enumerate(sorted(COMPOSE["networks"]))
    )
    (bin_dir / "ip").write_text(f'#!/bin/sh\nfor last; do :; done\ncase "$last" in\n{routes}esac\n')
    (bin_dir / "tc").write_text(f'#!/bin/sh\necho "$*" >> "{log}"\n')
    for tool in ("ip", "tc"):
        (bin_dir / tool).chmod(0o755)


def test_netem_sh_shapes_each_interface_then_runs_the_service(tmp_path: Path) -> None:
    log = tmp_path / "tc.log"
    _fake_tools(tmp_path / "bin", log)
    entry = _argv(SERVICES["controller-0"]["entrypoint"])
    env = {**os.environ, "PATH": f"{tmp_path / 'bin'}:{os.environ['PATH']}"}
    done = subprocess.run(
        ["sh", str(DEPLOY / "netem.sh"), *entry[1:], "echo", "service", "started"],
        env=env,
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout == "service started\n"
    eth = {n: f"eth{i}" for i, n in enumerate(sorted(COMPOSE["networks"]))}
    ring, wifi = CONFIG.controller_link, CONFIG.drone_link
    assert log.read_text().splitlines() == [
        f"qdisc replace dev {eth['ring']} root netem delay 20ms rate 25mbit",
        f"qdisc replace dev {eth['wifi']} root netem delay 2ms rate 20mbit",
    ]
    assert (ring.latency, ring.bandwidth, wifi.latency, wifi.bandwidth) == (0.02, 25e6, 0.002, 20e6)


def test_netem_sh_refuses_a_subnet_it_is_not_on(tmp_path: Path) -> None:
    _fake_tools(tmp_path / "bin", tmp_path / "tc.log")
    env = {**os.environ, "PATH": f"{tmp_path / 'bin'}:{os.environ['PATH']}"}
    done = subprocess.run(
        ["sh", str(DEPLOY / "netem.sh"), "--shape", "10.9.9.0/24", "1ms", "1mbit", "--", "true"],
        env=env,
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert done.returncode == 1
    assert "no interface on 10.9.9.0/24" in done.stderr
    assert not (tmp_path / "tc.log").exists()


# -- the image ----------------------------------------------------------------------------


def _dockerfile_runs() -> list[str]:
    text = (DEPLOY / "Dockerfile").read_text().replace("\\\n", " ")
    return [line.split(None, 1)[1] for line in text.splitlines() if line.startswith("RUN ")]


def _make_recipe(target: str) -> list[str]:
    """The recipe lines ``make TARGET`` runs, following its prerequisites in the Makefile."""
    text = (REPO / "Makefile").read_text()
    variables = dict(re.findall(r"^([A-Z]+) [?:]?= ?(.*)$", text, re.M))
    rules: dict[str, tuple[list[str], list[str]]] = {}
    current: list[str] = []
    for line in text.splitlines():
        rule = re.match(r"^([^\s#.][^:=]*):(?!=)(.*)$", line)
        if rule:
            current = []
            rules[rule.group(1).strip()] = (rule.group(2).split(), current)
        elif line.startswith("\t"):
            current.append(line.strip().lstrip("@"))
    prerequisites, recipe = rules[target]
    lines = []
    for name in prerequisites:
        resolved = re.sub(r"\$\((\w+)\)", lambda m: variables[m.group(1)], name)
        for key, (_, body) in rules.items():
            if re.sub(r"\$\((\w+)\)", lambda m: variables[m.group(1)], key) == resolved:
                lines += body
    return lines + recipe


def _build_args(dockerfile: str) -> dict[str, str]:
    """A Dockerfile's ``ARG NAME=DEFAULT`` lines (``ARG NAME``: empty default)."""
    found = re.findall(r"^ARG (\w+)(?:=(\S*))?\s*$", dockerfile, re.M)
    return {name: default for name, default in found}


def _images_sh() -> str:
    return (DEPLOY / "images.sh").read_text().replace("\\\n", " ")


def _images_sh_builds(dockerfile: str) -> str:
    """The ``docker build`` command line of deploy/images.sh for ``dockerfile``."""
    (build,) = [
        line.strip()
        for line in _images_sh().splitlines()
        if "docker build" in line and f"-f deploy/{dockerfile} " in line
    ]
    return build


def test_dockerfile_takes_its_base_as_a_build_argument() -> None:
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    args = _build_args(dockerfile)
    # Users get the public image; a machine with no registry passes its own base.
    assert args["BASE"] == "python:3.11-slim-bookworm"
    froms = re.findall(r"^FROM (\S+)", dockerfile, re.M)
    assert froms and set(froms) == {"${BASE}"}, f"every stage starts from BASE: {froms}"
    assert dockerfile.index("ARG BASE=") < dockerfile.index("FROM "), "ARG BASE before FROM"
    build = _images_sh_builds("Dockerfile")
    assert '--build-arg BASE="$from"' in build and "-t baton-testbed:dev ." in build
    assert re.search(r"^public=python:3\.11-slim-bookworm$", _images_sh(), re.M)
    assert re.search(r"^local_base=baton-base:bookworm$", _images_sh(), re.M)


def test_dockerfile_installs_baton_from_the_host_wheelhouse() -> None:
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    assert "WHEELHOUSE" in _build_args(dockerfile)
    runs = " ".join(_dockerfile_runs())
    assert "python3 -m venv /opt/venv" in runs
    # With a wheelhouse: nothing but the wheelhouse (no index, so no network) ...
    assert '-m pip install --no-cache-dir --no-index --find-links "$WHEELHOUSE" baton' in runs
    # ... and it does not stay in the image.
    (wheelhouse,) = re.findall(r"^wheelhouse=(\S+)", _images_sh(), re.M)
    assert f'rm -rf "/opt/baton/${{WHEELHOUSE:-{wheelhouse}}}"' in runs
    assert re.search(r"^ENV PATH=/opt/venv/bin:", dockerfile, re.M)
    assert any("iproute2" in run for run in _dockerfile_runs()), "tc comes with iproute2"
    assert "command -v tc" in runs, "a base with tc (the debootstrap one) needs no apt"
    # images.sh builds that wheelhouse on the host (`pip wheel` of this repository)
    # inside the build context, and passes the same folder.
    sh = _images_sh()
    (wheelhouse,) = re.findall(r"^wheelhouse=(\S+)", sh, re.M)
    assert not wheelhouse.startswith(("/", "..")), "the wheelhouse must be in the build context"
    assert '-m pip wheel --quiet --disable-pip-version-check --wheel-dir "$wheelhouse" .' in sh
    assert '--build-arg WHEELHOUSE="$wheelhouse"' in _images_sh_builds("Dockerfile")
    lines = (REPO / ".dockerignore").read_text().splitlines()
    ignored = [line.strip() for line in lines if line.strip() and not line.startswith("#")]
    assert not any(wheelhouse.startswith(p.strip("/")) for p in ignored)
    # The legacy builder (Debian's docker.io has no BuildKit) reads only the
    # context's root .dockerignore: a Dockerfile-specific one would let the host
    # .venv into the image (it did: 1.3 GB and 111 s a build).
    assert {".venv", ".git", "reports"} <= set(ignored)
    assert not (DEPLOY / "Dockerfile.dockerignore").exists()
    # The offline base: no network in the build at all.
    assert "from=$local_base from_sitl=$local_base network=none" in sh


def test_make_image_and_compose_test_run_the_deploy_scripts() -> None:
    assert _make_recipe("image")[-1] == "PYTHON=$(BIN)/python deploy/images.sh"
    assert _make_recipe("compose-test")[-1] == "PYTHON=$(BIN)/python deploy/compose-test.sh"
    for script in ("images.sh", "base-image.sh", "compose-test.sh"):
        assert os.access(DEPLOY / script, os.X_OK), f"deploy/{script} must be executable"
    assert 'deploy/base-image.sh "$local_base"' in _images_sh()


def test_base_image_reads_the_mirror_from_apt_at_run_time() -> None:
    text = (DEPLOY / "base-image.sh").read_text()
    assert "apt-cache policy" in text and "DEBIAN_MIRROR" in text
    # No mirror is written into the project.
    assert not re.search(r"https?://", text.replace("^https?:", ""))
    assert "--variant=minbase --include=python3,python3-venv,iproute2" in text
    assert "docker import" in text


@pytest.mark.parametrize("service", [s for s in BATON_SERVICES if s != "certs"])
def test_every_baton_service_reads_the_certificates_the_certs_service_makes(
    service: str,
) -> None:
    """Mutual TLS in the compose testbed: testbed.yaml's tls.certs is the volume the
    `certs` service writes, mounted read-only wherever a part runs."""
    folder = str(CONFIG.tls.certs)
    assert not CONFIG.tls.insecure
    assert f"certs:{folder}:ro" in SERVICES[service]["volumes"]
    certs = _command("certs")
    assert certs[:3] == ["baton", "certs", "init"] and certs[3] == folder
    assert _option(certs, "--config") == CONFIG_IN_CONTAINER and "--keep-ca" in certs
    assert f"certs:{folder}" in SERVICES["certs"]["volumes"]


def test_the_drone_starts_once_the_certificates_are_made() -> None:
    depends = SERVICES["drone"]["depends_on"]
    assert depends["certs"] == {"condition": "service_completed_successfully"}
    health = " ".join(SERVICES["drone"]["healthcheck"]["test"])
    assert "tls_for(DRONE)" in health and "insecure_channel" not in health


# -- the CI compose file: host networking on loopback, `baton link` for shaping ----------

CI_COMPOSE: dict[str, Any] = yaml.safe_load(_expand((DEPLOY / "compose.ci.yml").read_text()))
CI_SERVICES: dict[str, dict[str, Any]] = CI_COMPOSE["services"]
CI_CONFIG: BatonConfig = load_config(DEPLOY / "testbed.ci.yaml")
RING_LINKS = {f"link-ring-{cid}": cid for cid in CI_CONFIG.ring_order}
DRONE_LINKS = {f"link-drone-{cid}": cid for cid in CI_CONFIG.ring_order}


def _ci_command(service: str) -> list[str]:
    return _argv(CI_SERVICES[service].get("command"))


def _ci_link(service: str) -> tuple[str, str, LinkSpec]:
    """A link service's ``--listen``, ``--target`` and shaping, parsed by baton's parser."""
    args = build_parser().parse_args(_ci_command(service)[1:])
    spec = LinkSpec(latency=args.latency, bandwidth=args.bandwidth)
    return args.listen, args.target, spec


def test_ci_compose_runs_the_users_testbed_less_px4_plus_links() -> None:
    users = set(SERVICES) - {SITL_PROFILES["px4"]}
    assert set(CI_SERVICES) == users | set(RING_LINKS) | set(DRONE_LINKS)
    for service, spec in CI_SERVICES.items():
        assert spec["image"] == SERVICES[service if service in SERVICES else "drone"]["image"], (
            f"{service}: the image make image builds"
        )
        assert "build" not in spec, "compose-test.sh builds the images with deploy/images.sh"
        assert not spec.get("networks") and not spec.get("cap_add")
        expected = "none" if service == "certs" else "host"
        assert spec["network_mode"] == expected, f"{service}: loopback only on our machines"


def test_ci_ardupilot_sitl_runs_like_the_users_on_the_host_network() -> None:
    sitl = CI_SERVICES["ardupilot-sitl"]
    assert sitl["profiles"] == ["ardupilot"]
    assert _ci_command("ardupilot-sitl") == _command("ardupilot-sitl")
    # compose-test.sh points the drone at SERIAL0 on loopback.
    url = urlsplit("tcpout://127.0.0.1:5760")
    assert url.port == _serial_tcp_port(0, 0)
    text = (DEPLOY / "compose-test.sh").read_text()
    assert f"export BATON_VEHICLE_URL={url.geturl()}" in text
    assert "CI_COMPOSE+=(--profile ardupilot)" in text


CI_BATON_SERVICES = sorted(s for s in CI_SERVICES if s != "ardupilot-sitl")


@pytest.mark.parametrize("service", CI_BATON_SERVICES)
def test_ci_baton_command_parses(service: str) -> None:
    argv = _ci_command(service)
    _parsed(argv, service)
    if "--config" in argv:
        assert _option(argv, "--config") == CONFIG_IN_CONTAINER
        assert f"./testbed.ci.yaml:{CONFIG_IN_CONTAINER}:ro" in CI_SERVICES[service]["volumes"]


def test_ci_testbed_is_the_users_testbed_on_loopback() -> None:
    for field in ("ring", "initial_master", "flush_limit", "speedup"):
        assert getattr(CI_CONFIG, field) == getattr(CONFIG, field), field
    assert CI_CONFIG.controller_link == CONFIG.controller_link
    assert CI_CONFIG.drone_link == CONFIG.drone_link
    assert CI_CONFIG.drone.home == CONFIG.drone.home
    assert CI_CONFIG.tls.certs == CONFIG.tls.certs
    addresses = [CI_CONFIG.drone.address]
    for c in CI_CONFIG.controllers:
        addresses += [c.address, c.reach, CI_CONFIG.drone_address_for(c.id)]
    for address in addresses:
        host, _ = _host_port(address)
        assert host.startswith("127."), f"{address}: only loopback on our CI machines"
    assert len(set(addresses)) == len(addresses), "one listening address per part"


def test_ci_commands_are_the_users_commands_on_other_addresses() -> None:
    for service in ("certs", *CONTROLLER_SERVICES):
        assert _ci_command(service) == _command(service), service
    users_report, ci_report = _command("report"), _ci_command("report")
    assert _option(ci_report, "--timeout").isdigit()
    i = ci_report.index("--timeout")
    assert ci_report[:i] + ci_report[i + 2 :] == users_report
    assert _option(_ci_command("drone"), "--handover-file") == HANDOVERS_IN_CONTAINER
    assert f"./handovers.txt:{HANDOVERS_IN_CONTAINER}:ro" in CI_SERVICES["drone"]["volumes"]


def test_ci_drone_and_sim_vehicle_addresses_agree_with_the_config() -> None:
    drone = _ci_command("drone")
    assert _option(drone, "--address") == CI_CONFIG.drone.address
    assert CI_SERVICES["drone"]["healthcheck"]["test"][-1] == CI_CONFIG.drone.address
    raw = yaml.safe_load((DEPLOY / "compose.ci.yml").read_text())
    url = _option(_argv(raw["services"]["drone"]["command"]), "--vehicle-url")
    assert url == f"${{BATON_VEHICLE_URL:-{CI_CONFIG.drone.vehicle_url}}}"
    vehicle = urlsplit(CI_CONFIG.drone.vehicle_url)
    sim = _ci_command("sim-vehicle")
    assert (vehicle.hostname, vehicle.port) == (
        _option(sim, "--host"),
        int(_option(sim, "--port")),
    )
    assert float(_option(sim, "--speedup")) == CI_CONFIG.speedup


def test_ci_links_sit_where_the_config_says_and_shape_like_it() -> None:
    for service, cid in RING_LINKS.items():
        listen, target, spec = _ci_link(service)
        controller = CI_CONFIG.controller(cid)
        assert (listen, target) == (controller.reach, controller.address), service
        assert controller.reach != controller.address, "peers reach controllers through it"
        assert spec == CI_CONFIG.controller_link, f"{service}: controller_link"
    for service, cid in DRONE_LINKS.items():
        listen, target, spec = _ci_link(service)
        assert listen == CI_CONFIG.drone_address_for(cid), service
        assert target == CI_CONFIG.drone.address
        assert spec == CI_CONFIG.drone_link, f"{service}: drone_link"


def test_ci_controllers_start_once_the_drone_and_their_links_are_ready() -> None:
    for service in (*RING_LINKS, *DRONE_LINKS):
        ready = _option(_ci_command(service), "--address-file")
        assert CI_SERVICES[service]["healthcheck"]["test"] == ["CMD", "test", "-s", ready]
    for cid in CI_CONFIG.ring_order:
        depends = CI_SERVICES[f"controller-{cid}"]["depends_on"]
        needed = {"drone", *RING_LINKS, f"link-drone-{cid}"}
        assert set(depends) == needed
        assert all(depends[s] == {"condition": "service_healthy"} for s in needed)
    assert CI_SERVICES["drone"]["depends_on"]["certs"] == {
        "condition": "service_completed_successfully"
    }
    assert set(CI_SERVICES["report"]["depends_on"]) == set(CONTROLLER_SERVICES)


def test_compose_test_runs_the_ci_file_and_fails_on_anything_but_a_pass() -> None:
    text = (DEPLOY / "compose-test.sh").read_text()
    assert "CI_COMPOSE=(-f deploy/compose.ci.yml)" in text
    assert "deploy/images.sh" in text
    out = _option(_ci_command("report"), "--out")
    assert ("../reports:" + str(Path(out).parent)) in CI_SERVICES["report"]["volumes"]
    assert f"run_mission grid reports/{Path(out).name}" in text
    assert "--bridge=none --iptables=false" in text
    for need in ("docker.io", "debootstrap", "docker-compose"):
        assert f"missing+=({need})" in text


def _compose_cli() -> list[str] | None:
    """``docker compose`` (v2) or ``docker-compose`` (1.x), whichever answers here."""
    for argv in (["docker", "compose"], ["docker-compose"]):
        try:
            done = subprocess.run(
                [*argv, "version"], capture_output=True, text=True, timeout=30, check=False
            )
        except (OSError, subprocess.TimeoutExpired):
            continue
        if done.returncode == 0:
            return argv
    return None


def test_compose_files_validate_with_the_compose_at_hand() -> None:
    """The users' file needs Compose v2 (`name:`, `additional_contexts`); the CI file
    must load in Debian's docker-compose 1.29 too, alone and under its radio override,
    and so must the fleet's.
    Skipped where neither is installed (make compose-test installs docker-compose)."""
    cli = _compose_cli()
    if cli is None:
        pytest.skip("no docker compose / docker-compose on this machine")
    files = [
        ["compose.ci.yml"],
        ["compose.ci.yml", "compose.ci.radio.yml"],
        ["compose.ci.fleet.yml"],
    ]
    if cli == ["docker", "compose"]:
        files += [["docker-compose.yml"], ["docker-compose.yml", "radio.yml"]]
    for names in files:
        name = " + ".join(names)
        done = subprocess.run(
            [*cli, *(a for n in names for a in ("-f", str(DEPLOY / n))), "config", "-q"],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert done.returncode == 0, f"{' '.join(cli)} config: deploy/{name}: {done.stderr}"


def test_images_sh_removes_only_its_own_leftovers() -> None:
    """Every build leaves the previous image and the build stage untagged; images.sh
    prunes the dangling ones that carry the Dockerfiles' label, nothing else."""
    assert "docker image prune -f --filter label=baton.image " in _images_sh()
    for name in ("Dockerfile", "Dockerfile.sitl"):
        text = (DEPLOY / name).read_text()
        stages = len(re.findall(r"^FROM \$\{BASE\}", text, re.M))
        labels = re.findall(r"^LABEL baton\.image=\S+\s*$", text, re.M)
        assert stages and len(labels) == stages, f"{name}: one label per stage on BASE"
    assert 'docker import --change "LABEL baton.image=sitl-files"' in _images_sh()


# -- radio range: radio.yml over docker-compose.yml, compose.ci.radio.yml over compose.ci.yml --


def _mount_target(volume: str) -> str:
    return volume.split(":")[1]


def _merged(base: dict[str, Any], override: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """What compose makes of ``-f base -f override``'s services, as far as these files use
    it: a service's options replaced, its volumes merged by their path in the container."""
    services = {name: dict(spec) for name, spec in base["services"].items()}
    for name, spec in override["services"].items():
        merged = services.setdefault(name, {})
        for key, value in spec.items():
            if key == "volumes":
                mounts = {_mount_target(v): v for v in merged.get("volumes", [])}
                mounts.update({_mount_target(v): v for v in value})
                merged["volumes"] = list(mounts.values())
            else:
                merged[key] = value
    return services


RADIO_OVERRIDE: dict[str, Any] = yaml.safe_load(_expand((DEPLOY / "radio.yml").read_text()))
RADIO_SERVICES = _merged(COMPOSE, RADIO_OVERRIDE)
RADIO_CONFIG: BatonConfig = load_config(DEPLOY / "testbed.radio.yaml")
CI_RADIO_OVERRIDE: dict[str, Any] = yaml.safe_load(
    _expand((DEPLOY / "compose.ci.radio.yml").read_text())
)
CI_RADIO_SERVICES = _merged(CI_COMPOSE, CI_RADIO_OVERRIDE)
CI_RADIO_CONFIG: BatonConfig = load_config(DEPLOY / "testbed.ci.radio.yaml")
RADIO_SIDECARS = {f"radio-{cid}": cid for cid in RADIO_CONFIG.ring_order}


def _station_range(config: BatonConfig, cid: int) -> tuple[float, float, float]:
    station = config.controller(cid)
    assert station.location is not None and station.range_m is not None
    return (station.location.latitude_deg, station.location.longitude_deg, station.range_m)


def _assert_radio_like(args: Any, config: BatonConfig, cid: int, what: str) -> None:
    """A `baton link` or `baton radio-netem`: the station's range and the config's fade."""
    radio = args.range
    assert (radio.latitude_deg, radio.longitude_deg, radio.range_m) == _station_range(
        config, cid
    ), f"{what}: --range is not controller {cid}'s location and range_m"
    assert config.radio_fade is not None
    fade = config.radio_fade
    assert (args.fade.begins, args.fade.latency_s, args.fade.bandwidth_factor) == (
        fade.begins_at,
        fade.latency,
        fade.bandwidth_factor,
    ), f"{what}: --fade is not radio_fade"


def _position_volume(services: dict[str, dict[str, Any]]) -> tuple[str, str]:
    """The sim vehicle's --position-file, and the named volume that holds it."""
    position = Path(_option(_argv(services["sim-vehicle"]["command"]), "--position-file"))
    volumes = [
        v for v in services["sim-vehicle"]["volumes"] if v.split(":")[1] == str(position.parent)
    ]
    assert len(volumes) == 1, "the sim vehicle writes its position file to a volume"
    name = volumes[0].split(":")[0]
    assert not name.startswith((".", "/")), f"{name}: a named volume, shared between containers"
    return str(position), name


def test_radio_testbeds_are_the_plain_ones_with_stations_and_radio_range() -> None:
    for radio, plain in ((RADIO_CONFIG, CONFIG), (CI_RADIO_CONFIG, CI_CONFIG)):
        assert radio.radio_range and radio.radio_fade is not None
        assert radio.handover_policy.name == "nearest"
        for field in ("drone", "ring", "initial_master", "flush_limit", "speedup", "tls"):
            assert getattr(radio, field) == getattr(plain, field), field
        assert (radio.controller_link, radio.drone_link) == (
            plain.controller_link,
            plain.drone_link,
        )
        for c in plain.controllers:
            placed = radio.controller(c.id)
            assert (placed.address, placed.reach) == (c.address, c.reach)
            assert radio.drone_address_for(c.id) == plain.drone_address_for(c.id)
    # The same stations for users and on CI, and the same fade and policy.
    for cid in RADIO_CONFIG.ring_order:
        assert _station_range(RADIO_CONFIG, cid) == _station_range(CI_RADIO_CONFIG, cid)
    assert RADIO_CONFIG.radio_fade == CI_RADIO_CONFIG.radio_fade
    assert RADIO_CONFIG.handover_policy == CI_RADIO_CONFIG.handover_policy


def test_radio_stations_cover_the_corridor_together_and_none_alone() -> None:
    report = _parsed(_argv(RADIO_SERVICES["report"]["command"]))
    home = RADIO_CONFIG.drone.home

    stations = [RadioRange(*_station_range(RADIO_CONFIG, c)) for c in RADIO_CONFIG.ring_order]
    east = 0.0
    while east <= report.length:
        p = offset(Position(home.latitude_deg, home.longitude_deg), 0.0, east)
        covering = [s for s in stations if s.covers(p.latitude_deg, p.longitude_deg)]
        assert covering, f"{east:g} m east of home: no station in range"
        east += 10.0
    for s in stations:
        assert not all(
            s.covers(q.latitude_deg, q.longitude_deg)
            for q in (
                offset(Position(home.latitude_deg, home.longitude_deg), 0.0, e)
                for e in (0.0, report.length)
            )
        ), "no single station covers the corridor"


@pytest.mark.parametrize("services", [RADIO_SERVICES, CI_RADIO_SERVICES], ids=["users", "ci"])
def test_radio_runs_mount_the_radio_testbed_everywhere(services: dict[str, dict[str, Any]]) -> None:
    name = "testbed.radio.yaml" if services is RADIO_SERVICES else "testbed.ci.radio.yaml"
    for service, spec in services.items():
        argv = _argv(spec.get("command"))
        if argv[:1] != ["baton"] or "--config" not in argv:
            continue
        _parsed(argv)
        assert _option(argv, "--config") == CONFIG_IN_CONTAINER
        mounts = [v for v in spec["volumes"] if _mount_target(v) == CONFIG_IN_CONTAINER]
        assert mounts == [f"./{name}:{CONFIG_IN_CONTAINER}:ro"], service


@pytest.mark.parametrize("services", [RADIO_SERVICES, CI_RADIO_SERVICES], ids=["users", "ci"])
def test_radio_runs_fly_the_corridor_with_no_handover_script(
    services: dict[str, dict[str, Any]],
) -> None:
    assert "--handover-file" not in _argv(services["drone"]["command"])
    report = _parsed(_argv(services["report"]["command"]))
    assert (report.mission, report.handover_file) == ("corridor", None)
    expected = [f"length_m={report.length:g}", f"spacing_m={report.spacing:g}"]
    for service in CONTROLLER_SERVICES:
        argv = _argv(services[service]["command"])
        args = _parsed(argv)
        assert Path(args.mission).name == "corridor_mission.py"
        assert (REPO / args.mission).is_file()
        assert args.mission_arg == expected, f"{service} flies what the report follows"
    # The drone's own address and vehicle: the plain run's.
    plain = SERVICES if services is RADIO_SERVICES else CI_SERVICES
    drone, plain_drone = _argv(services["drone"]["command"]), _argv(plain["drone"]["command"])
    for option in ("--address", "--vehicle-url", "--config"):
        assert _option(drone, option) == _option(plain_drone, option)
    sim, plain_sim = (
        _argv(services["sim-vehicle"]["command"]),
        _argv(plain["sim-vehicle"]["command"]),
    )
    i = sim.index("--position-file")
    assert sim[:i] + sim[i + 2 :] == plain_sim, "the plain sim vehicle plus its position file"


def test_radio_sidecars_shape_each_controller_s_wifi_like_the_config() -> None:
    position, volume = _position_volume(RADIO_SERVICES)
    assert volume in RADIO_OVERRIDE["volumes"]
    assert set(s for s in RADIO_SERVICES if s.startswith("radio-")) == set(RADIO_SIDECARS)
    for service, cid in RADIO_SIDECARS.items():
        spec = RADIO_SERVICES[service]
        args = _parsed(_argv(spec["command"]))
        assert args.run.__name__ == "run_radio_netem", f"{service} runs baton radio-netem"
        # In its controller's network namespace, allowed to change its qdiscs.
        assert spec["network_mode"] == f"service:controller-{cid}"
        assert f"controller-{cid}" in spec["depends_on"]
        assert "NET_ADMIN" in spec["cap_add"] and "networks" not in spec
        assert spec["image"] == SERVICES["drone"]["image"]
        assert args.subnet == _subnet("wifi")
        assert args.latency == RADIO_CONFIG.drone_link.latency
        assert args.bandwidth == RADIO_CONFIG.drone_link.bandwidth
        _assert_radio_like(args, RADIO_CONFIG, cid, service)
        assert str(args.position_file) == position
        assert f"{volume}:{Path(position).parent}:ro" in spec["volumes"]


@pytest.mark.parametrize("service", CONTROLLER_SERVICES)
def test_radio_controllers_start_with_the_drone_link_dropped(service: str) -> None:
    entry = _argv(RADIO_SERVICES[service]["entrypoint"])
    plain = _argv(SERVICES[service]["entrypoint"])
    assert entry[0] == plain[0] and entry[-1] == "--"
    drop = [entry[i + 1] for i, arg in enumerate(entry) if arg == "--drop"]
    assert drop == [_subnet("wifi")], "the sidecar opens the drone's network when in range"
    ring = _subnet("ring")
    i = entry.index("--shape")
    assert entry[i : i + 4] == ["--shape", ring, "20ms", "25mbit"]
    assert entry.count("--shape") == 1, "the wifi is the radio-netem sidecar's alone"
    assert RADIO_SERVICES[service]["networks"] == SERVICES[service]["networks"]


def test_ci_radio_links_carry_each_controller_s_link_within_its_range() -> None:
    position, volume = _position_volume(CI_RADIO_SERVICES)
    assert volume in CI_RADIO_OVERRIDE["volumes"]
    assert set(CI_RADIO_SERVICES) == set(CI_SERVICES), "the same services, range-driven"
    for service, cid in DRONE_LINKS.items():
        spec = CI_RADIO_SERVICES[service]
        argv = _argv(spec["command"])
        args = _parsed(argv)
        _assert_radio_like(args, CI_RADIO_CONFIG, cid, service)
        assert str(args.position_file) == position
        assert f"{volume}:{Path(position).parent}:ro" in spec["volumes"]
        # Otherwise the plain run's link.
        plain = _ci_command(service)
        for option in ("--range", "--fade", "--position-file"):
            i = argv.index(option)
            argv = argv[:i] + argv[i + 2 :]
        assert argv == plain
    for service in RING_LINKS:
        assert CI_RADIO_SERVICES[service]["command"] == CI_SERVICES[service]["command"]


def test_netem_sh_drops_a_subnet_then_runs_the_service(tmp_path: Path) -> None:
    log = tmp_path / "tc.log"
    _fake_tools(tmp_path / "bin", log)
    entry = _argv(RADIO_SERVICES["controller-1"]["entrypoint"])
    env = {**os.environ, "PATH": f"{tmp_path / 'bin'}:{os.environ['PATH']}"}
    done = subprocess.run(
        ["sh", str(DEPLOY / "netem.sh"), *entry[1:], "echo", "started"],
        env=env,
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout == "started\n"
    eth = {n: f"eth{i}" for i, n in enumerate(sorted(COMPOSE["networks"]))}
    assert log.read_text().splitlines() == [
        f"qdisc replace dev {eth['ring']} root netem delay 20ms rate 25mbit",
        f"qdisc replace dev {eth['wifi']} root netem loss 100%",
    ]


def test_compose_test_runs_the_grid_then_the_radio_run_and_checks_its_story() -> None:
    text = (DEPLOY / "compose-test.sh").read_text()
    assert "RUNS=${BATON_COMPOSE_RUNS:-grid radio fleet}" in text
    grid_out = _option(_ci_command("report"), "--out")
    radio_out = _option(_argv(CI_RADIO_SERVICES["report"]["command"]), "--out")
    assert grid_out != radio_out
    assert f"run_mission grid reports/{Path(grid_out).name}" in text
    assert (
        f"run_mission radio reports/{Path(radio_out).name} report "
        '"${CI_COMPOSE[@]}" -f deploy/compose.ci.radio.yml' in text
    )
    assert 'report.get("masters") != [0, 1, 2]' in text
    # Each link to the drone logged the vehicle crossing its circle (proxy.py's words).
    proxy = (REPO / "services" / "baton" / "link" / "proxy.py").read_text()
    for message in ("vehicle in radio range", "vehicle out of radio range"):
        assert f'"{message}"' in proxy
        assert f'"1:{message}"' in text
    assert ("../reports:" + str(Path(radio_out).parent)) in CI_RADIO_SERVICES["report"]["volumes"]

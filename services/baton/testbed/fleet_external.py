"""``baton testbed --fleet FILE --external PARTS``: the fleet flown on stations and
drones that run elsewhere, at the addresses ``PARTS`` gives (the compose fleet,
deploy/compose.ci.fleet.yml, one container each).

The steps are the local fleet's (``testbed/fleet.py``), minus starting processes:
the registry admits every mission over the file's stations, each drone's mission
configuration is written to its folder of the workdir (``NAME/drone.json``), then
the network's file (``network.yaml``): written last, it tells whoever starts the
drone services that their configurations are there. Then ``fly_fleet``: every
vehicle ready, each mission's sessions started on its ring's stations, every
mission's end, each judged from what its vehicle and camera counted in their
effects files, ``NAME/vehicle-effects.jsonl`` and ``NAME/camera-effects.jsonl``
of the same workdir (a folder the parts share), and from its replicas.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from baton.config import ConfigError, format_validation_error, read_yaml
from baton.rpc.tls import OPERATOR
from baton.testbed.fleet import (
    NETWORK_FILE,
    REGISTRY_FILE,
    FleetFile,
    FleetRun,
    admit_fleet,
    close_parts,
    connect_drone,
    connect_station,
    fleet_network,
    fly_fleet,
    mission_config,
    note_drone_addresses,
    write_drone_config,
    write_network,
)

# A part's address: HOST:PORT, the host a name or an IPv4 address.
ADDRESS_PATTERN = r"^[A-Za-z0-9.-]+:[0-9]{1,5}$"


class ExternalParts(BaseModel):
    """``--external FILE``: where the fleet's parts run. Every station of the fleet
    file by its id and every drone by its name, each at the HOST:PORT it listens on,
    and the certificates' folder they were all issued from."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    certs: Path
    stations: dict[int, str] = Field(min_length=1)
    drones: dict[str, str] = Field(min_length=1)

    @model_validator(mode="after")
    def _addresses(self) -> ExternalParts:
        import re

        named = [*(f"stations.{k}" for k in self.stations), *(f"drones.{k}" for k in self.drones)]
        addresses = [*self.stations.values(), *self.drones.values()]
        for where, address in zip(named, addresses, strict=True):
            if not re.match(ADDRESS_PATTERN, address):
                raise ValueError(f"{where}: {address!r} is not HOST:PORT")
        twice = sorted({a for a in addresses if addresses.count(a) > 1})
        if twice:
            raise ValueError(f"{', '.join(twice)}: two parts at one address; give each its own")
        return self

    def check_against(self, fleet: FleetFile, source: str) -> None:
        """ConfigError unless the file names exactly the fleet's stations and drones."""
        for what, have, want in (
            ("stations", set(self.stations), {s.id for s in fleet.stations}),
            ("drones", set(self.drones), {d.name for d in fleet.drones}),
        ):
            missing, unknown = sorted(map(str, want - have)), sorted(map(str, have - want))
            if missing:
                raise ConfigError(
                    f"{source}: {what}: no address for {', '.join(missing)}; add where each runs"
                )
            if unknown:
                raise ConfigError(
                    f"{source}: {what}: {', '.join(unknown)} not in the fleet file; remove them"
                )


def load_external(path: Path, fleet: FleetFile) -> ExternalParts:
    """Reads ``--external FILE`` for ``fleet``; ConfigError names the file, the field
    and the fix."""
    data = read_yaml(path, "external parts file")
    try:
        parts = ExternalParts.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(str(path), exc)) from None
    parts.check_against(fleet, str(path))
    return parts


async def run_external_fleet(
    fleet: FleetFile, parts: ExternalParts, workdir: Path, timeout_s: float
) -> FleetRun:
    """Admits every mission, writes each drone's configuration and then the network's
    file to ``workdir``, and flies the fleet on the parts at their addresses;
    ValueError names a refused mission before anything is written for the drones."""
    workdir.mkdir(parents=True, exist_ok=True)
    # Its presence says the drones' configurations are written: none left from before.
    (workdir / NETWORK_FILE).unlink(missing_ok=True)
    admitted = admit_fleet(fleet, workdir / REGISTRY_FILE)
    network = fleet_network(fleet, parts.stations, parts.certs)
    configs = {
        d.name: mission_config(network, d, admitted[d.name], parts.drones[d.name])
        for d in fleet.drones
    }
    for name, config in configs.items():
        (workdir / name).mkdir(exist_ok=True)
        write_drone_config(workdir / name, config)
    write_network(workdir, network)
    operator = network.tls_for(OPERATOR)
    stations = {
        sid: connect_station(sid, address, workdir / f"station-{sid}", operator)
        for sid, address in parts.stations.items()
    }
    drones = {
        name: connect_drone(name, address, workdir / name, configs[name])
        for name, address in parts.drones.items()
    }
    note_drone_addresses(workdir / REGISTRY_FILE, admitted, drones)
    try:
        return await fly_fleet(fleet, admitted, configs, network, stations, drones, timeout_s)
    finally:
        await close_parts(stations, drones)

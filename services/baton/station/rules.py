"""A station's decisions, pure: which session a call is for, and whether a mission
may start here.

A station serves every mission it hosts on one port and one identity
(docs/design.md, "Stations"). Each call names its mission in the
``baton-mission`` metadata (rpc/mission.py), read before the request: a call
goes to that mission's session or to none, never to another's. A mission
starts only with a valid id the station does not host yet and a
configuration whose ring holds this station; the station's own TLS and the
mission's id replace what the configuration says of them, so a session can
present no other certificate than the station's and stream under no other
mission's name.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import TypeVar

import grpc
import yaml

from baton.config import BatonConfig, ConfigError, TlsConfig, parse_config
from baton.rpc.errors import StatusError
from baton.rpc.mission import MISSION_ID_METADATA, MISSION_ID_PATTERN

S = TypeVar("S")


# What a refusal quotes of a value that is not a mission id, at most (the metadata
# can be kilobytes long).
SHOWN_CHARS = 80


def _hosted(sessions: Mapping[str, object]) -> str:
    return ", ".join(sorted(sessions)) or "none"


def not_a_mission_id(value: str) -> str | None:
    """Why ``value`` is not a mission id (MISSION_ID_PATTERN), quoting it; None if it is."""
    if re.fullmatch(MISSION_ID_PATTERN, value) is not None:
        return None
    shown = value if len(value) <= SHOWN_CHARS else f"{value[:SHOWN_CHARS]}... ({len(value)} chars)"
    return (
        f"{shown!r} is not a mission id: letters, digits, '.', '_' and '-', at most 64, "
        "starting with a letter or a digit"
    )


def route(
    sessions: Mapping[str, S], mission_id: str | None, station_id: int, method: str
) -> S | StatusError:
    """The session ``method``'s call is for, or why there is none: INVALID_ARGUMENT
    for a call that names no mission or names it with what is not a mission id,
    NOT_FOUND naming one the station does not host."""
    name = method.rsplit("/", 1)[-1]
    if mission_id is None:
        return StatusError(
            grpc.StatusCode.INVALID_ARGUMENT,
            f"{name}: station {station_id} serves several missions on this port; name one in "
            f"the {MISSION_ID_METADATA} metadata (grpcurl -H '{MISSION_ID_METADATA}: ID'); "
            f"it hosts: {_hosted(sessions)}",
        )
    malformed = not_a_mission_id(mission_id)
    if malformed is not None:
        return StatusError(
            grpc.StatusCode.INVALID_ARGUMENT,
            f"{name}: the {MISSION_ID_METADATA} metadata {malformed}; station {station_id} "
            f"hosts: {_hosted(sessions)}; nothing was done",
        )
    session = sessions.get(mission_id)
    if session is None:
        return StatusError(
            grpc.StatusCode.NOT_FOUND,
            f"{name}: station {station_id} hosts no mission {mission_id!r} (it hosts: "
            f"{_hosted(sessions)}); nothing was done",
        )
    return session


def invalid(field: str, what: str) -> StatusError:
    """INVALID_ARGUMENT naming a StartMission field."""
    return StatusError(grpc.StatusCode.INVALID_ARGUMENT, f"StartMission: {field}: {what}")


def mission_config(
    mission_id: str,
    config_text: str,
    program: str,
    station_id: int,
    sessions: Mapping[str, object],
    tls: TlsConfig,
) -> BatonConfig | StatusError:
    """The configuration a mission's session runs with on station ``station_id``, or
    why it may not start here (the field named, and the fix)."""
    malformed = not_a_mission_id(mission_id)
    if malformed is not None:
        return invalid("mission_id", malformed)
    if mission_id in sessions:
        return StatusError(
            grpc.StatusCode.ALREADY_EXISTS,
            f"StartMission: station {station_id} hosts mission {mission_id!r} already; "
            "StopMission ends it first",
        )
    if not program:
        return invalid("program", "empty; give the path of the mission file on the station")
    source = f"mission {mission_id}'s config"
    try:
        data = yaml.safe_load(config_text)
    except yaml.YAMLError as exc:
        return invalid("config", f"not valid YAML or JSON: {exc}")
    try:
        config = parse_config(data, source)
    except ConfigError as exc:
        return invalid("config", str(exc))
    if station_id not in config.ring_order:
        return StatusError(
            grpc.StatusCode.FAILED_PRECONDITION,
            f"StartMission: {source}: its ring {config.ring_order} does not hold station "
            f"{station_id}; start it on the ring's stations only",
        )
    return config.model_copy(update={"tls": tls, "mission_id": mission_id})

"""Who may call a controller's drone API: its own mission program, by a token; and
which mission a call to a station is for, by its id.

A controller proxies the drone API to one mission program; every call is
logged and replayed by every replica, so a second caller (a monitoring tool
on the master, a typo in grpcurl) used to break the mission: its call took
the program's request number, or made the program's call fail with
"concurrent call". The controller that starts the mission program gives it a
random token in the environment (``BATON_MISSION_TOKEN``); the SDK sends it
as metadata on every call, and the controller refuses calls without it with
PERMISSION_DENIED. A program started by hand (``python -m baton.sdk.run``)
gets the token the same way: set ``BATON_MISSION_TOKEN`` for the controller
and the program alike. GetStatus stays open to anyone. This is not
authentication: mutual TLS with identities is issue 11's.

A station (``baton station``) serves the controller of many missions on one
port: a call to it names its mission in the ``baton-mission`` metadata, which
the station's dispatcher reads before the request (baton/station/router.py).
"""

from __future__ import annotations

from collections.abc import Iterable

MISSION_TOKEN_ENV = "BATON_MISSION_TOKEN"
MISSION_TOKEN_METADATA = "baton-mission-token"
MISSION_ID_METADATA = "baton-mission"
# A mission id: what a registry, a file name and a log line all take as it is.
MISSION_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"


def metadata_value(metadata: Iterable[tuple[str, str | bytes]] | None, key: str) -> str | None:
    """The value a caller sent under ``key``, if any."""
    for name, value in metadata or ():
        if name == key:
            return value.decode() if isinstance(value, bytes) else value
    return None


def token_in(metadata: Iterable[tuple[str, str | bytes]] | None) -> str | None:
    """The mission token a caller sent, if any."""
    return metadata_value(metadata, MISSION_TOKEN_METADATA)


def mission_in(metadata: Iterable[tuple[str, str | bytes]] | None) -> str | None:
    """The mission id a caller named (the ``baton-mission`` metadata), if any."""
    return metadata_value(metadata, MISSION_ID_METADATA)


def mission_metadata(mission_id: str | None) -> tuple[tuple[str, str], ...] | None:
    """The metadata naming ``mission_id`` on a call to a station; None for none."""
    return None if mission_id is None else ((MISSION_ID_METADATA, mission_id),)

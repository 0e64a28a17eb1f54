"""Who may call a controller's drone API: its own mission program, by a token.

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
"""

from __future__ import annotations

from collections.abc import Iterable

MISSION_TOKEN_ENV = "BATON_MISSION_TOKEN"
MISSION_TOKEN_METADATA = "baton-mission-token"


def token_in(metadata: Iterable[tuple[str, str | bytes]] | None) -> str | None:
    """The mission token a caller sent, if any."""
    for key, value in metadata or ():
        if key == MISSION_TOKEN_METADATA:
            return value.decode() if isinstance(value, bytes) else value
    return None

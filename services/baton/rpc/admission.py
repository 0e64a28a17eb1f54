"""Who may make a call, decided before its request is read; which live calls to cut.

Pure decisions, applied by the gate (baton/rpc/gate.py) on every port:

- ``admit``: a call arrives with the caller's certificate (its identity and
  serial number), the method, and how many calls that caller has in flight
  on this port. A revoked or expired certificate is UNAUTHENTICATED; a caller the
  method's rule excludes is PERMISSION_DENIED; a caller with
  ``calls_per_caller`` calls in flight is RESOURCE_EXHAUSTED. Nothing of the
  request has been read then, so a refused caller costs the port what gRPC
  buffers before the refusal reaches it (its flow-control window), not its
  message.
- ``port_full``: a port of one caller known by no certificate (a controller's
  mission port, whose caller is its mission program, known by its token) takes
  at most ``calls_in_flight`` calls at a time, whoever makes them, TLS or not.
  A program makes one drone call at a time; the calls above that would each
  wait for the one pending and be refused together when it ends, a burst that
  holds the event loop every session of a station shares.
- ``to_cut``: the live streams whose certificates a newer revocation list
  names, or which expired since the stream opened, re-checked by a timer: a
  revoked station loses the streams it held within that timer's period, not
  at its next connection, and a short-lived certificate ends with its time.

Rules that need the request (a controller_id that must be the caller's own)
stay with the servicers; a port's rules here are what the caller's
certificate alone decides. The largest request a port reads
(``max_request_bytes``) is gRPC's ``max_receive_message_length``: gRPC
refuses a bigger message from its length prefix, RESOURCE_EXHAUSTED, before
buffering it.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import TypeVar

import grpc

from baton.rpc.errors import StatusError
from baton.rpc.tls import Identity

# A part's calls in flight on one port at a time. A controller holds a handful of
# streams on the drone (Connect, Standby, InvokeStream) and makes a few unary calls
# beside them; the cap bounds what one certificate can make a port hold in requests
# (the cap times max_request_bytes).
CALLS_PER_CALLER = 32
# How often a port re-reads its revocation list and re-checks its live streams.
RECHECK_S = 1.0


@dataclass(frozen=True)
class Rule:
    """Who may call a method, as a predicate on the caller's identity and in words."""

    who: str
    allowed: Callable[[Identity], bool]


# The certificate issuer is no part of a mission: it mints certificates and acts on none.
ANY_PART = Rule(
    "any part of the mission may, with its certificate", lambda who: who.role != "issuer"
)


def only(identity: Identity, as_: str) -> Rule:
    """A rule admitting exactly ``identity`` (``as_``: what it is, in words)."""
    return Rule(f"only {as_} ({identity.uri}) may", lambda who: who == identity)


def controllers(ids: Iterable[int], of: str) -> Rule:
    """A rule admitting the controllers ``ids`` (``of``: whose controllers, in words)."""
    known = frozenset(ids)
    listed = ", ".join(map(str, sorted(known)))
    return Rule(
        f"only {of}'s controllers ({listed}) may",
        lambda who: who.role == "controller" and who.number in known,
    )


@dataclass(frozen=True)
class PortPolicy:
    """One port's admission: a rule per full method name (a method without one takes
    ``default``), the largest request it reads, and calls in flight per caller."""

    name: str
    max_request_bytes: int
    rules: Mapping[str, Rule] = field(default_factory=dict)
    default: Rule = ANY_PART
    calls_per_caller: int = CALLS_PER_CALLER
    # A port of many missions (a station's): ``calls_per_caller`` counts a caller's
    # calls per mission it names, so that its calls for one mission cannot hold the
    # port's room for another's; this bounds them over all missions (None: no port
    # of many missions).
    calls_per_caller_all_missions: int | None = None
    # The port's calls in flight, whoever makes them, with or without TLS (``port_full``;
    # None: no bound but each caller's).
    calls_in_flight: int | None = None

    def rule(self, method: str) -> Rule:
        return self.rules.get(method, self.default)


@dataclass(frozen=True)
class Caller:
    """Who calls, from its certificate: its identity (None: a certificate of the CA
    naming none of ours), serial number (None: no certificate) and end of validity
    (seconds since the epoch; None: not known)."""

    identity: Identity | None
    serial: int | None
    not_after: float | None = None

    def invalid(self, revoked: frozenset[int], now: float) -> str | None:
        """Why its certificate no longer counts (revoked, expired), or None."""
        if self.serial is not None and self.serial in revoked:
            return "is revoked (the CA folder's revoked.crl)"
        if self.not_after is not None and now > self.not_after:
            return "has expired (baton certs rotate renews a running part's)"
        return None


def describe(caller: Caller) -> str:
    """The caller in a refusal: its identity and its certificate's serial."""
    who = str(caller.identity) if caller.identity is not None else "a certificate naming no part"
    return who if caller.serial is None else f"{who} (certificate serial {caller.serial:x})"


def admit(
    policy: PortPolicy,
    method: str,
    caller: Caller,
    revoked: frozenset[int],
    in_flight: int,
    now: float,
    in_flight_all_missions: int = 0,
) -> StatusError | None:
    """Why ``caller`` may not start ``method`` on this port at ``now``, or None if it
    may. Called on a port with mutual TLS only (an insecure port admits everyone).
    ``in_flight``: the caller's calls in flight (for the mission the call names, on a
    port of many missions); ``in_flight_all_missions``: for all of them.

    gRPC checks a certificate's validity at the handshake only; a connection made
    before the certificate expired is refused here from then on.
    """
    name = method.rsplit("/", 1)[-1]
    invalid = caller.invalid(revoked, now)
    if invalid is not None:
        return invalid_error(name, caller, invalid)
    if caller.identity is None:
        return StatusError(
            grpc.StatusCode.UNAUTHENTICATED,
            f"{name}: the caller presented no baton certificate; {policy.rule(method).who} "
            f"call it on the {policy.name}",
        )
    rule = policy.rule(method)
    if not rule.allowed(caller.identity):
        return StatusError(
            grpc.StatusCode.PERMISSION_DENIED,
            f"{name}: refused to {caller.identity} before reading its request: "
            f"{rule.who} call it on the {policy.name}",
        )
    if in_flight >= policy.calls_per_caller:
        of = " for this mission" if policy.calls_per_caller_all_missions is not None else ""
        return StatusError(
            grpc.StatusCode.RESOURCE_EXHAUSTED,
            f"{name}: {caller.identity} has {in_flight} calls in flight{of} on the "
            f"{policy.name}, the most one part may; end some or wait for them",
        )
    cap = policy.calls_per_caller_all_missions
    if cap is not None and in_flight_all_missions >= cap:
        return StatusError(
            grpc.StatusCode.RESOURCE_EXHAUSTED,
            f"{name}: {caller.identity} has {in_flight_all_missions} calls in flight for "
            f"all its missions on the {policy.name}, the most one part may; end some or "
            "wait for them",
        )
    return None


def port_full(policy: PortPolicy, method: str, in_flight: int) -> StatusError | None:
    """RESOURCE_EXHAUSTED if the port holds ``policy.calls_in_flight`` calls already
    (``in_flight``), before anything of the call is read; None if it has room."""
    cap = policy.calls_in_flight
    if cap is None or in_flight < cap:
        return None
    return StatusError(
        grpc.StatusCode.RESOURCE_EXHAUSTED,
        f"{method.rsplit('/', 1)[-1]}: the {policy.name} has {in_flight} calls in flight, the "
        "most it takes; a mission program makes one drone call at a time (on its "
        "ProgramCalls stream); nothing of this call was read",
    )


def invalid_error(name: str, caller: Caller, why: str) -> StatusError:
    """The refusal of a call ``name`` (LogRing), or the end of its stream, whose
    certificate no longer counts (``why``: ``Caller.invalid``)."""
    return StatusError(
        grpc.StatusCode.UNAUTHENTICATED,
        f"{name}: the certificate of {describe(caller)} {why}; the part needs a new one "
        "(baton certs issue or rotate)",
    )


K = TypeVar("K", bound=Hashable)


def to_cut(live: Mapping[K, Caller], revoked: frozenset[int], now: float) -> list[K]:
    """The live calls whose certificates no longer count at ``now``: revoked by the
    list, or expired while the call was open."""
    return [key for key, who in live.items() if who.invalid(revoked, now) is not None]

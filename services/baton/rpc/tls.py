"""Mutual TLS: who a caller is comes from its certificate, never from a request field.

Every part of a mission has one identity, written in its certificate as a
URI subject alternative name (``spiffe://baton/controller/1``,
``spiffe://baton/drone``, ``spiffe://baton/operator``) beside a DNS name
(``controller-1.baton``). A channel names the identity it expects to reach
and checks the server's certificate against that DNS name, not against the
address it dials: the testbed's link emulators and a container's published
port stand between the two, and the peer is the same whatever the route.
A server requires a client certificate from the mission's CA, and its
servicers ask ``caller(context)`` who is calling (docs/design.md, Security).

Certificates are files in one folder, named after the identity
(``ca.crt``, ``controller-1.crt``, ``controller-1.key``), made by
``baton certs init`` (baton/certs/make.py).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol, cast

import grpc
from cryptography import x509
from cryptography.hazmat.primitives import serialization

from baton.rpc.errors import StatusError

SPIFFE_PREFIX = "spiffe://baton/"
DNS_SUFFIX = ".baton"
ROLES = ("controller", "drone", "operator", "issuer")
CA_CERT = "ca.crt"
CA_KEY = "ca.key"
INSECURE_WARNING = (
    "running insecure: every port is plain and anyone on the network may call it, "
    "the drone included; for debugging only (drop --insecure / tls.insecure)"
)
# A drone's own name in a fleet (spiffe://baton/drone/NAME): one DNS label.
DRONE_NAME_PATTERN = r"[a-z0-9](?:[a-z0-9-]{0,61}[a-z0-9])?"
_URI = re.compile(
    r"spiffe://baton/(controller/(0|[1-9][0-9]{0,9})|drone(?:/(" + DRONE_NAME_PATTERN + r"))?"
    r"|operator|issuer)"
)


@dataclass(frozen=True, order=True)
class Identity:
    """One part of a mission: a controller (with its id), the drone (with its name in a
    fleet, where each drone has its own certificate), an operator, or the certificate
    issuer (baton/certs/issuer.py), which no port lets act on a mission."""

    role: str
    number: int | None = None
    # A drone's name (``Identity.drone``): "" for a mission's one drone.
    label: str = ""

    def __post_init__(self) -> None:
        if self.role not in ROLES:
            raise ValueError(f"unknown role {self.role!r}; one of {', '.join(ROLES)}")
        if (self.role == "controller") != (self.number is not None):
            raise ValueError("a controller identity has a number, the others none")
        if self.label and (
            self.role != "drone" or not re.fullmatch(DRONE_NAME_PATTERN, self.label)
        ):
            raise ValueError(
                f"drone name {self.label!r}: a drone's name in its certificate is one DNS "
                "label: lower-case letters, digits and inner hyphens, at most 63"
            )

    @classmethod
    def controller(cls, cid: int) -> Identity:
        return cls("controller", cid)

    @classmethod
    def drone(cls, name: str = "") -> Identity:
        """A drone: the mission's one drone (``name`` ""), or a fleet's drone ``name``."""
        return cls("drone", label=name)

    @property
    def _tail(self) -> str:
        if self.number is not None:
            return f"{self.role}/{self.number}"
        return f"{self.role}/{self.label}" if self.label else self.role

    @property
    def uri(self) -> str:
        """The URI SAN of its certificate: ``spiffe://baton/controller/1``."""
        return SPIFFE_PREFIX + self._tail

    @property
    def name(self) -> str:
        """Its file name stem and the first label of its DNS name: ``controller-1``,
        ``drone``, ``drone-d1``."""
        return self._tail.replace("/", "-")

    @property
    def dns_name(self) -> str:
        return self.name + DNS_SUFFIX

    @classmethod
    def from_uri(cls, uri: str) -> Identity | None:
        """The identity a URI SAN names, or None for a URI that names none of ours."""
        match = _URI.fullmatch(uri)
        if match is None:
            return None
        if match.group(2) is not None:
            return cls.controller(int(match.group(2)))
        if match.group(3) is not None:
            return cls.drone(match.group(3))
        return cls(uri.removeprefix(SPIFFE_PREFIX))

    def __str__(self) -> str:
        return self.uri


DRONE = Identity.drone()
OPERATOR = Identity("operator")
ISSUER = Identity("issuer")


class TlsError(OSError):
    """A certificate folder that cannot be used; the message names the file and the fix."""


@dataclass(frozen=True)
class Tls:
    """The CA, certificate and key one part presents, loaded from a folder."""

    identity: Identity
    ca: bytes
    cert: bytes
    key: bytes
    # The folder it was read from: its revocation list (revocation.py) lives there.
    folder: Path | None = None

    @classmethod
    def load(cls, directory: str | Path, identity: Identity) -> Tls:
        """Reads ``ca.crt``, ``NAME.crt`` and ``NAME.key`` from ``directory``."""
        folder = Path(directory)
        files = [folder / CA_CERT, folder / f"{identity.name}.crt", folder / f"{identity.name}.key"]
        contents = []
        for path in files:
            try:
                contents.append(path.read_bytes())
            except OSError as exc:
                raise TlsError(
                    f"{path}: cannot read the {identity.name} TLS files ({exc.strerror}); "
                    f"make them with `baton certs init {folder}`, or run with --insecure "
                    "(debugging only: anyone on the network may then call this part)"
                ) from None
        ca, cert, key = contents
        return cls(identity, ca, cert, key, folder)

    def current(self) -> Tls:
        """This part's certificate and key as its folder holds them now (``baton certs
        rotate`` replaces them while the part runs), else these. A pair caught between
        the writes of its two files (a key that is not the certificate's) is not taken:
        the one before it still serves. The CA is the one the part started with."""
        if self.folder is None:
            return self
        try:
            cert = (self.folder / f"{self.identity.name}.crt").read_bytes()
            key = (self.folder / f"{self.identity.name}.key").read_bytes()
        except OSError:
            return self
        if (cert, key) == (self.cert, self.key) or not _pair(cert, key):
            return self
        return replace(self, cert=cert, key=key)

    @staticmethod
    def read_certificate(directory: str | Path, identity: Identity) -> bytes:
        """Another part's certificate (``NAME.crt``, public) from ``directory``: a
        controller checks the drone's signatures against it (baton.authenticity)."""
        path = Path(directory) / f"{identity.name}.crt"
        try:
            return path.read_bytes()
        except OSError as exc:
            raise TlsError(
                f"{path}: cannot read the {identity.name} certificate ({exc.strerror}); "
                f"every controller checks the {identity.name}'s signatures against it: "
                f"copy {identity.name}.crt (not its key) into {directory}, or make the "
                f"folder with `baton certs init {directory}`"
            ) from None

    def server_credentials(self) -> grpc.ServerCredentials:
        """A server that requires a client certificate signed by the mission's CA, and
        presents its newest certificate (``current``) at every new connection."""
        presented = [self]

        def newer() -> grpc.ServerCertificateConfiguration | None:
            # Called by gRPC at each handshake: None keeps the certificate it has.
            fresh = presented[0].current()
            if fresh is presented[0]:
                return None
            presented[0] = fresh
            return grpc.ssl_server_certificate_configuration(
                [(fresh.key, fresh.cert)], root_certificates=self.ca
            )

        first = grpc.ssl_server_certificate_configuration(
            [(self.key, self.cert)], root_certificates=self.ca
        )
        # grpc's stubs omit the None its documentation allows the fetcher to return.
        fetcher = cast(Callable[[], grpc.ServerCertificateConfiguration], newer)
        return grpc.dynamic_ssl_server_credentials(
            first, fetcher, require_client_authentication=True
        )

    def channel_credentials(self) -> grpc.ChannelCredentials:
        """A client that presents its newest certificate (``current``) and trusts the
        mission's CA only; a channel keeps the one it was made with."""
        fresh = self.current()
        return grpc.ssl_channel_credentials(
            root_certificates=self.ca, private_key=fresh.key, certificate_chain=fresh.cert
        )


def _pair(cert_pem: bytes, key_pem: bytes) -> bool:
    """Whether the key is the certificate's (both parse)."""
    try:
        cert = x509.load_pem_x509_certificate(cert_pem)
        key = serialization.load_pem_private_key(key_pem, None)
    except (ValueError, TypeError):
        return False
    spki = serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    return cert.public_key().public_bytes(*spki) == key.public_key().public_bytes(*spki)


class _HasAuthContext(Protocol):
    def auth_context(self) -> Mapping[str, Iterable[bytes]]: ...


def caller(context: _HasAuthContext) -> Identity | None:
    """The identity in the caller's certificate; None on an insecure port or for a
    certificate that names none of ours. gRPC has verified the chain already."""
    auth = context.auth_context()
    for uri in [*auth.get("peer_spiffe_id", ()), *auth.get("x509_subject_alternative_name", ())]:
        found = Identity.from_uri(uri.decode(errors="replace"))
        if found is not None:
            return found
    return None


def refused(
    context: _HasAuthContext,
    enforced: bool,
    what: str,
    rule: str,
    allowed: Callable[[Identity], bool],
) -> StatusError | None:
    """Why the caller may not make this call, or None if it may.

    ``enforced`` is False on an insecure server (everyone may). Otherwise a
    caller without a baton certificate is UNAUTHENTICATED (a plain port, or
    the mission program's loopback port, where only the token counts) and one
    whose identity the ``allowed`` rule excludes is PERMISSION_DENIED; the
    message names the call, the identity and the ``rule`` in words.
    """
    if not enforced:
        return None
    who = caller(context)
    if who is None:
        return StatusError(
            grpc.StatusCode.UNAUTHENTICATED,
            f"{what}: the caller presented no baton certificate; {rule}",
        )
    if allowed(who):
        return None
    return StatusError(grpc.StatusCode.PERMISSION_DENIED, f"{what}: refused to {who}: {rule}")


def refused_status(context: _HasAuthContext, enforced: bool) -> StatusError | None:
    """``refused`` for a GetStatus: any part of the mission, with its certificate."""
    return refused(
        context,
        enforced,
        "GetStatus",
        "any part of the mission may read the status, with its certificate",
        lambda who: True,
    )

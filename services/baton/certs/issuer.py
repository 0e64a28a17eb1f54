"""The certificate issuer: short-lived certificates for running parts (``baton certs
issuer``), in the spirit of SPIFFE's short-lived SVIDs.

It runs where the CA key is and serves ``baton.v1.Issuer`` under mutual TLS. A
part that holds a valid certificate of the CA asks for its next one (renewal.py),
over a key it has just made; the issuer signs a certificate naming the identity
of the certificate the part called with, never one the request names, valid for
the issuer's lifetime from now. So a part renews only itself, a revoked
certificate renews nothing (the port's gate refuses it before its request is
read, gate.py), and a stolen certificate that is not renewed dies within one
lifetime. The issuer's own server certificate is minted in memory at start from
the CA key it holds (identity ``spiffe://baton/issuer``, which no other port lets
act on a mission).

One lineage per identity: the issuer keeps the serial it last gave each identity
(``issued.json`` in the folder, replaced atomically) and renews only from that
certificate, or from the one the folder holds for the part (``baton certs issue``
or ``rotate`` by hand). A second holder of a part's certificate (a copy, a thief)
can renew at most once; then one of the two is refused at its next renewal, says
so, and the operator revokes and re-keys the part.
"""

from __future__ import annotations

import datetime
import json
from pathlib import Path

import grpc
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec

from baton.certs.make import key_pem, load_ca, serial_of, sign_certificate, write_file
from baton.rpc.admission import PortPolicy, Rule
from baton.rpc.errors import StatusError, abort_with
from baton.rpc.gate import caller_of
from baton.rpc.server import BatonServer, servicer
from baton.rpc.tls import CA_CERT, ISSUER, Identity, Tls, TlsError
from baton.v1 import issuer_pb2, issuer_pb2_grpc

# A renewal request is a public key, a few hundred bytes.
RENEW_REQUEST_BYTES = 4096
# How far back a new certificate's validity starts: the clocks of edge nodes are not
# exact, and a certificate not yet valid on its peer would be refused.
CLOCK_SKEW = datetime.timedelta(seconds=30)
SERVICE = "baton.v1.Issuer"
# In the CA's folder: the serial the issuer last gave each identity, by name.
ISSUED_FILE = "issued.json"

_A_PART = Rule(
    "any part with a certificate of the CA may renew its own",
    lambda who: who != ISSUER,
)


def issuer_policy() -> PortPolicy:
    """The issuer's port: every part of the CA may renew itself; a request is a key."""
    return PortPolicy("issuer's port", RENEW_REQUEST_BYTES, default=_A_PART)


def public_key_of(pem: bytes) -> ec.EllipticCurvePublicKey:
    """The P-256 public key in ``pem``; StatusError (INVALID_ARGUMENT) otherwise."""
    try:
        key = serialization.load_pem_public_key(pem)
    except (ValueError, TypeError) as exc:
        raise StatusError(
            grpc.StatusCode.INVALID_ARGUMENT,
            f"Renew: public_key_pem is not a PEM public key ({exc}); send the public half "
            "of a new EC P-256 key, as SubjectPublicKeyInfo",
        ) from None
    if not isinstance(key, ec.EllipticCurvePublicKey) or key.curve.name != "secp256r1":
        raise StatusError(
            grpc.StatusCode.INVALID_ARGUMENT,
            "Renew: public_key_pem is not an EC P-256 key; every baton key is (baton certs)",
        )
    return key


class IssuerService(issuer_pb2_grpc.IssuerServicer):
    """Signs the caller's next certificate with the folder's CA key."""

    def __init__(self, folder: Path, lifetime: datetime.timedelta) -> None:
        self.folder = folder
        self.ca_cert, self.ca_key = load_ca(folder)
        self.lifetime = lifetime
        self.issued = 0
        self.newest = _read_issued(folder / ISSUED_FILE)

    def renewed(
        self, identity: Identity, public_key: ec.EllipticCurvePublicKey, now: datetime.datetime
    ) -> x509.Certificate:
        """``identity``'s next certificate over ``public_key``, valid from ``now`` (less
        the clock skew) for the lifetime."""
        return sign_certificate(
            self.ca_cert,
            self.ca_key,
            identity,
            public_key,
            now - CLOCK_SKEW,
            now + self.lifetime,
        )

    def lineage(self, identity: Identity, serial: int | None) -> StatusError | None:
        """Why a certificate with ``serial`` may not renew ``identity`` (not the newest
        this issuer gave it, nor the folder's), or None."""
        newest = self.newest.get(identity.name)
        if newest is None or serial == newest:
            return None
        if serial is not None and serial == serial_of(self.folder / f"{identity.name}.crt"):
            return None
        return StatusError(
            grpc.StatusCode.PERMISSION_DENIED,
            f"Renew: refused to {identity}: certificate serial {serial or 0:x} is not the "
            f"newest this issuer gave it ({newest:x}); another holder of its certificate "
            f"renewed it. Revoke both (baton certs revoke) and re-key the part "
            f"(baton certs issue)",
        )

    async def Renew(
        self, request: issuer_pb2.RenewRequest, context: grpc.aio.ServicerContext
    ) -> issuer_pb2.RenewReply:
        who = caller_of(context)
        try:
            if who.identity is None:  # the gate lets no such caller through on a secure port
                raise StatusError(
                    grpc.StatusCode.UNAUTHENTICATED,
                    "Renew: the caller presented no certificate naming a baton part",
                )
            refused = self.lineage(who.identity, who.serial)
            if refused is not None:
                raise refused
            key = public_key_of(request.public_key_pem)
        except StatusError as exc:
            await abort_with(context, exc)
        cert = self.renewed(who.identity, key, datetime.datetime.now(datetime.UTC))
        self.newest[who.identity.name] = cert.serial_number
        write_file(
            self.folder / ISSUED_FILE,
            json.dumps(
                {name: f"{serial:x}" for name, serial in sorted(self.newest.items())}
            ).encode(),
        )
        self.issued += 1
        return issuer_pb2.RenewReply(
            certificate_pem=cert.public_bytes(serialization.Encoding.PEM),
            not_before_unix_s=cert.not_valid_before_utc.timestamp(),
            not_after_unix_s=cert.not_valid_after_utc.timestamp(),
        )


def _read_issued(path: Path) -> dict[str, int]:
    """The serials ``issued.json`` names (none without the file); TlsError naming the
    file if it does not parse."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        return {}
    try:
        return {str(name): int(serial, 16) for name, serial in json.loads(text).items()}
    except (ValueError, AttributeError, TypeError) as exc:
        raise TlsError(
            f"{path}: not the issuer's record of the serials it gave ({exc}); remove it to "
            "let every part's next renewal start a new record"
        ) from None


def issuer_tls(folder: Path) -> Tls:
    """The issuer's own certificate and key, minted in memory with the CA key for as
    long as the CA is valid. ``folder`` is kept for its revocation list."""
    ca_cert, ca_key = load_ca(folder)
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.UTC)
    cert = sign_certificate(
        ca_cert, ca_key, ISSUER, key.public_key(), now - CLOCK_SKEW, ca_cert.not_valid_after_utc
    )
    return Tls(
        ISSUER,
        (folder / CA_CERT).read_bytes(),
        cert.public_bytes(serialization.Encoding.PEM),
        key_pem(key),
        folder,
    )


def issuer_server(
    folder: Path, address: str, lifetime: datetime.timedelta
) -> tuple[BatonServer, IssuerService]:
    """The issuer's server on ``address`` (not started) and its servicer."""
    service = IssuerService(folder, lifetime)
    server = BatonServer(
        address,
        [servicer(SERVICE, issuer_pb2_grpc.add_IssuerServicer_to_server, service)],
        tls=issuer_tls(folder),
        policy=issuer_policy(),
    )
    return server, service

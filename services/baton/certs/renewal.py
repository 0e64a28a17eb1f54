"""A running part keeps its certificate short-lived: it asks the issuer (issuer.py) for
the next one halfway through the one it holds (``--renew-from ADDRESS``).

The part makes a new key, sends its public half, checks what comes back (signed
by its CA, naming its own identity, over its new key, valid now) and writes the
pair into its folder, key first. It takes the pair without a restart, as it takes
a ``baton certs rotate`` (tls.py's ``Tls.current``: its port presents it at every
new connection, and every channel it makes from then on). An ask that fails is
tried again, sooner and sooner before the certificate expires, with a warning
each time; past expiry it is an error, named, because no peer will then take a
new connection from the part. A revoked certificate renews nothing: the issuer
refuses it, and the part says so.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Awaitable
from dataclasses import dataclass
from typing import TypeVar

import grpc
from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec

from baton.certs.make import key_pem, write_file
from baton.logs import get_logger
from baton.rpc.channels import aio_channel
from baton.rpc.tls import ISSUER, Identity, Tls
from baton.v1 import issuer_pb2, issuer_pb2_grpc

T = TypeVar("T")

# Asked for the next certificate this far through the lifetime of the one held.
RENEW_AT = 0.5
# After a failed ask: again after this share of the lifetime (within the bounds).
RETRY_SHARE = 0.05
RETRY_MIN_S = 1.0
RETRY_MAX_S = 60.0
ASK_TIMEOUT_S = 10.0
# The longest sleep between looks at the certificate held.
RECHECK_S = 60.0


@dataclass(frozen=True)
class Validity:
    """A certificate's serial and validity, in seconds since the Unix epoch."""

    serial: int
    not_before: float
    not_after: float

    @classmethod
    def of(cls, cert_pem: bytes) -> Validity:
        cert = x509.load_pem_x509_certificate(cert_pem)
        return cls(
            cert.serial_number,
            cert.not_valid_before_utc.timestamp(),
            cert.not_valid_after_utc.timestamp(),
        )


def next_ask(validity: Validity, taken_at: float, now: float, failures: int) -> float:
    """When to ask for the next certificate (Unix seconds): ``RENEW_AT`` of the way
    from when the part took the one it holds (``taken_at``; its start of validity if
    later) to its expiry, so that a certificate back-dated for clock skew is not renewed
    at once; after ``failures`` failed asks in a row, a back-off of ``RETRY_SHARE`` of
    that span (1 s to 60 s) from ``now``."""
    start = max(taken_at, validity.not_before)
    span = max(validity.not_after - start, 0.0)
    due = start + RENEW_AT * span
    if failures == 0:
        return due
    return max(due, now + min(max(RETRY_SHARE * span, RETRY_MIN_S), RETRY_MAX_S))


def checked(
    reply: issuer_pb2.RenewReply,
    ca_pem: bytes,
    identity: Identity,
    public_key: ec.EllipticCurvePublicKey,
    now: float,
) -> x509.Certificate | str:
    """The issued certificate, or why it cannot be taken: not signed by our CA, not
    naming us, not over the key we sent, or not valid now."""
    try:
        cert = x509.load_pem_x509_certificate(reply.certificate_pem)
        ca = x509.load_pem_x509_certificate(ca_pem)
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature) as exc:
        return f"the reply is not a certificate signed by our CA ({exc or 'bad signature'})"
    try:
        sans = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return "the certificate names no part"
    uris = sans.get_values_for_type(x509.UniformResourceIdentifier)
    if uris != [identity.uri]:
        return f"the certificate names {uris}, not {identity.uri}"
    spki = serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    if cert.public_key().public_bytes(*spki) != public_key.public_bytes(*spki):
        return "the certificate is not over the key we sent"
    if not cert.not_valid_before_utc.timestamp() <= now < cert.not_valid_after_utc.timestamp():
        return (
            f"the certificate is not valid now (from {cert.not_valid_before_utc} to "
            f"{cert.not_valid_after_utc}); check both machines' clocks"
        )
    return cert


async def ask(tls: Tls, address: str) -> tuple[x509.Certificate, bytes]:
    """One renewal: a new key, the issuer's certificate over it, checked. Returns the
    certificate and the key's PEM; raises grpc.aio.AioRpcError or ValueError (the
    reply not taken, saying why)."""
    key = ec.generate_private_key(ec.SECP256R1())
    public = key.public_key()
    request = issuer_pb2.RenewRequest(
        public_key_pem=public.public_bytes(
            serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
        )
    )
    async with aio_channel(address, tls, ISSUER) as channel:
        reply = await issuer_pb2_grpc.IssuerStub(channel).Renew(request, timeout=ASK_TIMEOUT_S)
    cert = checked(reply, tls.ca, tls.identity, public, time.time())
    if isinstance(cert, str):
        raise ValueError(cert)
    return cert, key_pem(key)


async def keep_renewed(tls: Tls, address: str) -> None:
    """Renews ``tls``'s certificate from the issuer at ``address`` for as long as it runs
    (until cancelled). ``tls`` must have its folder: the new pair is written there."""
    folder = tls.folder
    assert folder is not None, "a part renews the certificate of its folder"
    log = get_logger("certs", identity=str(tls.identity), issuer=address)
    failures = 0
    taken: tuple[int, float] | None = None  # the serial held, and when it was taken
    while True:
        held = Validity.of(tls.current().cert)
        now = time.time()
        if taken is None or taken[0] != held.serial:  # at start, or rotated by hand
            taken = held.serial, now
        due = next_ask(held, taken[1], now, failures)
        if due > now:
            # Looked at again at least every RECHECK_S: a rotation by hand moves it.
            await asyncio.sleep(min(due - now, RECHECK_S))
            continue
        try:
            cert, key = await ask(tls, address)
            # Key first: a reader between the two writes finds a key that is not the
            # certificate's, and keeps the pair it had (Tls.current).
            write_file(folder / f"{tls.identity.name}.key", key, private=True)
            write_file(
                folder / f"{tls.identity.name}.crt",
                cert.public_bytes(serialization.Encoding.PEM),
            )
        except (grpc.aio.AioRpcError, ValueError, OSError) as exc:
            failures += 1
            reason = exc.details() if isinstance(exc, grpc.aio.AioRpcError) else str(exc)
            code = exc.code().name if isinstance(exc, grpc.aio.AioRpcError) else type(exc).__name__
            left = held.not_after - time.time()
            if left <= 0:
                log.error(
                    "certificate expired and not renewed: no peer takes a new connection "
                    "from this part; start the issuer, or renew it (baton certs rotate)",
                    serial=f"{held.serial:x}",
                    code=code,
                    reason=reason,
                    failures=failures,
                )
            else:
                log.warning(
                    "certificate not renewed; asking again",
                    serial=f"{held.serial:x}",
                    expires_in_s=round(left, 1),
                    code=code,
                    reason=reason,
                    failures=failures,
                )
            continue
        failures = 0
        taken = cert.serial_number, time.time()
        log.info(
            "certificate renewed",
            replaced=f"{held.serial:x}",
            serial=f"{cert.serial_number:x}",
            valid_until=cert.not_valid_after_utc.isoformat(timespec="seconds"),
        )


async def renewing(main: Awaitable[T], tls: Tls | None, address: str | None) -> T:
    """Runs ``main`` with ``tls``'s certificate kept renewed from ``address`` beside it
    (nothing beside it without an address or insecure)."""
    if tls is None or address is None:
        return await main
    task = asyncio.create_task(keep_renewed(tls, address), name="certificate renewal")
    try:
        return await main
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task

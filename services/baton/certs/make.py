"""Making a mission's CA and its parts' certificates, with ``cryptography``.

One CA per mission (or per fleet): its key signs one certificate per part,
each naming the part's identity (baton/rpc/tls.py) as a URI SAN and a DNS
name, usable as a server and as a client (every part is both). Keys are
ECDSA P-256, written owner-read-only. The CA key stays in the folder so that
``issue`` can add a part or renew one later; a deployment moves it offline.
"""

from __future__ import annotations

import datetime
import os
from collections.abc import Iterable
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from baton.rpc.revocation import REVOKED_CRL, revoked_serials
from baton.rpc.tls import CA_CERT, CA_KEY, Identity, TlsError

DEFAULT_DAYS = 365
_SKEW = datetime.timedelta(minutes=5)  # clocks of edge nodes are not exact


def write_file(path: Path, data: bytes, private: bool = False) -> None:
    """Replaces ``path`` atomically: a running part that re-reads it (a rotation, a
    revocation list) sees the old file or the new one, never a part of one."""
    partial = path.with_name(path.name + ".new")
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC
    fd = os.open(partial, flags, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as out:
        out.write(data)
    os.replace(partial, path)


def key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _name(common_name: str) -> x509.Name:
    return x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "baton"),
            x509.NameAttribute(NameOID.COMMON_NAME, common_name),
        ]
    )


def make_ca(directory: Path, days: int = DEFAULT_DAYS) -> None:
    """Writes ``ca.crt`` and ``ca.key`` into ``directory``."""
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.UTC)
    name = _name("baton mission CA")
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - _SKEW)
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=False,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    write_file(directory / CA_CERT, cert.public_bytes(serialization.Encoding.PEM))
    write_file(directory / CA_KEY, key_pem(key), private=True)


def load_ca(directory: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    try:
        cert = x509.load_pem_x509_certificate((directory / CA_CERT).read_bytes())
        key = serialization.load_pem_private_key((directory / CA_KEY).read_bytes(), None)
    except (OSError, ValueError) as exc:
        raise TlsError(
            f"{directory}: no usable CA ({CA_CERT} and {CA_KEY}: {exc}); "
            f"make one with `baton certs init {directory}`"
        ) from None
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise TlsError(f"{directory / CA_KEY}: not an EC key; make the CA with `baton certs init`")
    return cert, key


def issue(
    directory: Path,
    identity: Identity,
    days: int = DEFAULT_DAYS,
    not_before: datetime.datetime | None = None,
    valid_for: datetime.timedelta | None = None,
) -> tuple[int | None, int]:
    """Writes ``NAME.crt`` and ``NAME.key`` for ``identity``, signed by the folder's CA;
    returns the serial of the certificate it replaced (None: none) and the new one's.

    Valid for ``days`` from now (``valid_for`` instead: a short-lived certificate,
    ``rotate``), or from ``not_before`` (tests make expired certificates).
    """
    ca_cert, ca_key = load_ca(directory)
    replaced = serial_of(directory / f"{identity.name}.crt")
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.UTC)
    valid = valid_for or datetime.timedelta(days=days)
    # Valid from a little before now (clock skew) for ``valid`` from now, or from
    # ``not_before`` for ``valid`` from then.
    start, end = (
        (now - _SKEW, now + valid) if not_before is None else (not_before, not_before + valid)
    )
    cert = sign_certificate(ca_cert, ca_key, identity, key.public_key(), start, end)
    write_file(directory / f"{identity.name}.crt", cert.public_bytes(serialization.Encoding.PEM))
    write_file(directory / f"{identity.name}.key", key_pem(key), private=True)
    return replaced, cert.serial_number


def sign_certificate(
    ca_cert: x509.Certificate,
    ca_key: ec.EllipticCurvePrivateKey,
    identity: Identity,
    public_key: ec.EllipticCurvePublicKey,
    not_before: datetime.datetime,
    not_after: datetime.datetime,
) -> x509.Certificate:
    """A certificate naming ``identity`` (URI and DNS SANs) over ``public_key``, usable
    as a server and as a client, signed by the CA: ``issue`` and the issuer's
    ``Renew`` (issuer.py) both make theirs here."""
    return (
        x509.CertificateBuilder()
        .subject_name(_name(identity.name))
        .issuer_name(ca_cert.subject)
        .public_key(public_key)
        .serial_number(x509.random_serial_number())
        .not_valid_before(not_before)
        .not_valid_after(not_after)
        .add_extension(
            x509.SubjectAlternativeName(
                [
                    x509.UniformResourceIdentifier(identity.uri),
                    x509.DNSName(identity.dns_name),
                ]
            ),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
            critical=False,
        )
        .sign(ca_key, hashes.SHA256())
    )


def serial_of(path: Path) -> int | None:
    """The serial number of the certificate in ``path``; None if there is none."""
    try:
        return x509.load_pem_x509_certificate(path.read_bytes()).serial_number
    except (OSError, ValueError):
        return None


def revoke(directory: Path, serial: int) -> frozenset[int]:
    """Adds ``serial`` to the folder's revocation list (``revoked.crl``, signed by its
    CA) and returns every serial it revokes."""
    ca_cert, ca_key = load_ca(directory)
    path = directory / REVOKED_CRL
    now = datetime.datetime.now(datetime.UTC)
    builder = (
        x509.CertificateRevocationListBuilder()
        .issuer_name(ca_cert.subject)
        .last_update(now)
        # Parts keep a list however old it is (a revocation never expires);
        # next_update is X.509's required field, not a deadline baton keeps.
        .next_update(now + datetime.timedelta(days=DEFAULT_DAYS))
    )
    revoked = {serial: now}
    if path.exists():
        ca_pem = ca_cert.public_bytes(serialization.Encoding.PEM)
        data = path.read_bytes()
        revoked_serials(data, ca_pem, path)  # refuses a list that is not this CA's
        for entry in x509.load_pem_x509_crl(data):
            revoked.setdefault(entry.serial_number, entry.revocation_date_utc)
    for number, when in sorted(revoked.items()):
        builder = builder.add_revoked_certificate(
            x509.RevokedCertificateBuilder().serial_number(number).revocation_date(when).build()
        )
    crl = builder.sign(ca_key, hashes.SHA256())
    write_file(path, crl.public_bytes(serialization.Encoding.PEM))
    return frozenset(revoked)


def init(directory: Path, identities: Iterable[Identity], days: int = DEFAULT_DAYS) -> None:
    """A new CA in ``directory`` (created) and a certificate for each identity.

    Refuses a folder that holds a CA already: a new CA would lock out every part
    still holding a certificate of the old one (``issue`` adds to a folder).
    """
    if (directory / CA_KEY).exists():
        raise TlsError(
            f"{directory / CA_KEY}: a CA exists already; add or renew a part's certificate "
            f"with `baton certs issue {directory} NAME`, or remove the folder for a new CA"
        )
    directory.mkdir(parents=True, exist_ok=True)
    make_ca(directory, days)
    for identity in identities:
        issue(directory, identity, days)


def ensure(directory: Path, identities: Iterable[Identity], days: int = DEFAULT_DAYS) -> None:
    """A CA in ``directory`` and a certificate for each identity, making only what is
    missing (a testbed run again in its folder keeps the CA it made before)."""
    directory.mkdir(parents=True, exist_ok=True)
    if not (directory / CA_KEY).exists():
        make_ca(directory, days)
    for identity in identities:
        if not (directory / f"{identity.name}.crt").exists():
            issue(directory, identity, days)

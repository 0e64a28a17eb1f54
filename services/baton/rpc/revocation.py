"""The revocation list every part reads: ``revoked.crl`` beside ``ca.crt``.

``baton certs revoke`` (baton/certs/make.py) writes it, a CRL signed by the
folder's CA, atomically (a reader sees the old list or the new one). Every
port with mutual TLS reads it when it starts and again whenever the file
changes (gate.py's timer), so a revoked certificate is refused without
re-keying the other parts or restarting them. A list that does not parse or
is not signed by the folder's CA is not believed: the port keeps the list it
had and says why, so a damaged file never un-revokes a certificate.
"""

from __future__ import annotations

import os
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec

from baton.rpc.tls import TlsError

REVOKED_CRL = "revoked.crl"


def revoked_serials(crl_pem: bytes, ca_pem: bytes, path: Path) -> frozenset[int]:
    """The serial numbers a CRL revokes; TlsError if it is not one of this CA's."""
    try:
        crl = x509.load_pem_x509_crl(crl_pem)
        ca = x509.load_pem_x509_certificate(ca_pem)
    except ValueError as exc:
        raise TlsError(
            f"{path}: not a PEM revocation list ({exc}); write it with `baton certs revoke`"
        ) from None
    key = ca.public_key()
    if not isinstance(key, ec.EllipticCurvePublicKey):
        raise TlsError(
            f"{path.parent / 'ca.crt'}: not an EC key; make the CA with `baton certs init`"
        )
    if crl.issuer != ca.subject or not crl.is_signature_valid(key):
        raise TlsError(
            f"{path}: not signed by this folder's CA ({path.parent / 'ca.crt'}); write it "
            "with `baton certs revoke` in the folder of the CA that signed the parts"
        )
    return frozenset(revoked.serial_number for revoked in crl)


class RevocationList:
    """A folder's ``revoked.crl``, read again when its file changes."""

    def __init__(self, path: Path, ca_pem: bytes) -> None:
        self.path = path
        self._ca = ca_pem
        self._seen: tuple[int, int, int] | None = None
        self.serials: frozenset[int] = frozenset()

    def refresh(self) -> str | None:
        """Reads the file if it changed since the last look (no file: nothing revoked).
        Returns why a changed file was not believed (the old list stays), else None."""
        try:
            stat = os.stat(self.path)
        except FileNotFoundError:
            self._seen, self.serials = None, frozenset()
            return None
        except OSError as exc:
            return f"{self.path}: cannot read the revocation list ({exc.strerror})"
        seen = (stat.st_ino, stat.st_mtime_ns, stat.st_size)
        if seen == self._seen:
            return None
        self._seen = seen
        try:
            self.serials = revoked_serials(self.path.read_bytes(), self._ca, self.path)
        except (TlsError, OSError) as exc:
            return f"{exc}; the {len(self.serials)} revocations read before still hold"
        return None

"""The keys a controller checks log messages against, and seals its own with, kept as
current as the certificate folder and its revocation list.

A controller reads the drone's and every ring controller's certificate when it
starts (``ring_keys``). ``PeerKeys.refresh`` runs whenever the ring port's gate
re-reads the revocation list (``rpc/gate.py``, every second): a certificate that
list revokes no longer signs for its part (``authenticity.Keys.revoked``), a
certificate replaced in the folder (``baton certs rotate``) is read again, the
one it replaced kept for the messages it signed (until it is revoked), and this
controller seals with its own newest key (``Tls.current``), so its peers, which
read the new certificate, believe what it creates from then on. A file that
cannot be read or checked leaves the key read before (said in the log).
"""

from __future__ import annotations

import datetime
import os
from collections.abc import Callable
from pathlib import Path

from baton.authenticity import AuthenticityError, Keys, Signer, Verifier
from baton.config import BatonConfig
from baton.controller.protocol import Sealable
from baton.rpc.tls import Identity, Tls, TlsError


def ring_keys(config: BatonConfig, tls: Tls) -> Keys:
    """The drone's and every ring controller's key, from ``NAME.crt`` in the certificate
    folder, each checked against the mission's CA now; TlsError naming the file and the
    fix otherwise."""
    return Keys(
        _verifier(config, tls, config.drone_identity),
        {cid: _verifier(config, tls, Identity.controller(cid)) for cid in config.ring_order},
    )


def _verifier(config: BatonConfig, tls: Tls, who: Identity) -> Verifier:
    certs = config.tls.certs
    pem = Tls.read_certificate(certs, who)
    try:
        return Verifier.from_pem(pem, tls.ca, datetime.datetime.now(datetime.UTC), who)
    except (AuthenticityError, ValueError) as exc:
        raise TlsError(
            f"{certs / (who.name + '.crt')}: {exc}; make it with `baton certs issue "
            f"{certs} {who.name}` and copy {who.name}.crt to every controller"
        ) from None


class PeerKeys:
    """The keys of a running controller (``ring_keys`` at its start), refreshed."""

    def __init__(
        self, config: BatonConfig, tls: Tls, warn: Callable[[str], None] | None = None
    ) -> None:
        self.config = config
        self.tls = tls
        self.keys = ring_keys(config, tls)
        self.sealing = tls
        self._warn = warn or (lambda _: None)
        self._seen = self._stats()

    def _who(self) -> list[Identity]:
        return [self.config.drone_identity, *map(Identity.controller, self.config.ring_order)]

    def _stats(self) -> dict[Path, tuple[int, int, int] | None]:
        stats: dict[Path, tuple[int, int, int] | None] = {}
        for who in self._who():
            path = Path(self.config.tls.certs) / f"{who.name}.crt"
            try:
                found = os.stat(path)
                stats[path] = (found.st_ino, found.st_mtime_ns, found.st_size)
            except OSError:
                stats[path] = None
        return stats

    def refresh(self, revoked: frozenset[int]) -> bool:
        """Takes the revocation list's serials and any certificate replaced since the
        last look; whether the keys changed."""
        stats = self._stats()
        if stats == self._seen and revoked == self.keys.revoked:
            return False
        read_again = stats != self._seen
        self._seen = stats
        keys = self.keys
        drone, controllers = keys.drone, dict(keys.controllers)
        earlier = {cid: tuple(held) for cid, held in keys.earlier.items()}
        if read_again:
            for who in self._who():
                try:
                    new = _verifier(self.config, self.tls, who)
                except TlsError as exc:
                    self._warn(f"{exc}; its key read before still holds")
                    continue
                if who.role == "drone":
                    drone = new if new.serial != drone.serial else drone
                    continue
                cid = who.number
                assert cid is not None
                old = controllers[cid]
                if new.serial != old.serial:
                    controllers[cid] = new
                    earlier[cid] = (old, *earlier.get(cid, ()))
        self.keys = Keys(drone, controllers, earlier, revoked)
        return True

    def seal(self) -> Callable[[Sealable], bytes] | None:
        """This controller's newest key's seal, if its folder holds a newer pair than the
        one it seals with (``Tls.current``), else None."""
        current = self.tls.current()
        if current.key == self.sealing.key:
            return None
        self.sealing = current
        return Signer.from_pem(current.key).seal

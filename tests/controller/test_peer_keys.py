"""A running controller's log message keys follow its certificate folder and the
revocation list (controller/peer_keys.py): files, no sockets."""

from __future__ import annotations

from pathlib import Path

from baton.authenticity import Signer, refusal
from baton.certs.make import init, issue
from baton.controller.peer_keys import PeerKeys
from baton.rpc.tls import DRONE, Identity, Tls
from baton.testbed.local import local_config
from baton.v1 import ring_pb2


def by(key: bytes) -> ring_pb2.LogMessage:
    """An empty log message of controller 1, sealed with ``key``."""
    message = ring_pb2.LogMessage(lognr=2, origin=1, sender=1)
    Signer.from_pem(key).seal(message)
    return message


def test_a_rotated_peer_is_read_again_and_a_revoked_key_believed_no_more(
    tmp_path: Path,
) -> None:
    folder = tmp_path / "certs"
    init(folder, [DRONE, *map(Identity.controller, (0, 1))])
    config = local_config(2, tls={"certs": str(folder)})
    ours = Tls.load(folder, Identity.controller(0))
    peers = PeerKeys(config, ours)
    old = Tls.load(folder, Identity.controller(1))
    assert not peers.refresh(frozenset())  # nothing changed
    assert peers.seal() is None
    issue(folder, Identity.controller(1))  # `baton certs rotate` of controller 1
    new = Tls.load(folder, Identity.controller(1))
    assert peers.refresh(frozenset())
    assert refusal(peers.keys, by(new.key), 0) is None  # its new key, read again
    assert refusal(peers.keys, by(old.key), 0) is None  # what it signed before
    old_serial = peers.keys.earlier[1][0].serial
    assert peers.refresh(frozenset({old_serial}))
    why = refusal(peers.keys, by(old.key), 0) or ""
    assert f"controller 1's revoked certificate (serial {old_serial:x})" in why
    assert refusal(peers.keys, by(new.key), 0) is None
    # Our own rotation: we seal with the new key from then on, once.
    issue(folder, Identity.controller(0))
    seal = peers.seal()
    assert seal is not None and peers.seal() is None
    message = ring_pb2.LogMessage(lognr=3, origin=0, sender=0)
    seal(message)
    assert peers.refresh(frozenset({old_serial}))  # its peers read our new certificate
    assert refusal(peers.keys, message, 1) is None

"""The request digest shared by the drone's reply cache and the controllers' log.

SHA-256 over the full method name and the serialized request: the drone uses
it to refuse a re-sent request number that asks something else, and the
controllers use it as the determinism guard of the replay. Both sides must
compute it the same way, so there is exactly one function.
"""

from __future__ import annotations

import hashlib


def request_digest(method: str, request: bytes) -> bytes:
    """SHA-256 of ``method``, a zero byte, and the serialized ``request``."""
    return hashlib.sha256(method.encode() + b"\0" + bytes(request)).digest()

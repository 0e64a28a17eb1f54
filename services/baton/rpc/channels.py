"""The one place that creates gRPC channels, with the project's options.

Log messages and pictures are far larger than gRPC's 4 MB default, so every
channel and server raises the message limits explicitly; keepalive detects a
dead peer on a long-lived ring or Connect stream within seconds. gRPC needs
three options for that, not one: the ping interval and its timeout, the
minimum time between pings on a connection that carries no data (5 minutes
by default, which would space the pings of an idle held stream out that
far), and the ping timeout (gRPC 1.8x closes a transport whose ping goes
unanswered only after ``grpc.http2.ping_timeout_ms``, 1 minute by default,
whatever the keepalive timeout). Found with a frozen link emulator: a held
stream outlived a silent peer for a minute (tests/controller/test_takeover.py).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import grpc

if TYPE_CHECKING:
    from baton.rpc.tls import Identity, Tls

# A picture at the largest resolution is 8192*8192*3 bytes (192 MiB) plus its
# header; the ring additionally slices log messages into frames (see ring.py),
# so this bound is for single replies only.
MAX_MESSAGE_BYTES = 256 * 1024 * 1024
# A ping after 10 s without one, the peer dead after 5 s more without its answer.
KEEPALIVE_MS, KEEPALIVE_TIMEOUT_MS = 10_000, 5_000

CHANNEL_OPTIONS: list[tuple[str, int | str]] = [
    ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
    ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
    ("grpc.keepalive_time_ms", KEEPALIVE_MS),
    ("grpc.keepalive_timeout_ms", KEEPALIVE_TIMEOUT_MS),
    ("grpc.http2.min_time_between_pings_ms", KEEPALIVE_MS),
    ("grpc.http2.ping_timeout_ms", KEEPALIVE_TIMEOUT_MS),
    ("grpc.keepalive_permit_without_calls", 1),
    ("grpc.http2.max_pings_without_data", 0),
    # Reconnect quickly after a peer restarts; the caller adds its own back-off.
    ("grpc.initial_reconnect_backoff_ms", 100),
    ("grpc.max_reconnect_backoff_ms", 2_000),
    # Despite its name, gRPC core reads this as the shortest time a connection
    # attempt is given (its handshakes included) before it is abandoned: at
    # 100 ms a TLS handshake over a link with seconds of latency never
    # completed (the stale-request test's 4 s uplink). 20 s is gRPC's default.
    ("grpc.min_reconnect_backoff_ms", 20_000),
    ("grpc.enable_retries", 0),
]

SERVER_OPTIONS: list[tuple[str, int | str]] = [
    ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
    ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
    ("grpc.keepalive_time_ms", KEEPALIVE_MS),
    ("grpc.keepalive_timeout_ms", KEEPALIVE_TIMEOUT_MS),
    ("grpc.http2.min_time_between_pings_ms", KEEPALIVE_MS),
    ("grpc.http2.ping_timeout_ms", KEEPALIVE_TIMEOUT_MS),
    ("grpc.keepalive_permit_without_calls", 1),
    ("grpc.http2.min_ping_interval_without_data_ms", 5_000),
    ("grpc.http2.max_pings_without_data", 0),
    ("grpc.so_reuseport", 0),
]


def _secure_options(tls: Tls | None, peer: Identity | None) -> list[tuple[str, int | str]]:
    if tls is None:
        return CHANNEL_OPTIONS
    if peer is None:
        raise ValueError("a TLS channel names the identity it expects to reach")
    # The peer's certificate is checked against who we mean to reach, not the
    # address: a link emulator or a published port may stand between (tls.py).
    return [*CHANNEL_OPTIONS, ("grpc.ssl_target_name_override", peer.dns_name)]


# gRPC lets a channel with no call for 30 minutes go IDLE (its connection closed).
KEEP_IDLE_OPTIONS: list[tuple[str, int | str]] = [("grpc.client_idle_timeout_ms", 2**31 - 1)]


def aio_channel(
    address: str, tls: Tls | None = None, peer: Identity | None = None, keep_idle: bool = False
) -> grpc.aio.Channel:
    """An asyncio channel to ``host:port`` with the project's options: mutual TLS as
    ``tls``'s identity to ``peer`` (whose certificate is checked), else insecure.
    ``keep_idle``: its connection stays open however long no call uses it (a channel
    connected in advance, ``controller.drone_link.WarmChannel``)."""
    options = _secure_options(tls, peer) + (KEEP_IDLE_OPTIONS if keep_idle else [])
    if tls is None:
        return grpc.aio.insecure_channel(address, options=options)
    return grpc.aio.secure_channel(address, tls.channel_credentials(), options=options)


def sync_channel(
    address: str, tls: Tls | None = None, peer: Identity | None = None
) -> grpc.Channel:
    """A blocking channel to ``host:port``, as ``aio_channel``."""
    options = _secure_options(tls, peer)
    if tls is None:
        return grpc.insecure_channel(address, options=options)
    return grpc.secure_channel(address, tls.channel_credentials(), options=options)

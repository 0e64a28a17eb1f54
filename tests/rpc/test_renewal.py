"""Issue 33, item 4: short-lived station certificates renewed from the issuer.

Across real processes: a `baton station` started with `--renew-from` beside a
`baton certs issuer` renews its 10 s certificate halfway through, again and
again, without a restart; once the certificate it started with has expired, a
new connection to it still succeeds (it presents the renewed one). Revoked, it
renews nothing: the issuer refuses it and the station says so. The pure corners
(when to ask, what reply to take) are unit tests below."""

from __future__ import annotations

import datetime
import json
import time
from pathlib import Path

import grpc
import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec
from waiting import eventually

from baton.certs.issuer import IssuerService, public_key_of
from baton.certs.make import init, revoke, serial_of
from baton.certs.renewal import Validity, checked, next_ask
from baton.rpc.channels import aio_channel
from baton.rpc.errors import StatusError
from baton.rpc.tls import OPERATOR, Identity, Tls
from baton.testbed.fleet import start_stations
from baton.testbed.supervisor import Supervisor
from baton.v1 import issuer_pb2, station_pb2, station_pb2_grpc

STATION = Identity.controller(1)
LIFETIME_S = 10.0


def _events(log: Path) -> list[dict[str, object]]:
    return [json.loads(line) for line in log.read_text().splitlines() if line.startswith("{")]


async def test_a_station_renews_its_certificate_and_a_revoked_one_renews_nothing(
    tmp_path: Path,
) -> None:
    certs = tmp_path / "certs"
    init(certs, [STATION, OPERATOR])
    crt = certs / f"{STATION.name}.crt"
    async with Supervisor(tmp_path / "parts") as supervisor:
        stations = await start_stations(supervisor, [1], certs, cert_lifetime_s=LIFETIME_S)
        process = supervisor.parts["station-1"].process
        assert process is not None
        started = Validity.of(crt.read_bytes())
        assert started.not_after - time.time() <= LIFETIME_S
        serials = [started.serial]

        def renewed_twice() -> bool:
            serial = serial_of(crt)
            if serial is not None and serial != serials[-1]:
                serials.append(serial)
            return len(serials) >= 3

        await eventually(renewed_twice, "two renewals of the station's certificate", 4 * LIFETIME_S)
        await eventually(
            lambda: time.time() > started.not_after + 0.5,
            "the certificate the station started with expired",
            2 * LIFETIME_S,
        )
        # A new connection: the station presents its renewed certificate (the operator's
        # channel checks the server's), and the station never restarted.
        operator = Tls.load(certs, OPERATOR)
        async with aio_channel(stations[1].address, operator, STATION) as channel:
            status = await station_pb2_grpc.StationStub(channel).GetStation(
                station_pb2.GetStationRequest(), timeout=10
            )
        assert status.id == 1
        assert supervisor.parts["station-1"].process is process and process.returncode is None
        log = supervisor.workdir / "station-1.log"
        renewals = [e for e in _events(log) if e.get("msg") == "certificate renewed"]
        assert len(renewals) >= 2, renewals

        # Revoked: the issuer refuses its next ask, and the station says why.
        current = serial_of(crt)
        assert current is not None
        revoke(certs, current)

        def refused() -> list[dict[str, object]]:
            return [
                e
                for e in _events(log)
                if str(e.get("msg", "")).startswith("certificate not renewed")
                and e.get("code") == "UNAUTHENTICATED"
                and "revoked" in str(e.get("reason", ""))
            ]

        await eventually(refused, "the issuer refused the revoked station", 4 * LIFETIME_S)
        assert serial_of(crt) == current


# -- the pure corners -------------------------------------------------------------


def test_the_next_ask_is_halfway_from_taking_and_backs_off_after_failures() -> None:
    backdated = Validity(1, not_before=970.0, not_after=1010.0)  # 30 s of clock skew
    assert next_ask(backdated, taken_at=1000.0, now=1000.0, failures=0) == 1005.0
    # A certificate held from before its start of validity: from its start.
    assert next_ask(Validity(1, 1000.0, 1100.0), 900.0, 900.0, 0) == 1050.0
    # After a failure: a back-off of 5 % of the span, at least 1 s, from now.
    assert next_ask(backdated, 1000.0, now=1006.0, failures=1) == 1007.0
    long = Validity(1, 0.0, 86400.0)
    assert next_ask(long, 0.0, now=50000.0, failures=3) == 50060.0  # at most 60 s


def _issued(folder: Path, identity: Identity, key: ec.EllipticCurvePrivateKey) -> bytes:
    service = IssuerService(folder, datetime.timedelta(seconds=LIFETIME_S))
    cert = service.renewed(identity, key.public_key(), datetime.datetime.now(datetime.UTC))
    return cert.public_bytes(serialization.Encoding.PEM)


def test_a_reply_is_taken_only_from_our_ca_for_us_over_our_key_and_valid_now(
    tmp_path: Path,
) -> None:
    folder, other = tmp_path / "certs", tmp_path / "other"
    init(folder, [STATION])
    init(other, [STATION])
    ca = (folder / "ca.crt").read_bytes()
    key, wrong_key = (
        ec.generate_private_key(ec.SECP256R1()),
        ec.generate_private_key(ec.SECP256R1()),
    )
    now = time.time()

    def reply(pem: bytes) -> issuer_pb2.RenewReply:
        return issuer_pb2.RenewReply(certificate_pem=pem)

    good = _issued(folder, STATION, key)
    assert not isinstance(checked(reply(good), ca, STATION, key.public_key(), now), str)
    cases = {
        "signed by our CA": reply(_issued(other, STATION, key)),
        "names ['spiffe://baton/controller/2']": reply(
            _issued(folder, Identity.controller(2), key)
        ),
        "not over the key we sent": reply(_issued(folder, STATION, wrong_key)),
        "not a certificate": reply(b"garbage"),
    }
    for why, bad in cases.items():
        problem = checked(bad, ca, STATION, key.public_key(), now)
        assert isinstance(problem, str) and why in problem, (why, problem)
    late = checked(reply(good), ca, STATION, key.public_key(), now + 2 * LIFETIME_S)
    assert isinstance(late, str) and "not valid now" in late


def test_a_renewal_of_anything_but_a_p256_public_key_is_invalid() -> None:
    for pem in (b"", b"-----BEGIN PUBLIC KEY-----\nxx\n-----END PUBLIC KEY-----\n"):
        with pytest.raises(StatusError) as refused:
            public_key_of(pem)
        assert refused.value.code is grpc.StatusCode.INVALID_ARGUMENT
        assert "public_key_pem" in refused.value.message
    p384 = ec.generate_private_key(ec.SECP384R1()).public_key()
    pem = p384.public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )
    with pytest.raises(StatusError, match="P-256"):
        public_key_of(pem)


def test_the_issuer_renews_one_lineage_per_part_and_keeps_it_across_restarts(
    tmp_path: Path,
) -> None:
    folder = tmp_path / "certs"
    init(folder, [STATION])
    in_folder = serial_of(folder / f"{STATION.name}.crt")
    service = IssuerService(folder, datetime.timedelta(seconds=LIFETIME_S))
    assert service.lineage(STATION, 12345) is None  # nothing recorded yet: any holder
    service.newest[STATION.name] = 777
    assert service.lineage(STATION, 777) is None
    assert service.lineage(STATION, in_folder) is None  # rotated by hand in the folder
    refused = service.lineage(STATION, 12345)
    assert refused is not None and refused.code is grpc.StatusCode.PERMISSION_DENIED
    assert "3039 is not the newest this issuer gave it (309)" in refused.message
    # Recorded in the folder: a restarted issuer keeps the lineage.
    (folder / "issued.json").write_text(json.dumps({STATION.name: "309"}))
    assert IssuerService(folder, datetime.timedelta(seconds=10)).lineage(STATION, 12345)
    (folder / "issued.json").write_text("[1, 2]")
    with pytest.raises(OSError, match=r"issued.json: not the issuer's record"):
        IssuerService(folder, datetime.timedelta(seconds=10))

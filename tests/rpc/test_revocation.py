"""Issue 33, item 4 across real processes: a running station's certificate rotated
with `baton certs rotate` and the old one revoked with `baton certs revoke` is
refused on every part at its next call and its live streams are cut, without
re-keying or restarting anyone, and a log message signed with its old key is no
longer believed, whoever relays it; the station, never restarted, reconnects with
its new certificate and the mission completes exactly once."""

from __future__ import annotations

import asyncio
import shutil
import time
from dataclasses import replace
from pathlib import Path

import grpc
import pytest
from grpc_health.v1 import health_pb2
from helpers.forgery import send
from helpers.missions import assert_mission_promises, log_events, three_on_fast_links, until_served
from waiting import eventually

from baton.authenticity import Signer
from baton.certs.make import init, revoke
from baton.cli import main
from baton.rpc.admission import RECHECK_S
from baton.rpc.channels import aio_channel
from baton.rpc.revocation import REVOKED_CRL, RevocationList
from baton.rpc.tls import CA_CERT, DRONE, OPERATOR, Identity, Tls
from baton.testbed.local import LocalTestbed
from baton.v1 import drone_pb2, drone_pb2_grpc, ring_pb2, ring_pb2_grpc

STATION = Identity.controller(2)


async def stream_end(call: grpc.aio.UnaryStreamCall, timeout_s: float) -> grpc.aio.AioRpcError:
    """The error a live stream ends with within ``timeout_s`` (fails the test otherwise)."""
    async with asyncio.timeout(timeout_s):
        while True:
            try:
                await call.read()
            except grpc.aio.AioRpcError as err:
                return err


async def test_a_revoked_certificate_is_refused_and_its_streams_cut(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plan = three_on_fast_links()
    async with LocalTestbed(plan, tmp_path) as testbed:
        config = testbed.config
        assert config is not None and testbed.drone_stub is not None
        await until_served(testbed, 5)
        certs = config.tls.certs
        # A copy of the station's files as they are now (a thief's): a Tls read from
        # the folder would present whatever the folder holds later.
        old = replace(Tls.load(certs, STATION), folder=None)

        # Live streams held with the station's certificate, on the drone and on a
        # controller's ring port: the health service's Watch.
        channels = [
            aio_channel(config.drone.address, old, DRONE),
            aio_channel(config.controller(0).address, old, Identity.controller(0)),
        ]
        watches = []
        for channel in channels:
            watch = channel.unary_stream(
                "/grpc.health.v1.Health/Watch",
                request_serializer=health_pb2.HealthCheckRequest.SerializeToString,
                response_deserializer=health_pb2.HealthCheckResponse.FromString,
            )(health_pb2.HealthCheckRequest())
            first = await watch.read()
            assert isinstance(first, health_pb2.HealthCheckResponse)
            watches.append(watch)

        # Rotated: the old certificate is still good until it is revoked.
        station = testbed.supervisor.parts[STATION.name].process
        assert station is not None
        assert main(["certs", "rotate", str(certs), STATION.name, "--hours", "1"]) == 0
        printed = capsys.readouterr().out
        replaced = printed.split("it replaces serial ")[1].split(",")[0]
        revoked_at = time.monotonic()
        assert main(["certs", "revoke", str(certs), replaced]) == 0
        assert f"serial {replaced} revoked" in capsys.readouterr().out

        for watch in watches:
            ended = await stream_end(watch, 4 * RECHECK_S + 5)
            assert ended.code() is grpc.StatusCode.UNAUTHENTICATED, ended.details()
            assert "revoked" in (ended.details() or "")
        with capsys.disabled():
            print(f"streams of the revoked certificate cut {time.monotonic() - revoked_at:.2f} s")
        for channel in channels:
            await channel.close()
        # Its next connection: refused on every part it calls, whatever the call.
        async with aio_channel(config.drone.address, old, DRONE) as channel:
            with pytest.raises(grpc.aio.AioRpcError) as refused:
                await drone_pb2_grpc.DroneStub(channel).GetStatus(
                    drone_pb2.GetDroneStatusRequest(), timeout=10
                )
        assert refused.value.code() is grpc.StatusCode.UNAUTHENTICATED
        assert f"serial {replaced}" in (refused.value.details() or "")
        # A log message sealed with the revoked key (the thief's), relayed by another
        # station, once the replica it reaches has read the list: refused, named.
        replica = Identity.controller(1)
        relay = Tls.load(certs, Identity.controller(0))

        async def list_read() -> bool:
            async with aio_channel(config.controller(1).address, old, replica) as channel:
                try:
                    await ring_pb2_grpc.ControllerRingStub(channel).GetStatus(
                        ring_pb2.GetControllerStatusRequest(), timeout=10
                    )
                except grpc.aio.AioRpcError as err:
                    return err.code() is grpc.StatusCode.UNAUTHENTICATED
            return False

        await eventually(list_read, "controller 1 read the revocation list", 4 * RECHECK_S + 5)
        forged = ring_pb2.LogMessage(origin=2, sender=2)
        address = config.controller(1).address
        await send(address, relay, 1, forged, True, Signer.from_pem(old.key).seal)
        async with aio_channel(address, relay, replica) as channel:
            seen = await ring_pb2_grpc.ControllerRingStub(channel).GetStatus(
                ring_pb2.GetControllerStatusRequest()
            )
        assert seen.refused_messages == 1, seen
        assert f"controller 2's revoked certificate (serial {replaced})" in seen.last_refused

        # The new certificate is taken, by parts never restarted nor re-keyed.
        new = Tls.load(certs, STATION)
        async with aio_channel(config.drone.address, new, DRONE) as channel:
            status = await drone_pb2_grpc.DroneStub(channel).GetStatus(
                drone_pb2.GetDroneStatusRequest(), timeout=10
            )
        assert status.controllers

        # The station's own streams held the old certificate too: they are cut, and
        # it connects again with the new one, never restarted.
        snapshot = await testbed.run_mission(240)
        assert testbed.supervisor.parts[STATION.name].process is station
        assert testbed.deaths == []
    assert_mission_promises(snapshot, plan)
    events = log_events(tmp_path, STATION.name)
    assert any("revoked" in str(event) for event in events), (
        "the station's own streams were not cut"
    )


def test_a_revocation_list_of_another_ca_is_not_believed(tmp_path: Path) -> None:
    """A list signed by another CA (or damaged) is refused with the file named, and
    the revocations read before it still hold."""
    ours, theirs = tmp_path / "ours", tmp_path / "theirs"
    init(ours, [STATION, OPERATOR])
    init(theirs, [STATION])
    station = Tls.load(ours, STATION)
    serial = revoke(ours, 0xBAD)
    assert serial == frozenset({0xBAD})
    revocations = RevocationList(ours / REVOKED_CRL, (ours / CA_CERT).read_bytes())
    assert revocations.refresh() is None and revocations.serials == {0xBAD}
    revoke(theirs, 0xF00)
    shutil.copy(theirs / REVOKED_CRL, ours / REVOKED_CRL)
    problem = revocations.refresh()
    assert problem is not None and str(ours / REVOKED_CRL) in problem
    assert "not signed by this folder's CA" in problem
    assert revocations.serials == {0xBAD}
    assert station.folder == ours


def test_revoke_names_what_it_cannot_revoke(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "c"
    init(folder, [STATION])
    assert main(["certs", "revoke", str(folder), "controller-7"]) == 2
    assert "controller-7.crt: no certificate" in capsys.readouterr().err
    assert main(["certs", "revoke", str(folder), "pilot"]) == 2
    assert "neither a part" in capsys.readouterr().err
    assert main(["certs", "revoke", str(folder), STATION.name]) == 0
    assert "1 in revoked.crl" in capsys.readouterr().out


def test_a_running_part_takes_a_rotated_certificate_only_with_its_own_key(
    tmp_path: Path,
) -> None:
    folder = tmp_path / "c"
    init(folder, [STATION])
    started = Tls.load(folder, STATION)
    assert started.current() is started
    key = (folder / f"{STATION.name}.key").read_bytes()
    assert main(["certs", "rotate", str(folder), STATION.name, "--hours", "2"]) == 0
    rotated = started.current()
    assert rotated.cert != started.cert and rotated.key != started.key
    assert rotated.ca == started.ca and rotated.folder == folder
    # Caught between the two files' writes: the new certificate, the old key.
    (folder / f"{STATION.name}.key").write_bytes(key)
    assert rotated.current() is rotated

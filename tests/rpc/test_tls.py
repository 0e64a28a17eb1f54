"""Mutual TLS through the one server and channel helper: identities from certificates,
and the certificates a server must refuse (a foreign CA, an expired one, none)."""

from __future__ import annotations

import datetime
from collections.abc import AsyncIterator
from pathlib import Path

import grpc
import pytest
from grpc_health.v1 import health_pb2
from pydantic import ValidationError

from baton.certs.make import init, issue, serial_of
from baton.cli import main
from baton.config import BatonConfig
from baton.controller.peer_keys import ring_keys
from baton.rpc.channels import aio_channel
from baton.rpc.server import BatonServer, generic
from baton.rpc.tls import DRONE, OPERATOR, Identity, Tls, TlsError, caller

CONTROLLER_1 = Identity.controller(1)
WHO = "/test.Who/Who"


@pytest.fixture
def certs(tmp_path: Path) -> Path:
    folder = tmp_path / "certs"
    init(folder, [CONTROLLER_1, DRONE, OPERATOR])
    return folder


@pytest.fixture
async def drone_server(certs: Path) -> AsyncIterator[tuple[BatonServer, list[str]]]:
    """A server with the drone's certificate whose one method answers who called."""
    callers: list[str] = []

    async def who(request: bytes, context: grpc.aio.ServicerContext) -> bytes:
        found = caller(context)
        callers.append(str(found))
        return str(found).encode()

    handler: grpc.RpcMethodHandler[bytes, bytes] = grpc.unary_unary_rpc_method_handler(who)
    who_is = generic(grpc.method_handlers_generic_handler("test.Who", {"Who": handler}))
    server = BatonServer("127.0.0.1:0", [who_is], tls=Tls.load(certs, DRONE))
    await server.start()
    yield server, callers
    await server.stop(0)


async def ask(channel: grpc.aio.Channel) -> str | grpc.StatusCode:
    """Who the server says called, or the status the call ended with."""
    async with channel:
        try:
            who: grpc.aio.UnaryUnaryMultiCallable[bytes, bytes] = channel.unary_unary(WHO)
            reply = await who(b"", timeout=5)
        except grpc.aio.AioRpcError as err:
            return err.code()
    assert isinstance(reply, bytes)
    return reply.decode()


async def test_the_server_knows_the_caller_from_its_certificate(
    certs: Path, drone_server: tuple[BatonServer, list[str]]
) -> None:
    server, _ = drone_server
    for identity in (CONTROLLER_1, OPERATOR):
        channel = aio_channel(server.address, Tls.load(certs, identity), DRONE)
        assert await ask(channel) == identity.uri


async def test_a_caller_refuses_a_server_that_is_not_the_one_it_means_to_reach(
    certs: Path, drone_server: tuple[BatonServer, list[str]]
) -> None:
    """The drone's port answered with a certificate that is not the controller's."""
    server, callers = drone_server
    channel = aio_channel(server.address, Tls.load(certs, OPERATOR), CONTROLLER_1)
    assert await ask(channel) is grpc.StatusCode.UNAVAILABLE
    assert callers == []


@pytest.mark.parametrize("how", ["foreign CA", "expired", "no certificate", "plaintext"])
async def test_a_server_refuses_callers_without_a_valid_certificate_of_its_ca(
    certs: Path, tmp_path: Path, drone_server: tuple[BatonServer, list[str]], how: str
) -> None:
    server, callers = drone_server
    if how == "foreign CA":
        foreign = tmp_path / "foreign"
        init(foreign, [CONTROLLER_1])
        # It trusts our CA (it could have stolen ca.crt) but its own was signed elsewhere.
        stolen = Tls.load(foreign, CONTROLLER_1)
        tls = Tls(CONTROLLER_1, Tls.load(certs, OPERATOR).ca, stolen.cert, stolen.key)
        channel = aio_channel(server.address, tls, DRONE)
    elif how == "expired":
        issue(
            certs,
            CONTROLLER_1,
            days=1,
            not_before=datetime.datetime.now(datetime.UTC) - datetime.timedelta(days=2),
        )
        channel = aio_channel(server.address, Tls.load(certs, CONTROLLER_1), DRONE)
    elif how == "no certificate":
        ca = Tls.load(certs, OPERATOR).ca
        channel = grpc.aio.secure_channel(
            server.address,
            grpc.ssl_channel_credentials(ca),
            options=[("grpc.ssl_target_name_override", DRONE.dns_name)],
        )
    else:
        channel = aio_channel(server.address)
    assert await ask(channel) is grpc.StatusCode.UNAVAILABLE
    assert callers == [], "the call reached the service"


def test_a_missing_certificate_names_the_file_and_the_fix(certs: Path) -> None:
    with pytest.raises(TlsError) as missing:
        Tls.load(certs, Identity.controller(7))
    message = str(missing.value)
    assert str(certs / "controller-7.crt") in message
    assert f"baton certs init {certs}" in message and "--insecure" in message


def test_identities_round_trip_through_their_uri() -> None:
    alpha = Identity.drone("alpha")
    for identity in (CONTROLLER_1, Identity.controller(0), DRONE, alpha, OPERATOR):
        assert Identity.from_uri(identity.uri) == identity
    assert (alpha.uri, alpha.name, alpha.dns_name) == (
        "spiffe://baton/drone/alpha",
        "drone-alpha",
        "drone-alpha.baton",
    )
    strangers = ("spiffe://baton/controller/01", "spiffe://baton/pilot", "https://x", "")
    for stranger in (*strangers, "spiffe://baton/drone/Alpha", "spiffe://baton/drone/a_b"):
        assert Identity.from_uri(stranger) is None
    with pytest.raises(ValueError):
        Identity("controller")
    for bad in ("Alpha", "a_b", "-a", "a" * 64):
        with pytest.raises(ValueError, match="one DNS label"):
            Identity.drone(bad)


async def test_a_fleets_drone_is_reached_only_with_its_own_certificate(
    tmp_path: Path, certs: Path
) -> None:
    """Each drone of a fleet has its own identity: a station that means to reach drone
    alpha refuses a server holding drone bravo's certificate (another drone of the same
    CA, a compromised one at alpha's address), and reaches alpha's."""
    alpha, bravo = Identity.drone("alpha"), Identity.drone("bravo")
    issue(certs, alpha)
    issue(certs, bravo)
    station = Tls.load(certs, CONTROLLER_1)
    for held, reached in ((bravo, False), (alpha, True)):
        server = BatonServer("127.0.0.1:0", [], tls=Tls.load(certs, held))
        await server.start()
        try:
            async with aio_channel(server.address, station, alpha) as channel:
                check = channel.unary_unary(
                    "/grpc.health.v1.Health/Check",
                    request_serializer=health_pb2.HealthCheckRequest.SerializeToString,
                    response_deserializer=health_pb2.HealthCheckResponse.FromString,
                )
                try:
                    await check(health_pb2.HealthCheckRequest(), timeout=5)
                    answered = True
                except grpc.aio.AioRpcError as err:
                    assert err.code() is grpc.StatusCode.UNAVAILABLE
                    answered = False
            assert answered is reached, held
        finally:
            await server.stop(0)
    # A mission names its drone (drone.name): its controllers check the drone's
    # replies against that drone's certificate, and no other.
    config = BatonConfig.model_validate(
        {
            "drone": {"name": "alpha"},
            "controllers": [{"id": 1, "address": "127.0.0.1:1"}],
            "tls": {"certs": str(certs)},
        }
    )
    assert config.drone_identity == alpha
    keys = ring_keys(config, station)
    assert keys.drone.serial == serial_of(certs / "drone-alpha.crt")
    with pytest.raises(ValidationError, match=r"drone\.name"):
        BatonConfig.model_validate(
            {"drone": {"name": "Alpha"}, "controllers": [{"id": 1, "address": "127.0.0.1:1"}]}
        )


def test_certs_init_for_a_fleet_gives_each_station_and_drone_its_own(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fleet = Path(__file__).parents[2] / "examples" / "fleet.yaml"
    folder = tmp_path / "c"
    assert main(["certs", "init", str(folder), "--fleet", str(fleet)]) == 0
    crts = sorted(p.stem for p in folder.glob("*.crt"))
    assert crts == sorted(
        ["ca", "controller-1", "controller-2", "controller-3", "drone-d1", "drone-d2", "operator"]
    )
    both = ["certs", "init", str(tmp_path / "d"), "--fleet", str(fleet), "--config", str(fleet)]
    assert main(both) == 2
    assert "--config or --fleet, not both" in capsys.readouterr().err
    assert main(["certs", "init", str(tmp_path / "e"), "--fleet", str(tmp_path / "none.yaml")]) == 2
    assert "none.yaml" in capsys.readouterr().err


def test_certs_init_writes_every_part_and_refuses_to_replace_a_ca(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "c"
    assert main(["certs", "init", str(folder), "--controllers", "0,2"]) == 0
    names = sorted(p.name for p in folder.iterdir())
    assert names == sorted(
        ["ca.crt", "ca.key"]
        + [
            f"{n}.{ext}"
            for n in ("controller-0", "controller-2", "drone", "operator")
            for ext in ("crt", "key")
        ]
    )
    assert (folder / "drone.key").stat().st_mode & 0o077 == 0
    assert main(["certs", "init", str(folder)]) == 1
    assert "a CA exists already" in capsys.readouterr().err
    assert main(["certs", "issue", str(folder), "controller-5"]) == 0
    assert (folder / "controller-5.crt").exists()

"""The contracts: generated stubs are fresh, and every server answers grpcurl."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

from baton.certs.make import ensure
from baton.config import parse_config
from baton.controller.app import ControllerApp
from baton.rpc.tls import DRONE, OPERATOR, Identity


def test_generated_stubs_match_the_protos() -> None:
    """`make proto`'s generator (tools/protogen.py, outside the package) finds nothing stale."""
    tool = Path(__file__).resolve().parents[1] / "tools" / "protogen.py"
    check = subprocess.run(
        [sys.executable, str(tool), "--check"], capture_output=True, text=True, timeout=120
    )
    assert check.returncode == 0, f"generated code is stale: run `make proto`\n{check.stderr}"


async def test_the_controller_serves_reflection_health_and_its_rpcs(
    grpcurl: Callable[..., str], tmp_path: Path
) -> None:
    """The ring port (mutual TLS, as docs/operating.md's grpcurl example) and the mission program's
    loopback port (plain, the drone API)."""
    certs = tmp_path / "certs"
    ensure(certs, [Identity.controller(0), DRONE, OPERATOR])  # drone.crt: its signatures
    config = parse_config(
        {"controllers": [{"id": 0, "address": "127.0.0.1:0"}], "tls": {"certs": str(certs)}}
    )
    app = ControllerApp(config, 0)
    await app.server.start()  # no node: nothing connects anywhere
    await app.mission_server.start()
    # What the drone's grant does at the mission's start (the effects, a drone
    # connection, are not carried out): master in epoch 1, ACTIVE.
    app.node.protocol.on_sync(0)
    app.node.protocol.on_granted(1)
    address, mission = app.server.address, app.mission_server.address
    tls = {"certs": certs, "peer": Identity.controller(0).dns_name}
    try:
        listed = set((await asyncio.to_thread(grpcurl, address, "list", **tls)).split())
        assert {
            "baton.v1.ControllerRing",
            "grpc.health.v1.Health",
            "grpc.reflection.v1alpha.ServerReflection",
        } <= listed
        assert "baton.v1.Mobility" not in listed  # the drone API is the program's port's
        described = await asyncio.to_thread(
            grpcurl, address, "describe", "baton.v1.ControllerRing", **tls
        )
        for rpc in ("LogRing", "GetStatus", "MissionDone"):
            assert f"rpc {rpc}" in described
        health = await asyncio.to_thread(
            grpcurl,
            "-d",
            '{"service": "baton.v1.ControllerRing"}',
            address,
            "grpc.health.v1.Health/Check",
            **tls,
        )
        assert json.loads(health) == {"status": "SERVING"}
        status = json.loads(
            await asyncio.to_thread(grpcurl, address, "baton.v1.ControllerRing/GetStatus", **tls)
        )
        assert (
            status["state"] == "CONTROLLER_STATE_ACTIVE"
            and status["master"] is True
            and status["epoch"] == "1"
        )
        assert status["mission_address"] == mission
        assert mission.startswith("127.0.0.1:")
        listed = set((await asyncio.to_thread(grpcurl, mission, "list")).split())
        assert {"baton.v1.Mobility", "baton.v1.Camera", "baton.v1.Clock"} <= listed
        # A drone-API call through the proxy: Clock.Now is answered by the controller.
        now = json.loads(await asyncio.to_thread(grpcurl, mission, "baton.v1.Clock/Now"))
        assert now["unix_time_s"] > 1.6e9  # grpcurl prints the proto field names
    finally:
        await app.mission_server.stop(0)
        await app.server.stop(0)

"""Malformed input at a controller's ring port, for a fixed, seeded budget (issue 11):
no crash, no hang, no change of state, every answer a defined status (tests/fuzzing.py).
The caller holds a valid controller certificate."""

from __future__ import annotations

import random
from pathlib import Path

import grpc
from fuzzing import INPUTS_PER_METHOD, SEED, UNHANDLED, answer, mutants

from baton.certs.make import ensure
from baton.config import parse_config
from baton.controller.app import ControllerApp
from baton.controller.ring import frames
from baton.rpc.channels import aio_channel
from baton.rpc.tls import DRONE, OPERATOR, Identity, Tls
from baton.v1 import ring_pb2

CONTROLLERS = (0, 1, 2)


def _controller_1(tmp_path: Path) -> tuple[ControllerApp, Path]:
    """Controller 1 of a three-controller ring under mutual TLS (not started), and the
    certificates' folder."""
    certs = tmp_path / "certs"
    ensure(certs, [*(Identity.controller(cid) for cid in CONTROLLERS), DRONE, OPERATOR])
    config = parse_config(
        {
            "controllers": [{"id": c, "address": "127.0.0.1:0"} for c in CONTROLLERS],
            "tls": {"certs": str(certs)},
        }
    )
    return ControllerApp(config, 1), certs


async def test_malformed_requests_to_a_controllers_ring_port(tmp_path: Path) -> None:
    app, certs = _controller_1(tmp_path)
    await app.server.start()  # the ring port only: its node is not started
    rng = random.Random(SEED)
    try:
        protocol = app.node.protocol
        before = (protocol.lognr, protocol.reqnr, protocol.state)
        valid = {
            ("GetStatus", False): [ring_pb2.GetControllerStatusRequest().SerializeToString()],
            ("MissionDone", False): [
                ring_pb2.MissionDoneRequest(failed=True, error="x").SerializeToString()
            ],
        }
        as_peer = Tls.load(certs, Identity.controller(0))
        async with aio_channel(app.server.address, as_peer, Identity.controller(1)) as channel:
            for (name, stream), examples in valid.items():
                method = f"/baton.v1.ControllerRing/{name}"
                for raw in mutants(examples, rng, INPUTS_PER_METHOD):
                    code = await answer(channel, method, raw, stream)
                    assert code not in UNHANDLED, (method, raw.hex(), code)
            assert await answer(channel, "/baton.v1.ControllerRing/GetStatus", b"", False) is (
                grpc.StatusCode.OK
            )
        assert (protocol.lognr, protocol.reqnr, protocol.state) == before
        assert app.node.program.mission == ring_pb2.MISSION_STATE_NONE
    finally:
        await app.server.stop(0)


async def test_malformed_log_frames_at_a_controllers_ring_port(tmp_path: Path) -> None:
    """Frames of a log message from controller 0, mutated. A mutant may still be a valid
    message of an authorized peer, so the oracle is the answer and the server's health,
    not its state."""
    app, certs = _controller_1(tmp_path)
    await app.server.start()
    rng = random.Random(SEED)
    entry = ring_pb2.LogEntry(reqnr=1, method="/baton.v1.Mobility/GetPosition", reply=b"x" * 40)
    message = ring_pb2.LogMessage(lognr=1, origin=0, entries=[entry], sender=0)
    valid = [frame.SerializeToString() for frame in frames(message, 0)]
    valid.append(ring_pb2.LogFrame(sync=True, holds_lognr=3, from_id=0).SerializeToString())
    seen = set()
    try:
        as_peer = Tls.load(certs, Identity.controller(0))
        async with aio_channel(app.server.address, as_peer, Identity.controller(1)) as channel:
            ring: grpc.aio.StreamStreamMultiCallable[bytes, bytes]
            ring = channel.stream_stream("/baton.v1.ControllerRing/LogRing")
            for raw in mutants(valid, rng, INPUTS_PER_METHOD):
                call = ring(iter([raw]), timeout=2)
                try:
                    async for _ in call:
                        pass
                    code = grpc.StatusCode.OK
                except grpc.aio.AioRpcError as err:
                    code = err.code()
                assert code not in UNHANDLED, (raw.hex(), code)
                seen.add(code)
            assert await answer(channel, "/baton.v1.ControllerRing/GetStatus", b"", False) is (
                grpc.StatusCode.OK
            )
    finally:
        await app.server.stop(0)
    assert grpc.StatusCode.INVALID_ARGUMENT in seen

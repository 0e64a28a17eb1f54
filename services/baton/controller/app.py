"""Runs one controller process: its gRPC server, its node and its mission program."""

from __future__ import annotations

import asyncio
import datetime
import os
import secrets
import sys
from pathlib import Path

from baton.authenticity import AuthenticityError, ReplyVerifier
from baton.config import BatonConfig
from baton.controller.node import ControllerNode
from baton.controller.service import ControllerRingService, mission_port, ring_receiver
from baton.lifecycle import announce, run_until_signalled
from baton.rpc.methods import service_full_name
from baton.rpc.mission import MISSION_TOKEN_ENV
from baton.rpc.server import BatonServer, servicer
from baton.rpc.tls import DRONE, INSECURE_WARNING, Identity, Tls, TlsError
from baton.v1 import ring_pb2_grpc

# How long a mission program has to end after SIGTERM before it is killed.
MISSION_STOP_GRACE_S = 2.0


def drone_verifier(certs: Path, tls: Tls) -> ReplyVerifier:
    """The drone's signature check, from ``drone.crt`` in the certificate folder checked
    against the mission's CA now; TlsError naming the file and the fix otherwise."""
    pem = Tls.read_certificate(certs, DRONE)
    try:
        return ReplyVerifier.from_pem(pem, tls.ca, datetime.datetime.now(datetime.UTC))
    except (AuthenticityError, ValueError) as exc:
        raise TlsError(
            f"{certs / (DRONE.name + '.crt')}: {exc}; make the drone's certificate "
            f"with `baton certs issue {certs} drone` and copy drone.crt to every controller"
        ) from None


class ControllerApp:
    """A controller's server, node and (optional) mission program subprocess."""

    def __init__(
        self,
        config: BatonConfig,
        cid: int,
        mission: str | None = None,
        mission_args: list[str] | None = None,
        log_file: str | None = None,
        mission_python: str | None = None,
    ) -> None:
        self.config = config
        tls = config.tls_for(Identity.controller(cid))
        self.node = ControllerNode(config, cid, log_file, tls)
        if tls is None:
            self.node.log.warning(INSECURE_WARNING)
        else:
            self.node.core.verifier = drone_verifier(config.tls.certs, tls)
        # The mission program's token (rpc/mission.py): given in the environment
        # (a program started by hand), else made up for the program started here.
        self.token = os.environ.get(MISSION_TOKEN_ENV) or (
            secrets.token_urlsafe(18) if mission else None
        )
        if self.token is None:
            self.node.log.warning(
                "no mission token: anyone who reaches this controller can call the drone API "
                f"through it (set {MISSION_TOKEN_ENV} here and for the mission program)"
            )
        # Two ports: the ring's (log frames, status), with mutual TLS, and the
        # mission program's on loopback (the drone API), tied to it by the token.
        ring = service_full_name("ControllerRing")
        add_ring = ring_pb2_grpc.add_ControllerRingServicer_to_server
        self.receiver = ring_receiver(self.node)
        peers = ControllerRingService(self.node, self.token, self.receiver, tls is not None)
        self.server = BatonServer(
            config.controller(cid).address, [servicer(ring, add_ring, peers)], tls=tls
        )
        self.mission_server = BatonServer(
            config.controller(cid).mission_address, mission_port(self.node, self.token)
        )
        self.node.mission_address = self.mission_server.address  # bound already
        self.mission = mission
        self.mission_args = mission_args or []
        # The interpreter that runs the program: this one, or a virtualenv of the
        # mission's own with only baton-sdk in it (clients/pyproject.toml). That one
        # runs with -E: a PYTHONPATH set for baton itself must not put the services'
        # tree (or another SDK) in front of what the virtualenv holds.
        self.mission_python = [mission_python, "-E"] if mission_python else [sys.executable]
        self.mission_process: asyncio.subprocess.Process | None = None
        self._watcher: asyncio.Task[None] | None = None
        self.node.on_rejoin = self.rejoin
        self.node.on_gap = self.receiver.drop_streams

    async def start(self) -> None:
        """Serves, starts the protocol, and launches the mission program if there is one."""
        await self.server.start()
        await self.mission_server.start()
        await self.node.start()
        await self._launch()

    async def rejoin(self) -> None:
        """After a takeover fenced us: the program stops, the node resets, the program restarts.

        The program had run ahead of the ring on replies that the new master
        logs in messages of its own: it replays them from the ring instead.
        """
        await self._stop_mission()
        await self.node.reset()
        self.receiver.drop_streams()
        await self._launch()

    async def _stop_mission(self) -> None:
        if self._watcher is not None:
            self._watcher.cancel()
            self._watcher = None
        process = self.mission_process
        if process is not None and process.returncode is None:
            process.terminate()
            try:
                await asyncio.wait_for(process.wait(), MISSION_STOP_GRACE_S)
            except TimeoutError:
                process.kill()
                await process.wait()

    async def _launch(self) -> None:
        if self.mission:
            self.mission_process = await asyncio.create_subprocess_exec(
                *self.mission_python,
                "-m",
                "baton.sdk.run",
                "--die-with-parent",
                str(os.getpid()),
                self.mission,
                self.mission_server.address,
                *self.mission_args,
                env={**os.environ, MISSION_TOKEN_ENV: self.token or ""},
            )
            self._watcher = asyncio.create_task(self._watch_mission(self.mission_process))

    async def _watch_mission(self, process: asyncio.subprocess.Process) -> None:
        code = await process.wait()
        error = "" if code == 0 else f"mission program exited with code {code}"
        await self.node.mission_done(failed=code != 0, error=error)

    async def stop(self) -> None:
        """Stops the mission program, the node and the server."""
        await self._stop_mission()
        await self.node.stop()
        await self.mission_server.stop()
        await self.server.stop()


async def serve(
    config: BatonConfig,
    cid: int,
    mission: str | None,
    mission_args: list[str],
    address_file: str | None,
    log_file: str | None = None,
    mission_python: str | None = None,
) -> int:
    """Runs a controller until SIGTERM or SIGINT."""
    app = ControllerApp(config, cid, mission, mission_args, log_file, mission_python)

    async def main(stop: asyncio.Event) -> int:
        await app.start()
        address = app.server.address
        listening = {"id": cid, "address": address, "mission_address": app.mission_server.address}
        announce(address_file, [address], listening)
        await stop.wait()
        await app.stop()
        return 0

    return await run_until_signalled(main)

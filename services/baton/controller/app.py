"""Runs one controller process: its gRPC server, its node and its mission program."""

from __future__ import annotations

import asyncio
import os
import secrets
import sys
from collections.abc import Awaitable, Callable

from baton.authenticity import Signer
from baton.config import BatonConfig
from baton.controller.node import ControllerNode
from baton.controller.peer_keys import PeerKeys
from baton.controller.service import ControllerRingService, mission_port, ring_receiver
from baton.lifecycle import announce, run_until_signalled
from baton.rpc.methods import service_full_name
from baton.rpc.mission import MISSION_TOKEN_ENV
from baton.rpc.ports import mission_policy, ring_policy
from baton.rpc.server import BatonServer, servicer
from baton.rpc.tls import INSECURE_WARNING, Identity
from baton.v1 import ring_pb2_grpc

# How long a mission program has to end after SIGTERM before it is killed.
MISSION_STOP_GRACE_S = 2.0
# The program's port pings its program as seldom as gRPC does by default (every two
# hours), not every 10 s with 5 s for the answer as a port pings a peer that may have
# gone silent: the program's end is its process's (``_watch_mission``), and a
# program stopped for a while (SIGSTOP, a debugger, a core it waits for) must find
# its stream and its call where it left them when it goes on.
PROGRAM_KEEPALIVE_S = (2 * 3600.0, 20.0)


class ControllerSession:
    """A controller's node, its mission program's port and (optional) mission program
    subprocess: everything of one mission's controller but the ring's port, which is
    its own (``ControllerApp``) or a station's, shared by many missions
    (baton/station/), which serves ``ring_servicer``."""

    def __init__(
        self,
        config: BatonConfig,
        cid: int,
        mission: str | None = None,
        mission_args: list[str] | None = None,
        log_file: str | None = None,
        mission_python: str | None = None,
        token: str | None = None,
    ) -> None:
        """``token``: the mission program's (rpc/mission.py); by default the one in the
        environment (a program started by hand), else one made up here."""
        self.config = config
        tls = config.tls_for(Identity.controller(cid))
        self.node = ControllerNode(config, cid, log_file, tls)
        if tls is None:
            self.node.log.warning(INSECURE_WARNING)
        else:
            self.peer_keys = PeerKeys(config, tls, self.node.log.warning)
            self.node.core.keys = self.peer_keys.keys
            self.node.core.protocol.seal = Signer.from_pem(tls.key).seal
        self.token = (
            token
            or os.environ.get(MISSION_TOKEN_ENV)
            or (secrets.token_urlsafe(18) if mission else None)
        )
        if self.token is None:
            self.node.log.warning(
                "no mission token: anyone who reaches this controller can call the drone API "
                f"through it (set {MISSION_TOKEN_ENV} here and for the mission program)"
            )
        # Two ports: the ring's (log frames, status), with mutual TLS, and the
        # mission program's on loopback (the drone API), tied to it by the token.
        # The ring's is ControllerApp's, or a station's shared by its missions.
        self.receiver = ring_receiver(self.node)
        self.ring_servicer = ControllerRingService(
            self.node, self.token, self.receiver, tls is not None
        )
        self.mission_server = BatonServer(
            config.controller(cid).mission_address,
            mission_port(self.node, self.token),
            keepalive=PROGRAM_KEEPALIVE_S,
            policy=mission_policy(),
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
        # Called with its exit code when the program ends on its own (not stopped).
        self.on_program_end: Callable[[int], Awaitable[None]] | None = None
        self.node.on_rejoin = self.rejoin
        self.node.on_gap = self.receiver.drop_streams

    def keys_refresh(self, revoked: frozenset[int]) -> None:
        """The ring's port re-read the revocation list (``Gate.on_refresh``): the log
        message keys follow it and the certificate folder (``PeerKeys``), those of the
        core serving now. Nothing on an insecure ring."""
        if self.node.tls is None:
            return
        if self.peer_keys.refresh(revoked):
            self.node.core.keys = self.peer_keys.keys
            self.node.log.info(
                "log message keys re-read", revoked=sorted(f"{s:x}" for s in revoked)
            )
        seal = self.peer_keys.seal()
        if seal is not None:
            self.node.core.protocol.seal = seal
            self.node.log.info("sealing with the rotated key")

    async def start(self) -> None:
        """Serves the program's port, starts the protocol, and launches the mission
        program if there is one."""
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
        await self.node.program.mission_done(failed=code != 0, error=error)
        if self.on_program_end is not None:
            await self.on_program_end(code)

    async def stop(self) -> None:
        """Stops the mission program, the node and the program's port."""
        await self._stop_mission()
        await self.node.stop()
        await self.mission_server.stop()


class ControllerApp(ControllerSession):
    """A controller process's session and its own ring port (mutual TLS: the ring's
    controllers only)."""

    def __init__(
        self,
        config: BatonConfig,
        cid: int,
        mission: str | None = None,
        mission_args: list[str] | None = None,
        log_file: str | None = None,
        mission_python: str | None = None,
    ) -> None:
        super().__init__(config, cid, mission, mission_args, log_file, mission_python)
        self.server = BatonServer(
            config.controller(cid).address,
            [
                servicer(
                    service_full_name("ControllerRing"),
                    ring_pb2_grpc.add_ControllerRingServicer_to_server,
                    self.ring_servicer,
                )
            ],
            tls=self.node.tls,
            policy=ring_policy(config.ring_order, config.ring.frame_bytes),
        )
        self.server.gate.on_refresh = self.keys_refresh

    async def start(self) -> None:
        """Serves the ring's port, then starts the session."""
        await self.server.start()
        await super().start()

    async def stop(self) -> None:
        """Stops the session, then the ring's port."""
        await super().stop()
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

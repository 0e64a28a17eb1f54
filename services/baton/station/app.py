"""``baton station``: one process, one port and one identity per edge node, hosting
a controller session per mission whose ring holds it.

Each session is a ``ControllerSession`` (controller/app.py) of its own: its
node, log, history file (``STATE_DIR/missions/ID/history.sqlite``), mission
program process and program port. The station's port serves every session's
ControllerRing through one dispatcher (router.py) and the Station service to
the operator, who starts the sessions admission decided and stops them on
cancel. A session whose program fails is reported (GetStation) and ended once
its log reached its successor (or after ``FAILED_FLUSH_S``): the station and
its other sessions go on. A session that cannot start, and one stopped, leave
nothing on the station.
"""

from __future__ import annotations

import asyncio
import contextlib
import secrets
import shutil
from dataclasses import dataclass
from pathlib import Path

import grpc

from baton.config import TlsConfig
from baton.controller.app import ControllerSession
from baton.controller.service import controller_status
from baton.lifecycle import announce, run_until_signalled
from baton.logs import get_logger
from baton.rpc.errors import StatusError, abort_with
from baton.rpc.ports import station_policy
from baton.rpc.server import BatonServer, generic, servicer
from baton.rpc.tls import INSECURE_WARNING, Identity, Tls, TlsError
from baton.station.router import RING_SERVICE, Handlers, MissionRouter, ring_handlers
from baton.station.rules import invalid, mission_config, route
from baton.tasks import TaskSet
from baton.v1 import station_pb2, station_pb2_grpc

# How long a session whose program failed keeps serving the ring for its last log
# message to reach its successor, at most, before it is ended.
FAILED_FLUSH_S = 10.0
FLUSH_POLL_S = 0.1
HISTORY_FILE = "history.sqlite"


@dataclass
class Hosted:
    """One mission's session on the station, while it hosts it."""

    mission_id: str
    folder: Path
    session: ControllerSession
    handlers: Handlers
    state: station_pb2.SessionState.ValueType = station_pb2.SESSION_STATE_HOSTING
    error: str = ""
    # Ending it after its program failed (``StationApp._end_failed``), and its stop.
    ending: asyncio.Task[None] | None = None
    stopping: asyncio.Future[None] | None = None


class StationApp:
    """A station's port and its sessions."""

    def __init__(
        self,
        station_id: int,
        address: str,
        tls: TlsConfig,
        state_dir: Path,
        mission_python: str | None = None,
    ) -> None:
        self.id = station_id
        self.tls_config = tls
        self.state_dir = state_dir
        self.mission_python = mission_python
        self.log = get_logger("station").bind(station=station_id)
        own = None if tls.insecure else Tls.load(tls.certs, Identity.controller(station_id))
        if own is None:
            self.log.warning(INSECURE_WARNING)
        self.hosted: dict[str, Hosted] = {}
        self._starting: set[str] = set()
        self._tasks = TaskSet()
        router = MissionRouter(station_id, self._routable)
        self.server = BatonServer(
            address,
            [
                generic(router, RING_SERVICE),
                servicer(
                    "baton.v1.Station",
                    station_pb2_grpc.add_StationServicer_to_server,
                    StationService(self),
                ),
            ],
            tls=own,
            policy=station_policy(),
        )
        self.server.gate.on_refresh = self._keys_refresh

    def _keys_refresh(self, revoked: frozenset[int]) -> None:
        """The port re-read the revocation list: every session's log message keys follow
        it (``ControllerSession.keys_refresh``)."""
        for hosted in self.hosted.values():
            hosted.session.keys_refresh(revoked)

    def _routable(self) -> dict[str, Handlers]:
        """The sessions that serve the ring now: hosting, not failed and ended."""
        return {
            mid: h.handlers
            for mid, h in self.hosted.items()
            if h.state == station_pb2.SESSION_STATE_HOSTING
        }

    def folder(self, mission_id: str) -> Path:
        return self.state_dir / "missions" / mission_id

    async def start_mission(self, request: station_pb2.StartMissionRequest) -> Hosted:
        """Starts a mission's session; StatusError says why not, with nothing left."""
        mid = request.mission_id
        taken = {**self.hosted, **dict.fromkeys(self._starting)}
        config = mission_config(
            mid, request.config, request.program, self.id, taken, self.tls_config
        )
        if isinstance(config, StatusError):
            raise config
        if not Path(request.program).is_file():
            raise invalid("program", f"no file {request.program} on station {self.id}")
        self._starting.add(mid)
        folder = self.folder(mid)
        # A folder left by this station's earlier run is the same mission's (ids are not
        # reused): its session starts from the history file, as a restarted controller.
        made = not folder.exists()
        session: ControllerSession | None = None
        try:
            folder.mkdir(parents=True, exist_ok=True)
            session = ControllerSession(
                config,
                self.id,
                request.program,
                list(request.args),
                str(folder / HISTORY_FILE),
                self.mission_python,
                token=secrets.token_urlsafe(18),
            )
            hosted = Hosted(mid, folder, session, ring_handlers(session.ring_servicer))
            session.on_program_end = lambda code: self._program_ended(hosted, code)
            await session.start()
        except (OSError, TlsError, ValueError) as exc:
            await self._discard(session, folder if made else None)
            left = "nothing of it is left here" if made else f"its earlier {folder} is kept"
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"StartMission: mission {mid} did not start on station {self.id}: {exc}; {left}",
            ) from None
        except BaseException:
            await self._discard(session, folder if made else None)
            raise
        finally:
            self._starting.discard(mid)
        self.hosted[mid] = hosted
        self.log.info("session started", mission=mid, ring=config.ring_order)
        return hosted

    async def _discard(self, session: ControllerSession | None, folder: Path | None) -> None:
        """Stops what a session started and removes its folder (None: keeps it)."""
        if session is not None:
            try:
                await session.stop()
            except Exception as exc:
                self.log.error("session did not stop cleanly", error=repr(exc))
        if folder is not None:
            await asyncio.to_thread(shutil.rmtree, folder, True)

    async def _program_ended(self, hosted: Hosted, code: int) -> None:
        """A session's program ended on its own: a failure ends the session."""
        if code == 0:
            return
        node = hosted.session.node
        hosted.error = node.program.mission_error or f"mission program exited with code {code}"
        self.log.warning("session failed", mission=hosted.mission_id, error=hosted.error)
        hosted.ending = self._tasks.spawn(self._end_failed(hosted), name=f"end-{hosted.mission_id}")

    async def _end_failed(self, hosted: Hosted) -> None:
        """Ends a failed session once its successor holds its log (or the flush bound)."""
        links = hosted.session.node.peers.values()
        # A bounded look at the acknowledgements: the ring links signal none outside the node.
        for _ in range(round(FAILED_FLUSH_S / FLUSH_POLL_S)):
            if not any(link.unacked for link in links):
                break
            await asyncio.sleep(FLUSH_POLL_S)
        hosted.state = station_pb2.SESSION_STATE_FAILED
        await self._stop_session(hosted)
        self.log.info("failed session ended", mission=hosted.mission_id)

    async def _stop_session(self, hosted: Hosted) -> None:
        """Stops a session's controller once, however many ask and if one is cancelled."""
        if hosted.stopping is None:
            hosted.stopping = asyncio.ensure_future(hosted.session.stop())
        try:
            await asyncio.shield(hosted.stopping)
        except Exception as exc:
            self.log.error("session did not stop cleanly", error=repr(exc))

    async def _end(self, hosted: Hosted) -> bool:
        """Ends a session now (a failed one's wait for its log to leave cut short);
        whether it was hosting."""
        was_running = hosted.state == station_pb2.SESSION_STATE_HOSTING
        if hosted.ending is not None and not hosted.ending.done():
            hosted.ending.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await hosted.ending
        await self._stop_session(hosted)
        return was_running

    async def stop_mission(self, mission_id: str) -> bool:
        """Ends a mission's session and removes its folder; whether it was hosting."""
        found = route(self.hosted, mission_id, self.id, "StopMission")
        if isinstance(found, StatusError):
            raise found
        del self.hosted[mission_id]
        was_running = await self._end(found)
        await self._discard(None, found.folder)
        self.log.info("session stopped", mission=mission_id)
        return was_running

    def mission_status(self, hosted: Hosted) -> station_pb2.StationMission:
        reply = station_pb2.StationMission(
            mission_id=hosted.mission_id,
            state=hosted.state,
            error=hosted.error,
            folder=str(hosted.folder),
        )
        if hosted.state == station_pb2.SESSION_STATE_HOSTING:
            reply.status.CopyFrom(controller_status(hosted.session.node))
        return reply

    def status(self) -> station_pb2.StationStatus:
        return station_pb2.StationStatus(
            id=self.id,
            address=self.server.address,
            missions=[self.mission_status(h) for _, h in sorted(self.hosted.items())],
        )

    async def start(self) -> None:
        await self.server.start()

    async def stop(self) -> None:
        """Stops every session (their folders stay), then the port."""
        await asyncio.gather(*(self._end(h) for h in self.hosted.values()))
        self._tasks.cancel()
        await self.server.stop()


class StationService(station_pb2_grpc.StationServicer):
    """The Station service: the operator's start, stop and status of sessions."""

    def __init__(self, app: StationApp) -> None:
        self._app = app

    async def StartMission(
        self, request: station_pb2.StartMissionRequest, context: grpc.aio.ServicerContext
    ) -> station_pb2.StationMission:
        try:
            hosted = await self._app.start_mission(request)
        except StatusError as exc:
            await abort_with(context, exc)
        return self._app.mission_status(hosted)

    async def StopMission(
        self, request: station_pb2.StopMissionRequest, context: grpc.aio.ServicerContext
    ) -> station_pb2.StopMissionReply:
        try:
            was_running = await self._app.stop_mission(request.mission_id)
        except StatusError as exc:
            await abort_with(context, exc)
        return station_pb2.StopMissionReply(was_running=was_running)

    async def GetStation(
        self, request: station_pb2.GetStationRequest, context: grpc.aio.ServicerContext
    ) -> station_pb2.StationStatus:
        return self._app.status()


async def serve(
    station_id: int,
    address: str,
    tls: TlsConfig,
    state_dir: Path,
    address_file: str | None,
    mission_python: str | None = None,
) -> int:
    """Runs a station until SIGTERM or SIGINT."""
    app = StationApp(station_id, address, tls, state_dir, mission_python)

    async def main(stop: asyncio.Event) -> int:
        await app.start()
        announce(
            address_file,
            [app.server.address],
            {"station": station_id, "address": app.server.address},
        )
        await stop.wait()
        await app.stop()
        return 0

    return await run_until_signalled(main)

"""Builds the drone service from its settings and runs it until stopped."""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Callable

from baton.authenticity import Signer
from baton.config import detection_time_s
from baton.drone.camera import Camera
from baton.drone.mobility_api import MobilityBackend, latest_position
from baton.drone.policy_runner import PolicyRunner
from baton.drone.sequencer import Sequencer
from baton.drone.service import DroneService
from baton.drone.settings import DroneSettings, landing_stations, safety_params
from baton.drone.store import DroneStore
from baton.lifecycle import announce
from baton.logs import get_logger
from baton.rpc.ports import drone_policy
from baton.rpc.server import BatonServer, servicer
from baton.rpc.tls import INSECURE_WARNING
from baton.v1 import drone_api_pb2 as api
from baton.v1 import drone_pb2, drone_pb2_grpc

# The drone pings every controller's connection each second and drops it
# after 2 s without the answer: a controller behind a silent link (a radio
# that fades without a reset, a frozen node) loses its streams within 3 s and
# is then lost like a dead one (the project's 10 s + 5 s would add 15 s).
# Only while takeovers are on: it is what finds a lost master behind such a
# link, and it drops any link whose round trip exceeds 2 s, which a drone that
# never takes over must keep (the 4 s uplink of the stale-request test).
CONTROLLER_KEEPALIVE_S = (1.0, 2.0)


def build_service(settings: DroneSettings, vehicle: MobilityBackend) -> DroneService:
    """The Drone servicer for ``settings`` over ``vehicle``."""

    async def position() -> api.Position:
        return await latest_position(vehicle)

    camera = Camera(
        position,
        settings.image_file,
        settings.resolution,
        settings.camera_effects_file,
        settings.thumbnails_dir,
        aim=vehicle.looking_at,  # where the gimbal points: a picture records it
    )
    sequencer = Sequencer(
        settings.controllers,
        settings.master,
        settings.handover_script,
        settings.cache_window,
        settings.prepare_timeout_s,
    )
    store = DroneStore(settings.state_file) if settings.state_file else None
    takeover_after_s = detection_time_s(settings.takeover_after, settings.speedup)
    service = DroneService(
        vehicle,
        camera,
        sequencer,
        settings.race,
        store,
        takeover_after_s,
        authenticated=settings.tls is not None,
        link_bounds=settings.link_bounds,
        safety=safety_params(settings.config),
        stations=landing_stations(settings.config),
    )
    if settings.tls is not None:
        service.signer = Signer.from_pem(settings.tls.key)
        sequencer.sign_grants_with(service.signer.seal_grant)
    if settings.policy is not None:
        service.policy = PolicyRunner(service, settings.policy, settings.stations, settings.speedup)
        service.policy.restore()
    gcs = getattr(vehicle, "gcs", None)  # ground stations watching (drone/gcs.py)
    if gcs is not None:
        gcs.on_override = service.operator.ground_station_paused
        gcs.controller = lambda: str(sequencer.master)
    return service


async def serve(
    settings: DroneSettings,
    vehicle: MobilityBackend,
    stop: asyncio.Event,
    on_listening: Callable[[str], None] | None = None,
) -> int:
    """Runs the drone service until ``stop`` is set."""
    service = build_service(settings, vehicle)
    name = drone_pb2.DESCRIPTOR.services_by_name["Drone"].full_name
    server = BatonServer(
        settings.address,
        [servicer(name, drone_pb2_grpc.add_DroneServicer_to_server, service)],
        keepalive=CONTROLLER_KEEPALIVE_S if service.takeover_after_s > 0 else None,
        tls=settings.tls,
        policy=drone_policy(settings.controllers),
    )
    await vehicle.start()
    await server.start()
    log = get_logger("drone")
    if settings.tls is None:
        log.warning(INSECURE_WARNING)
    log.info(
        "listening",
        address=server.address,
        vehicle_url=vehicle.url,
        controllers=list(settings.controllers),
        master=settings.master,
        scripted_handovers=len(settings.handover_script),
        handover_policy=settings.policy.name if settings.policy is not None else "none",
        speedup=settings.speedup,
    )
    announce(settings.address_file, [server.address], {"address": server.address})
    if on_listening is not None:
        on_listening(server.address)
    watchdog = asyncio.create_task(service.stalls.run(), name="stall-watchdog")
    takeovers = asyncio.create_task(service.watch_master(), name="takeover-watch")
    failsafes = asyncio.create_task(service.failsafes.run(), name="failsafe-watch")
    pings = asyncio.create_task(service.watch_links(), name="link-pings")
    policy = (
        asyncio.create_task(service.policy.run(), name="handover-policy")
        if service.policy is not None
        else None
    )
    try:
        await stop.wait()
    finally:
        watchdog.cancel()
        takeovers.cancel()
        failsafes.cancel()
        pings.cancel()
        if policy is not None:
            policy.cancel()
        await server.stop()
        await vehicle.close()
        if service.store is not None:
            service.store.close()
        log.info("stopped", executed=service.seq.executed, last_reqnr=service.last_reqnr)
    sys.stdout.flush()
    return 0

"""The sim vehicle's MAVLink habits, seen by a pymavlink ground station over real UDP.

The ones a real ArduPilot has and the project once forgot: nothing but
HEARTBEAT streamed until asked, no home and no arming until its estimator
has warmed up, and NaN command parameters meaning "unset".
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from baton.sim_vehicle.kinematics import FlightParams, GeoPoint
from baton.sim_vehicle.server import DEFAULT_INTERVALS_S, SimVehicle

from .ground_station import UNSET, GroundStation, mavlink

HOME = (47.397742, 8.545594, 488.0)
SPEEDUP = 10.0
# Long enough (2 s of wall time) that a ground station is surely talking to
# the vehicle before it ends, short enough to wait for.
WARMUP_S = 20.0

PREARM = mavlink.MAV_SYS_STATUS_PREARM_CHECK
GPS = mavlink.MAV_SYS_STATUS_SENSOR_GPS
ACCEPTED, DENIED = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED
UNSUPPORTED = mavlink.MAV_RESULT_UNSUPPORTED
POSITION = mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT
SYS_STATUS = mavlink.MAVLINK_MSG_ID_SYS_STATUS
HOME_POSITION = mavlink.MAVLINK_MSG_ID_HOME_POSITION
HEARTBEAT = mavlink.MAVLINK_MSG_ID_HEARTBEAT


@pytest.fixture
def start_vehicle() -> Iterator[Callable[[float], SimVehicle]]:
    """Starts in-process vehicles with a given warm-up (simulated s); stops them after."""
    vehicles: list[SimVehicle] = []

    def start(warmup_s: float) -> SimVehicle:
        vehicle = SimVehicle(
            GeoPoint(*HOME), speedup=SPEEDUP, params=FlightParams(warmup_s=warmup_s)
        )
        vehicle.start()
        vehicles.append(vehicle)
        return vehicle

    yield start
    for vehicle in vehicles:
        vehicle.stop()


def _flags(status: Any) -> tuple[int, int, int]:
    """SYS_STATUS's present, enabled and health bit sets."""
    return (
        status.onboard_control_sensors_present,
        status.onboard_control_sensors_enabled,
        status.onboard_control_sensors_health,
    )


def test_a_ground_station_that_asks_nothing_gets_only_heartbeats(
    start_vehicle: Callable[[float], SimVehicle],
) -> None:
    vehicle = start_vehicle(10.0)
    with GroundStation(vehicle.port) as gcs:
        gcs.say_hello()
        for _ in range(10):  # 1 s of wall time at the heartbeat's 10 Hz
            gcs.receive("HEARTBEAT")
        # STATUSTEXT: the vehicle says why it is not armable yet, unasked, as ArduPilot.
        assert gcs.kinds_received() <= {"HEARTBEAT", "STATUSTEXT"}, gcs.kinds_received()
        texts = [m.text for m in gcs.received if m.get_type() == "STATUSTEXT"]
        assert all(text.startswith("PreArm: ") for text in texts), texts

        assert gcs.set_interval(POSITION, 100_000) == ACCEPTED
        position = gcs.receive("GLOBAL_POSITION_INT")
        assert position.lat == round(HOME[0] * 1e7) and position.lon == round(HOME[1] * 1e7)
        assert vehicle.streams() == {
            HEARTBEAT: DEFAULT_INTERVALS_S[HEARTBEAT],
            POSITION: pytest.approx(0.1),
        }


def test_request_message_sends_one_and_interval_minus_one_stops_a_stream(
    start_vehicle: Callable[[float], SimVehicle],
) -> None:
    vehicle = start_vehicle(0.0)
    with GroundStation(vehicle.port) as gcs:
        gcs.say_hello()
        assert gcs.command(mavlink.MAV_CMD_REQUEST_MESSAGE, SYS_STATUS).result == ACCEPTED
        gcs.receive("SYS_STATUS")
        assert gcs.set_interval(POSITION, 50_000) == ACCEPTED
        gcs.receive("GLOBAL_POSITION_INT")
        stopped = gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, POSITION, -1)
        assert stopped.result == ACCEPTED
        # 0.5 s: ten intervals of the stopped stream, 2.5 of SYS_STATUS's default one.
        for _ in range(5):
            gcs.receive("HEARTBEAT")
        after = {m.get_type() for m in gcs.received_since(stopped)}
        assert "GLOBAL_POSITION_INT" not in after, after
        assert [m.get_type() for m in gcs.received].count("SYS_STATUS") == 1
        assert vehicle.streams().keys() == {HEARTBEAT}

        # What the vehicle cannot produce is refused, not silently ignored.
        rc_channels = mavlink.MAVLINK_MSG_ID_RC_CHANNELS
        assert gcs.set_interval(rc_channels, 100_000) == UNSUPPORTED
        assert gcs.command(mavlink.MAV_CMD_REQUEST_MESSAGE, rc_channels).result == UNSUPPORTED


def test_arming_is_denied_with_a_prearm_text_until_warmed_up(
    start_vehicle: Callable[[float], SimVehicle],
) -> None:
    vehicle = start_vehicle(WARMUP_S)
    with GroundStation(vehicle.port) as gcs:
        gcs.say_hello()
        denied = gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert denied.result == DENIED
        # Right before the refusal, so a ground station has the reason when it arrives.
        why = gcs.received[gcs.index(denied) - 1]
        assert why.get_type() == "STATUSTEXT", why
        assert why.text == "PreArm: Need Position Estimate"
        assert why.severity == mavlink.MAV_SEVERITY_CRITICAL
        assert not vehicle.state().armed and vehicle.state().time_s < WARMUP_S

        assert gcs.set_interval(SYS_STATUS, 100_000) == ACCEPTED
        gcs.receive("SYS_STATUS", lambda status: status.onboard_control_sensors_health & PREARM)
        assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == ACCEPTED
        gcs.receive("HEARTBEAT", lambda hb: hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)


def test_sys_status_and_home_position_change_at_the_warmup(
    start_vehicle: Callable[[float], SimVehicle],
) -> None:
    vehicle = start_vehicle(WARMUP_S)
    with GroundStation(vehicle.port) as gcs:
        gcs.say_hello()
        assert gcs.set_interval(SYS_STATUS, 0) == ACCEPTED  # 0: the default rate
        assert gcs.set_interval(HOME_POSITION, 100_000) == ACCEPTED

        warming = gcs.receive("SYS_STATUS")
        present, enabled, health = _flags(warming)
        assert not (present | enabled | health) & PREARM
        assert present & GPS and enabled & GPS and not health & GPS

        ready = gcs.receive(
            "SYS_STATUS", lambda status: status.onboard_control_sensors_health & PREARM
        )
        assert all(flags & PREARM and flags & GPS for flags in _flags(ready))
        home = gcs.receive("HOME_POSITION")
        assert home.latitude == round(HOME[0] * 1e7) and home.altitude == round(HOME[2] * 1000)

        # It flipped once and for all, and no home was sent before there was one.
        statuses = [m for m in gcs.received if m.get_type() == "SYS_STATUS"]
        armable = [bool(m.onboard_control_sensors_health & PREARM) for m in statuses]
        assert armable == sorted(armable) and armable.count(False) >= 1
        homes = [m for m in gcs.received if m.get_type() == "HOME_POSITION"]
        assert all(m.time_usec >= WARMUP_S * 1e6 for m in homes)
        assert vehicle.state().armable


def test_nan_parameters_mean_unset(start_vehicle: Callable[[float], SimVehicle]) -> None:
    """MAVLink's NaN is "unset": the default where there is one, DENIED where there is not."""
    vehicle = start_vehicle(0.0)
    cases = [
        ("arm or disarm?", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, [UNSET] * 7, DENIED),
        ("no mode", mavlink.MAV_CMD_DO_SET_MODE, [UNSET] * 7, DENIED),
        ("no message", mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, [UNSET] * 7, DENIED),
        ("no message", mavlink.MAV_CMD_REQUEST_MESSAGE, [UNSET] * 7, DENIED),
        ("default rate", mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, [POSITION] + [UNSET] * 6, ACCEPTED),
        ("one message", mavlink.MAV_CMD_REQUEST_MESSAGE, [SYS_STATUS] + [UNSET] * 6, ACCEPTED),
        ("arm as MAVSDK does", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, [1] + [UNSET] * 6, ACCEPTED),
        ("disarm, not forced", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, [0] + [UNSET] * 6, ACCEPTED),
    ]
    with GroundStation(vehicle.port) as gcs:
        gcs.say_hello()
        for what, command, params, expected in cases:
            assert gcs.command(command, *params).result == expected, what
        gcs.receive("GLOBAL_POSITION_INT")
        assert "SYS_STATUS" in gcs.kinds_received()  # sent right after its ACK
        assert vehicle.streams()[POSITION] == DEFAULT_INTERVALS_S[POSITION]
        assert not vehicle.state().armed

        # The same through COMMAND_INT.
        assert gcs.command_int(mavlink.MAV_CMD_DO_SET_MODE, UNSET, UNSET, UNSET).result == DENIED
        ack = gcs.command_int(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, SYS_STATUS, UNSET)
        assert ack.result == ACCEPTED
        ack = gcs.command_int(mavlink.MAV_CMD_REQUEST_MESSAGE, UNSET)
        assert ack.result == DENIED
        assert gcs.command(mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1).result == ACCEPTED


class _Warnings(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def test_a_bad_datagram_or_a_failing_handler_is_logged_and_skipped(
    start_vehicle: Callable[[float], SimVehicle], monkeypatch: pytest.MonkeyPatch
) -> None:
    vehicle = start_vehicle(0.0)

    def broken(*args: object) -> None:
        raise RuntimeError("a bug in the parameter handler")

    monkeypatch.setattr(vehicle, "_param", broken)
    warnings = _Warnings()
    logger = logging.getLogger("baton.sim_vehicle")
    logger.addHandler(warnings)
    try:
        with GroundStation(vehicle.port) as gcs:
            gcs.say_hello()
            gcs.link.write(b"not MAVLink at all")
            packet = gcs.link.mav.command_long_encode(
                1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, SYS_STATUS, 0, 0, 0, 0, 0, 0
            ).pack(gcs.link.mav)
            gcs.link.write(packet[:12])  # truncated: must not swallow the next datagram
            gcs.link.mav.param_request_read_send(1, 1, b"MIS_TAKEOFF_ALT", -1)
            # Still there, and the command right after the bad ones is answered.
            ack = gcs.command(mavlink.MAV_CMD_REQUEST_MESSAGE, SYS_STATUS)
            assert ack.result == ACCEPTED
            gcs.receive("SYS_STATUS")
            assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == ACCEPTED
    finally:
        logger.removeHandler(warnings)
    assert warnings.messages.count("bad data skipped") == 2, warnings.messages
    assert "datagram skipped: handling it failed" in warnings.messages

"""Bench-mission scripts with their log entries and flush points known in advance.

The bench mission (``baton.missions.bench``) runs a fixed list of calls.
Here each step's log entry is sized from the messages the drone sends back,
taking the largest value a field can have (all position fields set, a large
picture sequence number), so the predicted log is never smaller than the real
one: a log predicted to stay just under the flush limit really does. The
worst-case script fills the master's log to just under f, takes a full
picture (the log flushes at about f + e), and places the handover on the
small call right after it, so the old master has flushed its largest log
when the drone decides.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from baton.bench.model import Call, LogPoint, PredictedRing, master_log_sizes
from baton.bench.model import entry_size_of as entry_bytes
from baton.controller.core import CLOCK_SLEEP
from baton.drone.camera import DEFAULT_RESOLUTION, MIN_SIDE, ppm_header
from baton.missions import bench as bench_mission
from baton.rpc.methods import path
from baton.v1 import drone_api_pb2 as api

BENCH_MISSION = Path(bench_mission.__file__)

GET_POSITION = path("Mobility.GetPosition")
TAKE_PICTURE = path("Camera.TakePicture")
SET_RESOLUTION = path("Camera.SetResolution")

_FULL_POSITION = api.Position(
    latitude_deg=-89.123456789,
    longitude_deg=-179.123456789,
    absolute_altitude_m=9999.123,
    relative_altitude_m=999.123,
)
# Below this gap to the flush limit a filler picture is not worth a call.
FILL_MARGIN = 4096
# Room for one more small entry in the master's log than predicted: when the
# drone's notice overtakes the reply of the request the handover came after
# (footnote 2), that request's entry lands in the new master's log instead.
RACE_SLACK = 512


def bench_mission_args(script: str) -> tuple[str, ...]:
    """The testbed's ``mission_args`` that run ``script`` with the bench mission."""
    return (f"script={script}",)


def position_reply_bytes() -> int:
    """The largest GetPosition reply."""
    return api.GetPositionReply(position=_FULL_POSITION).ByteSize()


def picture_reply_bytes(width: int, height: int) -> int:
    """The largest TakePicture reply of a generated picture at ``width`` x ``height``."""
    image = len(ppm_header(width, height)) + width * height * 3
    return api.TakePictureReply(
        image=b"\1" * image,
        format="ppm",
        width=width,
        height=height,
        position=_FULL_POSITION,
        sequence=2**40,
    ).ByteSize()


def resolution_bytes(width: int, height: int) -> int:
    """SetResolution's request (and reply) size."""
    return api.SetResolutionRequest(width=width, height=height).ByteSize()


@dataclass
class ScriptBuilder:
    """Appends bench-mission steps and keeps the predicted calls, reqnr by reqnr."""

    steps: list[str] = field(default_factory=list)
    calls: list[Call] = field(default_factory=list)
    resolution: tuple[int, int] = DEFAULT_RESOLUTION

    @property
    def reqnr(self) -> int:
        """The last request number so far."""
        return len(self.calls)

    def _call(self, method: str, reply_bytes: int, request_bytes: int = 0) -> Call:
        call = Call(self.reqnr + 1, method, reply_bytes, request_bytes)
        self.calls.append(call)
        return call

    def position(self) -> Call:
        """A position read."""
        self.steps.append("p")
        return self._call(GET_POSITION, position_reply_bytes())

    def picture(self) -> Call:
        """A picture at the current resolution."""
        self.steps.append("c")
        return self._call(TAKE_PICTURE, picture_reply_bytes(*self.resolution))

    def set_resolution(self, width: int, height: int) -> Call:
        """Changes the picture size."""
        self.steps.append(f"r{width}x{height}")
        self.resolution = (width, height)
        size = resolution_bytes(width, height)
        return self._call(SET_RESOLUTION, size, size)

    def sleep(self, seconds: float) -> Call:
        """A sleep: answered and logged by the controller, never sent to the drone."""
        self.steps.append(f"s{seconds:g}")
        return self._call(
            CLOCK_SLEEP,
            api.SleepReply().ByteSize(),
            api.SleepRequest(seconds=seconds).ByteSize(),
        )

    @property
    def script(self) -> str:
        """The ``script`` parameter of the bench mission."""
        return ",".join(self.steps)


@dataclass(frozen=True)
class WorstCasePoint:
    """One scripted worst-case handover."""

    picture_reqnr: int  # the full picture whose entry makes the log flush at about f + e
    after_reqnr: int  # the handover: right after the next (small) call
    old_master: int
    new_master: int
    hops: int
    predicted_flush_bytes: int  # the predicted size of the log flushed at picture_reqnr


@dataclass
class WorstCaseScript:
    """A bench-mission script with worst-case handovers at known request numbers."""

    flush_limit: int
    script: str
    calls: list[Call]
    points: list[WorstCasePoint]

    @property
    def handovers(self) -> tuple[tuple[int, int], ...]:
        """The drone's handover script: (after reqnr, new master)."""
        return tuple((p.after_reqnr, p.new_master) for p in self.points)

    def predicted_log(self) -> list[LogPoint]:
        """The master's log after every request, as predicted."""
        return master_log_sizes(self.calls, self.flush_limit, [p.after_reqnr for p in self.points])


def _fill_to_just_under(builder: ScriptBuilder, log: PredictedRing, flush_limit: int) -> None:
    """Adds pictures until one more full picture would cross ``flush_limit``."""
    full = entry_bytes(Call(0, TAKE_PICTURE, picture_reply_bytes(*DEFAULT_RESOLUTION)))
    while log.size + full + RACE_SLACK < flush_limit:
        log.reply(builder.picture())
    width = DEFAULT_RESOLUTION[0]
    resolution_entries = 2 * entry_bytes(Call(0, SET_RESOLUTION, 8, 8))
    gap = flush_limit - log.size - resolution_entries - RACE_SLACK - FILL_MARGIN
    height = (gap - (full - width * DEFAULT_RESOLUTION[1] * 3)) // (width * 3)
    if height < MIN_SIDE:
        return
    log.reply(builder.set_resolution(width, height))
    log.reply(builder.picture())
    log.reply(builder.set_resolution(*DEFAULT_RESOLUTION))


def worst_case_script(
    flush_limit: int,
    hop_sequence: Sequence[int],
    controllers: int,
    settle_s: float,
    first_master: int = 0,
) -> WorstCaseScript:
    """A script that hands over ``len(hop_sequence)`` times, each right after the largest flush.

    Each handover is one cycle: the new master's first request (a position
    read), a sleep of ``settle_s`` so the previous log messages finish their
    way around the ring, pictures up to just under the flush limit, one full
    picture (the flush of about f + e), and a position read after which the
    drone hands over ``hops`` controllers further along the ring.
    """
    builder = ScriptBuilder()
    log = PredictedRing(flush_limit)  # the master's log, by the protocol's flush rule
    points: list[WorstCasePoint] = []
    master = first_master

    def add(call: Call) -> int:
        return log.reply(call).flushed

    for hops in hop_sequence:
        add(builder.position())
        add(builder.sleep(settle_s))
        if flush_limit > 0:
            _fill_to_just_under(builder, log, flush_limit)
            if log.size + RACE_SLACK >= flush_limit:
                raise AssertionError("the fill came too close to the flush limit")
        picture = builder.picture()
        flushed = add(picture)
        if not flushed:
            raise AssertionError(f"no flush at picture {picture.reqnr} (log {log.size} bytes)")
        after = builder.position()
        add(after)
        new_master = (master + hops) % controllers
        points.append(WorstCasePoint(picture.reqnr, after.reqnr, master, new_master, hops, flushed))
        log.hand_over()  # the handover message takes the rest; the new master starts empty
        master = new_master
    # The last handover's delay needs the new master's first request.
    builder.position()
    return WorstCaseScript(flush_limit, builder.script, builder.calls, points)

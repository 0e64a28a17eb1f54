"""Faults the testbed injects on purpose (``baton testbed --fault``), and the parts that die.

A fault is ``KIND:PART@WHEN[,for=DURATION]`` (a battery: ``,to=PERCENT``):

- ``kill:controller-1@reqnr=130``: kill -9 of a part once the drone has served
  request 130 (``for=10s``: started again 10 s later, with the same command line);
- ``stop:controller-0@reqnr=60,for=20s``: SIGSTOP, then SIGCONT 20 s later (a
  frozen node: its sockets stay open and say nothing);
- ``cut:link-ring-1@t=30s,for=10s``: the link emulator in front of a controller
  (``link-ring-N``) or between it and the drone (``link-drone-N``) stops, every
  connection through it breaks, and it is started again on its address 10 s later.
- ``full:controller-1@reqnr=20,for=10s``: the controller's disk fills: its log
  file (``--log-file``; the drone's: its state file) takes no more bytes, and
  every write that would grow it fails with EFBIG as a full disk fails it with
  ENOSPC (``fill_disk``); 10 s later the disk has room again.
- ``pause:drone@reqnr=20,for=5s``, ``abort:drone@reqnr=40``,
  ``land-now:drone@t=30s``: the operator's command to the drone (its
  Pause, Abort with a return, LandNow, as ``baton operator`` sends them, with
  the operator's certificate); a pause with ``for=`` is resumed after it.
- ``battery:sim-vehicle@reqnr=20,to=15%``: the vehicle's battery reads 15 % from then
  on and drains on from there, set by ArduPilot's MAV_CMD_BATTERY_RESET sent to the
  vehicle's own MAVLink port, signed with its key if it holds one (``battery.py``); the
  drone learns it from the vehicle's telemetry, and its battery failsafe acts below the
  mission's reserve (``safety.battery_reserve``). The sim vehicle only: on ``sitl`` it is
  refused, naming what to do instead. A battery is not recharged: no ``for=``.

WHEN is ``reqnr=N`` (the drone's ``last_reqnr``, polled) or ``t=DURATION`` (after
the mission's start: once every controller runs). Without ``for=`` a stop or a
cut lasts to the end of the run, and a killed part stays dead unless
``--restart-parts`` restarts it. ``FaultInjector`` fires each fault once, and
every fault and every death of a part (by a fault or from outside the testbed)
is kept for the report, with what the mission did meanwhile: the handovers the drone
decided and the failsafe it entered before the next fault, and the mission's verdict.
"""

from __future__ import annotations

import asyncio
import math
import re
import resource
import time
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from baton.config import parse_duration

if TYPE_CHECKING:
    from baton.testbed.local import LocalTestbed

FAULT_KINDS = ("kill", "stop", "cut", "full", "pause", "abort", "land-now", "battery")
# The operator's commands to the drone, as faults (``LocalTestbed.operator``).
OPERATOR_KINDS = ("pause", "abort", "land-now")
BATTERY_EXAMPLE = "battery:sim-vehicle@reqnr=20,to=15%"
FAULT_EXAMPLE = (
    "kill:controller-1@reqnr=130, stop:controller-0@reqnr=60,for=20s, "
    f"cut:link-ring-1@t=30s,for=10s or {BATTERY_EXAMPLE}"
)
_PART = re.compile(r"^(sim-vehicle|sitl|drone|(controller|link-ring|link-drone)-\d+)$")
# How often the injector reads the drone's last request number.
POLL_S = 0.05
# What a part filled by ``full`` may still write to its own log (stdout), bytes: its
# log lines, the error about the full disk among them, still reach a person.
LOG_ROOM = 1 << 20


def fill_disk(pid: int, files: Collection[Path], own_log: Path) -> int:
    """Makes the disk of ``files`` full for process ``pid``: RLIMIT_FSIZE set to the
    largest of them, so that no write of ``pid`` grows them any more (EFBIG; Python
    ignores SIGXFSZ), while its own log keeps ``LOG_ROOM``. Returns the limit.

    The limit is the process's, on every file it writes, not a file system's: the
    closest to a full disk that needs no root (a tmpfs needs a mount)."""
    sizes = [path.stat().st_size for path in files if path.exists()]
    own = own_log.stat().st_size if own_log.exists() else 0
    limit = max([*sizes, own + LOG_ROOM])
    resource.prlimit(pid, resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))
    return limit


def free_disk(pid: int) -> None:
    """Ends ``fill_disk``: writes of ``pid`` may grow files again."""
    resource.prlimit(pid, resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))


@dataclass(frozen=True)
class Fault:
    """One ``--fault``: what (``kind``), to which part, when (after ``reqnr``, or ``at_s``
    seconds after the mission started), for how long (``for_s``; None: to the end) and,
    for a battery, the percentage it reads from then on (``to_pct``)."""

    text: str
    kind: str
    part: str
    reqnr: int | None = None
    at_s: float | None = None
    for_s: float | None = None
    to_pct: float | None = None

    def to_json(self) -> dict[str, Any]:
        entry = {
            "fault": self.text,
            "kind": self.kind,
            "part": self.part,
            "at": {"reqnr": self.reqnr} if self.reqnr is not None else {"t_s": self.at_s},
            "for_s": self.for_s,
        }
        if self.to_pct is not None:
            entry["to_pct"] = self.to_pct
        return entry


def parse_fault(text: str) -> Fault:
    """``KIND:PART@WHEN[,for=DURATION]`` as a Fault; ValueError names the option and the fix."""

    def bad(why: str) -> ValueError:
        return ValueError(f"--fault {text!r}: {why}; e.g. {FAULT_EXAMPLE}")

    kind, colon, rest = text.partition(":")
    if not colon or kind not in FAULT_KINDS:
        named = kind if colon else text
        raise bad(f"unknown fault {named!r}, expected one of {', '.join(FAULT_KINDS)}")
    part, at, when = rest.partition("@")
    if not at:
        raise bad("no time: add @reqnr=N (after the drone served request N) or @t=30s")
    if not _PART.match(part):
        raise bad(
            f"unknown part {part!r}: expected controller-N, link-ring-N, link-drone-N, drone, "
            "sim-vehicle or sitl"
        )
    if kind == "full" and not (part == "drone" or part.startswith("controller-")):
        raise bad(
            f"full is for a controller's log file (controller-N) or the drone's state file "
            f"(drone), not {part}"
        )
    if kind in OPERATOR_KINDS and part != "drone":
        raise bad(f"{kind} is the operator's command to the drone (drone), not {part}")
    if kind == "cut" and not part.startswith("link-"):
        raise bad(
            f"cut is for a link emulator (link-ring-N, link-drone-N), not {part}; "
            f"stop:{part} freezes a part, kill:{part} kills it"
        )
    if kind == "battery" and part == "sitl":
        raise bad(
            "battery is not supported on sitl: the testbed sets the sim vehicle's battery "
            f"only: run --vehicle sim and {BATTERY_EXAMPLE}, or on SITL send ArduPilot's "
            "MAV_CMD_BATTERY_RESET (param1 1, param2 the percentage) from a ground station "
            "on its second port"
        )
    if kind == "battery" and part != "sim-vehicle":
        raise bad(f"battery is the vehicle's (sim-vehicle), not {part}")
    options: dict[str, str] = {}
    for item in when.split(","):
        key, eq, value = item.partition("=")
        if not eq or key not in ("reqnr", "t", "for", "to") or key in options:
            raise bad(
                f"{item!r} is not reqnr=N, t=DURATION, for=DURATION or to=PERCENT (each once)"
            )
        options[key] = value
    if ("reqnr" in options) == ("t" in options):
        raise bad("give the time once: @reqnr=N or @t=DURATION")
    reqnr = at_s = for_s = None
    if "reqnr" in options:
        if not options["reqnr"].isdigit() or int(options["reqnr"]) < 1:
            raise bad(f"reqnr={options['reqnr']!r} is not a request number >= 1")
        reqnr = int(options["reqnr"])
    try:
        if "t" in options:
            at_s = parse_duration(options["t"])
        if "for" in options:
            for_s = parse_duration(options["for"])
            if for_s <= 0:
                raise ValueError(f"for={options['for']!r} must be longer than 0")
    except ValueError as exc:
        raise bad(str(exc)) from None
    if for_s is not None and kind in ("abort", "land-now"):
        raise bad(f"{kind} ends the mission: it takes no for= (a pause does: it is resumed)")
    to_pct = None
    if kind == "battery":
        if for_s is not None:
            raise bad("a battery is not recharged in flight: battery takes no for=")
        if "to" not in options:
            raise bad("battery needs the percentage it drops to: add to=PERCENT (to=15%)")
        to_pct = _percentage(options["to"])
        if to_pct is None:
            raise bad(f"to={options['to']!r} is not a percentage from 0 to 100 (to=15%)")
    elif "to" in options:
        raise bad(f"to= is the battery's percentage, not {kind}'s")
    return Fault(text, kind, part, reqnr, at_s, for_s, to_pct)


def _percentage(text: str) -> float | None:
    """``15%`` or ``15`` (0-100, finite) as a number; None if it is not one."""
    try:
        value = float(text.removesuffix("%"))
    except ValueError:
        return None
    return value if math.isfinite(value) and 0.0 <= value <= 100.0 else None


def check_parts(faults: Collection[Fault], parts: Collection[str]) -> None:
    """ValueError unless every fault names one of the testbed's ``parts``."""
    for fault in faults:
        if fault.part not in parts:
            raise ValueError(
                f"--fault {fault.text!r}: this testbed has no {fault.part}; its parts: "
                f"{', '.join(sorted(parts))}"
            )


@dataclass
class PartDeath:
    """A part that exited while the mission ran: by a fault or from outside the testbed."""

    part: str
    at_s: float  # after the run's start
    wall: float  # time.time(), to place it among the drone's records
    returncode: int | None
    reqnr: int | None  # the drone's last request number then, if known
    master: int | None
    cause: str  # the fault's text, or "outside"
    restarted_at_s: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "part": self.part,
            "at_s": round(self.at_s, 3),
            "returncode": self.returncode,
            "reqnr": self.reqnr,
            "master": self.master,
            "cause": self.cause,
            "restarted_at_s": (
                None if self.restarted_at_s is None else round(self.restarted_at_s, 3)
            ),
        }

    def describe(self) -> str:
        cause = "killed from outside" if self.cause == "outside" else f"by --fault {self.cause}"
        where = f" at reqnr {self.reqnr} (master {self.master})" if self.reqnr is not None else ""
        back = (
            f"; restarted at {self.restarted_at_s:.1f} s"
            if self.restarted_at_s is not None
            else "; not restarted"
        )
        return (
            f"{self.part} exited with code {self.returncode} at {self.at_s:.1f} s{where}, "
            f"{cause}{back}"
        )


@dataclass
class FaultRecord:
    """A fault and what became of it."""

    fault: Fault
    fired_at_s: float | None = None
    fired_wall: float | None = None
    fired_at_reqnr: int | None = None
    master_before: int | None = None
    ended_at_s: float | None = None  # thawed, restored or restarted by for=
    applied: str = ""  # what was done, and what the part said ("the vehicle reads 15 %")
    problem: str = ""  # why it could not be applied

    def to_json(self) -> dict[str, Any]:
        return {
            **self.fault.to_json(),
            "fired": self.fired_at_s is not None,
            "fired_at_s": None if self.fired_at_s is None else round(self.fired_at_s, 3),
            "fired_at_reqnr": self.fired_at_reqnr,
            "master_before": self.master_before,
            "ended_at_s": None if self.ended_at_s is None else round(self.ended_at_s, 3),
            "applied": self.applied,
            "problem": self.problem,
        }


@dataclass
class FaultInjector:
    """Fires the run's faults at their time, on a live ``LocalTestbed``."""

    testbed: LocalTestbed
    faults: tuple[Fault, ...]
    say: Callable[[str], None] = print
    records: list[FaultRecord] = field(default_factory=list)
    _started: float = 0.0
    _tasks: list[asyncio.Task[None]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.records = [FaultRecord(f) for f in self.faults]

    @property
    def in_progress(self) -> bool:
        """A stop or a cut (or a kill with ``for=``) fired and not over yet."""
        return any(
            r.fired_at_s is not None
            and r.fault.for_s is not None
            and r.ended_at_s is None
            and not r.problem
            for r in self.records
        )

    async def run(self, started: float) -> None:
        """Fires every fault when due (``started``: the mission's start, monotonic), and
        ends each one with ``for=`` in time; cancelled, it ends none of them."""
        self._started = started
        pending = list(self.records)
        try:
            while pending:
                reqnr, master = await self.testbed.drone_reqnr()
                now = time.monotonic() - started
                for record in list(pending):
                    fault = record.fault
                    due = (
                        fault.reqnr is not None and reqnr is not None and reqnr >= fault.reqnr
                    ) or (fault.at_s is not None and now >= fault.at_s)
                    if due:
                        pending.remove(record)
                        record.fired_at_reqnr, record.master_before = reqnr, master
                        await self._fire(record)
                await asyncio.sleep(POLL_S)
            await asyncio.gather(*self._tasks)  # the stops and cuts still to end
        finally:
            for task in self._tasks:
                task.cancel()

    def _since(self) -> float:
        return time.monotonic() - self._started

    async def _fire(self, record: FaultRecord) -> None:
        fault = record.fault
        testbed = self.testbed
        part = testbed.supervisor.parts.get(fault.part)
        if part is None or part.returncode is not None or part.frozen:
            record.problem = f"{fault.part} was not running then"
            self.say(f"fault {fault.text}: not applied, {record.problem}")
            return
        record.fired_at_s, record.fired_wall = self._since(), time.time()
        where = f"reqnr {record.fired_at_reqnr}, master {record.master_before}"
        if fault.kind in OPERATOR_KINDS or fault.kind == "battery":
            try:
                what = await self._command(fault)
            except Exception as exc:  # refused or unreachable: the report says so
                whom = "drone" if fault.kind in OPERATOR_KINDS else "vehicle"
                record.problem = f"the {whom} did not take it: {exc}"
                self.say(f"fault {fault.text}: {record.problem}")
                return
        elif fault.kind == "kill":
            await testbed.kill_part(
                fault.part,
                cause=fault.text,
                at=(record.fired_at_reqnr, record.master_before),
                restart_later=fault.for_s is not None,
            )
            what = f"killed {fault.part} (kill -9)"
        elif fault.kind == "stop":
            testbed.supervisor.freeze(fault.part)
            what = f"stopped {fault.part} (SIGSTOP)"
        elif fault.kind == "full":
            durable = (
                testbed.drone_state
                if fault.part == "drone"
                else testbed.controller_log(int(fault.part.rsplit("-", 1)[1]))
            )
            wal = durable.with_name(durable.name + "-wal")
            assert part.process is not None
            limit = fill_disk(part.process.pid, [durable, wal], part.log_path)
            what = f"filled the disk of {durable.name} ({limit} bytes a file)"
        else:
            await testbed.cut_link(fault.part)
            what = f"cut {fault.part}"
        record.applied = what
        lasting = f" for {fault.for_s:g} s" if fault.for_s is not None else ""
        self.say(f"fault {fault.text}: {what}{lasting} at {where}")
        if fault.for_s is not None:
            self._tasks.append(asyncio.create_task(self._end_later(record)))

    async def _command(self, fault: Fault) -> str:
        """An operator's command to the drone, or the battery set on the vehicle: what the
        part took, in a line; raises if it refused or did not answer."""
        if fault.kind in OPERATOR_KINDS:
            return await self.testbed.operator(fault.kind, note=f"--fault {fault.text}")
        assert fault.to_pct is not None
        reads = await self.testbed.set_battery(fault.to_pct)
        return (
            f"set the battery of {fault.part} to {fault.to_pct:g} % (MAV_CMD_BATTERY_RESET); "
            f"the vehicle reads {reads} %"
        )

    async def _end_later(self, record: FaultRecord) -> None:
        fault = record.fault
        assert fault.for_s is not None
        await asyncio.sleep(fault.for_s)
        testbed = self.testbed
        try:
            if fault.kind == "stop":
                testbed.supervisor.thaw(fault.part)
                what = f"{fault.part} continued (SIGCONT)"
            elif fault.kind == "pause":
                what = await testbed.operator("resume", note=f"--fault {fault.text}")
            elif fault.kind == "cut":
                await testbed.restore_link(fault.part)
                what = f"{fault.part} restored"
            elif fault.kind == "full":
                part = testbed.supervisor.parts[fault.part]
                assert part.process is not None
                free_disk(part.process.pid)
                what = f"the disk of {fault.part} has room again"
            else:
                await testbed.restart_part(fault.part)
                what = f"{fault.part} restarted"
        except Exception as exc:  # the run goes on; the report says what failed
            record.problem = f"could not end the fault: {exc}"
            self.say(f"fault {fault.text}: {record.problem}")
            return
        record.ended_at_s = self._since()
        self.say(f"fault {fault.text}: {what} after {fault.for_s:g} s")


def fault_outcomes(
    records: list[FaultRecord], report: dict[str, Any], verdict: str
) -> list[dict[str, Any]]:
    """Each fault for the report: when it fired, the handovers the drone decided between
    it and the next fault (a takeover of a killed master, say), the failsafe the vehicle
    is in at the end if the drone entered it meanwhile (a battery's below the reserve),
    and the mission's verdict."""
    fired = sorted(r.fired_wall for r in records if r.fired_wall is not None)
    failsafe = report["drone"].get("failsafe")
    entries = []
    for record in records:
        entry = record.to_json()
        entry["failsafe_after"] = None
        if record.fired_wall is not None:
            later = [w for w in fired if w > record.fired_wall]
            until = later[0] if later else float("inf")
            if failsafe is not None and record.fired_wall <= failsafe["since"] < until:
                entry["failsafe_after"] = {
                    "cause": failsafe["cause"],
                    "action": failsafe["action"],
                    "reason": failsafe["reason"],
                    "entered_after_s": round(failsafe["since"] - record.fired_wall, 3),
                }
            entry["handovers_after"] = [
                {
                    "from": h["from"],
                    "to": h["to"],
                    "kind": h["kind"],
                    "trigger": h["trigger"],
                    "after_reqnr": h["after_reqnr"],
                    "decided_after_s": round(h["decided_at"] - record.fired_wall, 3),
                }
                for h in report["handovers"]
                if record.fired_wall <= h["decided_at"] < until
            ]
        else:
            entry["handovers_after"] = []
        entry["mission_verdict"] = verdict
        entries.append(entry)
    return entries


def fault_lines(report: Mapping[str, Any]) -> list[str]:
    """The faults and the parts that died, for the terminal's summary."""
    lines = []
    for f in report.get("faults", []):
        if not f["fired"]:
            why = f["problem"] or "its time did not come before the mission ended"
            lines.append(f"fault {f['fault']}: not fired ({why})")
            continue
        moved = ", ".join(
            f"{h['kind']} {h['from']} -> {h['to']} {h['decided_after_s']:.1f} s later"
            for h in f["handovers_after"]
        )
        ended = f", over at {f['ended_at_s']:.1f} s" if f["ended_at_s"] is not None else ""
        failsafe = f.get("failsafe_after")
        entered = (
            f"; failsafe {failsafe['cause']} ({failsafe['action']}) "
            f"{failsafe['entered_after_s']:.1f} s later"
            if failsafe
            else ""
        )
        lines.append(
            f"fault {f['fault']}: at {f['fired_at_s']:.1f} s, reqnr {f['fired_at_reqnr']}, "
            f"master {f['master_before']}{ended}; {moved or 'no handover'}{entered}; "
            f"mission {f['mission_verdict']}" + (f" ({f['problem']})" if f["problem"] else "")
        )
    for death in report.get("parts_died", []):
        lines.append(PartDeath(**{**death, "wall": 0.0}).describe())
    if report.get("ended_early"):
        lines.append(f"run ended early: {report['ended_early']}")
    return lines

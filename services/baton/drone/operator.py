"""An operator's commands to a running mission, as pure decisions: pause, resume, abort,
land now (docs/operating.md, "Operator commands").

No clock, no I/O: ``DroneCore`` holds an ``Operator`` and asks it; the drone service
(``operator_service.py``) and the simulation's drone carry out what it decides. The
rules it keeps:

- A command takes effect between two requests (its driver holds the execution lock),
  and is recorded with the time, the last request served then, what the vehicle is
  told and, once known, what it did.
- *Paused*: the vehicle holds, and the master's next request (above the last one
  served) waits at the drone, not admitted, until a resume. Nothing is decided for it
  meanwhile: once resumed it is admitted and executed like any request, and its reply
  is logged as always, so every replica's program sees the same. A request already
  served is still answered from the cache. A paused master holds its streams, so it
  is neither lost (no takeover) nor is the link (no lost-link failsafe).
- *Ended* (abort, land now): the vehicle returns or lands, and every request admitted
  after it is refused FAILED_PRECONDITION before execution and booked like a failure
  of the vehicle: the master logs it as the call's outcome, so every replica's program
  ends with the same error. An ended mission is not resumed.
- A resume gives the mission the vehicle back after a pause or a failsafe; after a
  pause that stopped a leg, the vehicle flies on to the last Goto's target.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Any

import grpc

from baton.drone.policy import ENDS_A_LEG
from baton.drone.safety import Failsafe
from baton.rpc.errors import StatusError

# The commands, as GetStatus and the report name them.
COMMANDS = ("pause", "resume", "abort", "land_now")
# What an abort may make the vehicle do.
ABORT_ACTIONS = ("rtl", "land")
# Commands kept for GetStatus (the newest).
KEPT = 100
# Who gives a command through Drone.Pause and the others (a ground station's override
# names the station instead).
OPERATOR = "operator"


@dataclass(frozen=True)
class OperatorCommand:
    """One command as the drone took it."""

    command: str  # one of COMMANDS
    at: float  # when it took effect, wall seconds (Unix)
    after_reqnr: int  # the last request served then
    # What the vehicle is told: "hold", "rtl", "land", "goto" (a resume flying on to
    # the last Goto's target), or "" (nothing).
    action: str
    reason: str  # for a person
    by: str = OPERATOR
    vehicle: str = ""  # what the vehicle did ("" until told, or when told nothing)

    def refusal(self, method: str) -> StatusError:
        """What a request gets once this command ended the mission: refused, booked."""
        return StatusError(
            grpc.StatusCode.FAILED_PRECONDITION,
            f"{method}: the mission has ended ({self.reason}); nothing was executed",
        )


@dataclass
class Operator:
    """The operator's hold on the mission: paused, ended, and every command taken."""

    paused: OperatorCommand | None = None
    ended: OperatorCommand | None = None
    # The leg the vehicle flies: the last Goto's request, serialized (None: none, or a
    # command that ends a leg came after it). A resume after a pause flies it on.
    leg: bytes | None = None
    commands: list[OperatorCommand] = field(default_factory=list)

    # -- what a request meets -----------------------------------------------------

    def holds(self, controller_id: int, reqnr: int, master: int, last_reqnr: int) -> bool:
        """Whether a request must wait at the drone: paused, and it is the master's next
        (a request of another controller is refused by the sequencer as always; one
        already served is answered from the cache)."""
        return self.paused is not None and controller_id == master and reqnr > last_reqnr

    def refusal(self, method: str) -> StatusError | None:
        """Why an admitted request is not executed: the mission ended; None otherwise."""
        return None if self.ended is None else self.ended.refusal(method)

    def executed(self, method_name: str, payload: bytes) -> None:
        """A Mobility command of the master was executed: the leg the vehicle flies."""
        if method_name == "Goto":
            self.leg = payload
        elif method_name in ENDS_A_LEG:
            self.leg = None

    # -- the commands ---------------------------------------------------------------

    def pause(
        self, now: float, after_reqnr: int, by: str = OPERATOR, note: str = ""
    ) -> OperatorCommand:
        """The mission paused: the vehicle holds (told nothing when a ground station took
        it over: the station commands it). FAILED_PRECONDITION once ended, or paused."""
        self._not_ended("Pause")
        if self.paused is not None:
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"Pause: the mission is paused already ({self.paused.reason}); Resume goes on",
            )
        action = "hold" if by == OPERATOR else ""
        reason = _reason(f"paused by the {by} after request {after_reqnr}", note)
        self.paused = self._take(OperatorCommand("pause", now, after_reqnr, action, reason, by))
        return self.paused

    def resume(
        self, now: float, after_reqnr: int, failsafe: Failsafe | None, by: str = OPERATOR
    ) -> OperatorCommand:
        """The mission gets the vehicle back, after a pause or a failsafe (the caller clears
        the failsafe); after a pause that stopped a leg the vehicle flies it on.
        FAILED_PRECONDITION once ended, or with neither a pause nor a failsafe."""
        self._not_ended("Resume")
        if self.paused is None and failsafe is None:
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                "Resume: the mission is neither paused nor in failsafe; the mission has the "
                "vehicle",
            )
        what = []
        if self.paused is not None:
            what.append(f"the pause since request {self.paused.after_reqnr}")
        if failsafe is not None:
            what.append(f"the {failsafe.cause} failsafe")
        flies_on = self.paused is not None and failsafe is None and self.leg is not None
        reason = f"resumed by the {by} after request {after_reqnr}: cleared " + " and ".join(what)
        if flies_on:
            reason += "; flying on to the last Goto's target"
        self.paused = None
        return self._take(
            OperatorCommand("resume", now, after_reqnr, "goto" if flies_on else "", reason, by)
        )

    def end(
        self, command: str, action: str, now: float, after_reqnr: int, note: str = ""
    ) -> OperatorCommand:
        """The mission ended (``abort`` with ``rtl`` or ``land``; ``land_now``, whose action
        is ``land``): a pause ends with it (a request waiting wakes to be refused).
        INVALID_ARGUMENT for another action; FAILED_PRECONDITION once ended."""
        if command == "land_now":
            action = "land"
        elif action not in ABORT_ACTIONS:
            raise StatusError(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"Abort: action {action!r} is not one of {', '.join(ABORT_ACTIONS)} "
                "(rtl: return home, land: land where it is)",
            )
        name = "Abort" if command == "abort" else "LandNow"
        self._not_ended(name)
        said = "aborted" if command == "abort" else "told to land now"
        reason = _reason(f"{said} by the operator after request {after_reqnr}: {action}", note)
        self.paused = None
        self.ended = self._take(OperatorCommand(command, now, after_reqnr, action, reason))
        return self.ended

    def acted(self, taken: OperatorCommand, vehicle: str) -> OperatorCommand:
        """What the vehicle did for ``taken`` (accepted, or the autopilot's refusal)."""
        done = replace(taken, vehicle=vehicle)
        self.commands = [done if c is taken else c for c in self.commands]
        if self.paused is taken:
            self.paused = done
        if self.ended is taken:
            self.ended = done
        return done

    def _not_ended(self, method: str) -> None:
        if self.ended is not None:
            raise StatusError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"{method}: the mission has ended ({self.ended.reason}); start a new mission",
            )

    def _take(self, command: OperatorCommand) -> OperatorCommand:
        self.commands = [*self.commands[-(KEPT - 1) :], command]
        return command

    # -- the state file (store.save_commanded) --------------------------------------

    def to_json(self) -> dict[str, Any]:
        """What a restarted drone needs again: the pause, the end, the leg, the commands."""
        return {
            "paused": None if self.paused is None else asdict(self.paused),
            "ended": None if self.ended is None else asdict(self.ended),
            "leg": None if self.leg is None else self.leg.hex(),
            "commands": [asdict(c) for c in self.commands],
        }

    @classmethod
    def from_json(cls, kept: dict[str, Any]) -> Operator:
        commands = [OperatorCommand(**c) for c in kept.get("commands", [])]
        paused, ended, leg = kept.get("paused"), kept.get("ended"), kept.get("leg")
        return cls(
            None if paused is None else OperatorCommand(**paused),
            None if ended is None else OperatorCommand(**ended),
            None if leg is None else bytes.fromhex(leg),
            commands,
        )


def _reason(said: str, note: str) -> str:
    return f"{said} ({note})" if note else said

"""What a controller knows of the masterships, as one value, and its legal combinations.

``ControllerProtocol`` keeps the mastership in several fields, each set where
its event is handled; ``ControllerProtocol.mastership`` reads them as one
``Mastership``. The combinations the protocol never makes are stated once,
here (``Mastership.problems``): the simulation checks them after every event
(invariant ``mastership-legal``) and a running controller after every step
of its core when ``BATON_CHECK_INVARIANTS=1`` (``ControllerCore.ready``).

The words (docs/design.md, "Glossary"): an *epoch* is the drone's number of a
mastership (raft's term); the drone *grants* one (its Connected event) or the
ring's *handover message* makes the receiver master in the epoch the drone
gave it; a *takeover* is the drone's grant to a controller after it lost the
master; a controller is *fenced* when the ring or the drone shows that a
takeover replaced its mastership.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from baton.v1 import ring_pb2


class State(enum.Enum):
    """The controller states of the paper's Figure 3 (named as the paper does;
    the values are the contract's ``ControllerStatus.state``)."""

    ACTIVE = ring_pb2.CONTROLLER_STATE_ACTIVE
    PASSIVE = ring_pb2.CONTROLLER_STATE_PASSIVE
    REPLAY = ring_pb2.CONTROLLER_STATE_REPLAY


@dataclass(frozen=True)
class Mastership:
    """A controller's masterships, as the protocol holds them.

    - ``state``: the paper's PASSIVE, REPLAY or ACTIVE.
    - ``master``: we hold the role (ACTIVE, or to be once caught up).
    - ``epoch``: the epoch of our current or last mastership (0: none yet).
    - ``granted``: the epoch of the drone's last grant to us (0: none).
    - ``took_over_in``: the epoch of our last takeover grant (0: none); a
      taker's while it equals ``epoch`` and we are master.
    - ``owed``: the epoch of a cooperative grant whose handover message we
      wait for (0: none owed).
    - ``over``: the epoch of a mastership of ours whose log is the ring's now
      (handed over, or the ring went on without us acting in it; 0: none).
    - ``flushed_in``: the epoch of the last mastership we flushed a message in.
    - ``fenced`` and ``fenced_in``: a takeover replaced our mastership, in
      that epoch; this state is given up, and the runtime rejoins.
    - ``before_handover``: our epoch before a handover message made us master
      (ours again if the ring shows that role was handed on before we took it;
      the same as the handover's if it was not newer).
    """

    state: State
    master: bool
    epoch: int
    granted: int
    took_over_in: int
    owed: int
    over: int
    flushed_in: int
    fenced: bool
    fenced_in: int
    before_handover: int

    @property
    def taker(self) -> bool:
        """Master by a takeover grant of the epoch we are master in."""
        return self.master and 0 < self.took_over_in == self.epoch

    def problems(self) -> list[str]:
        """Each combination the protocol never makes that this one has, said; [] if legal.

        1. ACTIVE only as master, and never once fenced: a fenced controller's
           log is given up, and an ACTIVE one sends the drone requests.
        2. A master's epoch is a real one (non-zero) and not a mastership of
           ours that is over: the role left with its log.
        3. No epoch we know of is newer than our own: ``granted``,
           ``took_over_in``, ``over`` and ``flushed_in`` are masterships of
           ours, and ``epoch`` is the newest of them, ``before_handover`` too.
        4. What a cooperative grant owes us is of our epoch, or nothing.
        5. The takeover that fenced us is newer than our mastership.
        """
        found: list[str] = []
        if self.state is State.ACTIVE and not self.master:
            found.append("ACTIVE without the role")
        if self.state is State.ACTIVE and self.fenced:
            found.append("ACTIVE though fenced")
        if self.master and self.epoch == 0:
            found.append("master in no epoch")
        if self.master and self.over == self.epoch:
            found.append(f"master in epoch {self.epoch}, a mastership of ours that is over")
        for name, value in (
            ("granted", self.granted),
            ("took over in", self.took_over_in),
            ("over", self.over),
            ("flushed in", self.flushed_in),
        ):
            if value > self.epoch:
                found.append(f"{name} epoch {value}, newer than our epoch {self.epoch}")
        if self.before_handover > self.epoch:
            found.append(f"epoch before the handover {self.before_handover} past {self.epoch}")
        if self.owed not in (0, self.epoch):
            found.append(f"owed the handover message of epoch {self.owed}, ours is {self.epoch}")
        if self.fenced and self.fenced_in <= self.epoch:
            found.append(f"fenced by epoch {self.fenced_in}, not newer than ours {self.epoch}")
        return found

    def __str__(self) -> str:
        role = "master" if self.master else "replica"
        fenced = f", fenced in {self.fenced_in}" if self.fenced else ""
        return (
            f"{self.state.name} {role} in epoch {self.epoch} (granted {self.granted}, "
            f"took over in {self.took_over_in}, owed {self.owed}, over {self.over}, "
            f"flushed in {self.flushed_in}, before the handover {self.before_handover}{fenced})"
        )

"""A controller's ring links as a set: which link carries the history, what a kept or
acknowledged message does to the history, where the ring routes, and how far a
prepared handover's target is behind.

The runtime's ``ControllerNode`` (links: ``ring.PeerLink``) and the simulation's
``SimController`` (links: ``sim.network.RingLink``) both keep one ``RingLinks``;
a link is anything with a ``LinkCore`` that can be sent to and told the history
grew. Opening, stopping and restarting streams stay with the drivers.

The rules:

- The link to the successor (or to the controller the ring routes to around a
  dead successor) carries the history: it gives a peer that restarted what it
  lacks, and says what we hold whenever the history grows or shrinks.
- A handover message enters our history once its new master acknowledged it
  or the ring went on past it (``settle_handovers``), never before: a history
  copy re-sent ahead of it would overtake it.
- A link routed away from is let go if it owes nothing and is neither the
  natural successor nor skipped; owing, it carries only what it owes. The
  natural or a skipped successor's keeps the history; routed back to while
  up, it is given what the history gained since.
- A link down counts for the route once it carries something: one kept open only
  for a handover to come is not routed around.
- A preparation's progress counts the acknowledgements of the stream the count
  began on: a link made since counts from 0.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Generic, Protocol, TypeVar

from baton.controller.history import LogHistory
from baton.controller.link_core import LinkCore
from baton.v1 import drone_pb2, ring_pb2

if TYPE_CHECKING:
    from baton.controller.core import ControllerCore, RouteTo


class Link(Protocol):
    """What ``RingLinks`` needs of a driver's link."""

    core: LinkCore

    def send(self, message: ring_pb2.LogMessage) -> None: ...

    def holds_changed(self) -> None: ...


L = TypeVar("L", bound=Link)


@dataclass(frozen=True)
class Rerouted(Generic[L]):
    """What a driver does after the ring routed to a new successor: give ``link`` the
    history and start its stream again (``needs_history``), start it, and stop
    ``retired`` (None: none to stop)."""

    link: L
    needs_history: bool
    retired: L | None


class RingLinks(Generic[L]):
    """The links of one controller incarnation, by peer id (the module's rules)."""

    def __init__(
        self,
        history: LogHistory,
        successor: Callable[[], int],
        make: Callable[[int, LogHistory | None], L],
    ) -> None:
        self.history = history
        self._successor = successor
        self._make = make
        self.links: dict[int, L] = {}
        # The stream to a preparation's target when it began, and its acknowledgements then.
        self._acked_before_prepare: tuple[L | None, int] = (None, 0)

    def peer(self, pid: int) -> L:
        """The link to ``pid``, made on first use; the successor's carries the history."""
        link = self.links.get(pid)
        if link is None:
            link = self._make(pid, self.history if pid == self._successor() else None)
            self.links[pid] = link
        return link

    def get(self, pid: int | None) -> L | None:
        """The link to ``pid`` if there is one."""
        return None if pid is None else self.links.get(pid)

    def drop_all(self) -> list[L]:
        """Forgets every link (a rejoin with nothing); returns them for the driver to stop."""
        links, self.links = list(self.links.values()), {}
        self._acked_before_prepare = (None, 0)
        return links

    # -- the history --------------------------------------------------------------

    def keep(self, message: ring_pb2.LogMessage, proof: bytes = b"") -> None:
        """``message`` enters the history (``proof``: its holding proof, if computed);
        the successor's link says what we hold."""
        self.history.add(message, proof)
        self.peer(self._successor()).holds_changed()

    def discard(self, lognr: int, epoch: int) -> None:
        """A queued message of a replaced framing leaves the history; the successor's
        link says the master's word again (it may hold the same:
        ``ControllerProtocol.on_sync``)."""
        self.history.discard(lognr, epoch)
        self.peer(self._successor()).holds_changed()

    def say_word(self) -> None:
        """The master's word we say on changed: the successor's link says it."""
        self.peer(self._successor()).holds_changed()

    def handover_acked(self, message: ring_pb2.LogMessage) -> None:
        """Our handover message reached its new master, or the ring went past it: it
        enters our history now (it may never come back round, and our hello counts
        it, so a predecessor never gives it again)."""
        if message.lognr not in self.history:
            self.keep(message)

    def settle_handovers(self, settled: Callable[[int], bool]) -> None:
        """Our unacknowledged handover messages whose role is ``settled`` lose their flag
        (``LinkCore.settle_handovers``) and enter the history, as on an acknowledgement."""
        for link in list(self.links.values()):
            for message in link.core.settle_handovers(settled):
                self.handover_acked(message)

    def send(self, dest: int, message: ring_pb2.LogMessage) -> bool:
        """Sends ``message`` on the link to ``dest``; True when the route must be judged
        again: a link down counts for the route once it carries something."""
        link = self.peer(dest)
        unused = not link.core.used
        link.send(message)
        return unused and not link.core.up

    def send_catch_up(self, core: ControllerCore, target: int) -> list[ring_pb2.LogMessage]:
        """What a handover's target may lack, straight to it (``ControllerCore.catch_up``)."""
        messages = core.catch_up(target, self.history) or []
        link = self.peer(target) if messages else None
        for message in messages:
            assert link is not None
            link.send(message)
        return messages

    # -- the route ------------------------------------------------------------------

    def down_since(self) -> dict[int, float]:
        """For ``ControllerCore.route`` (``RingSight``): since when each link that carries
        something (``LinkCore.used``) has been down; links up or unused are absent."""
        return {
            pid: link.core.down_since
            for pid, link in self.links.items()
            if link.core.down_since is not None and link.core.used
        }

    def rerouted(self, route: RouteTo) -> Rerouted[L]:
        """The ring now sends to ``route.successor``: its link carries the history. The
        previous successor's link is let go if ``RouteTo.retired`` and it owes
        nothing; retired and owing, it carries only what it owes; the natural
        successor's or a skipped one's keeps the history for when the route comes back
        (down, its next stream's greeting gives its peer what it lacks).

        A retired link that kept the history would give its peer our history again
        at every new stream (a framing the ring replaced among it, to a peer that
        rejoins on seeing the ring's, for ever). A link routed back to that kept the
        history and stayed up is given what the history gained since the route left
        it: no greeting gives it, and a taker behind it would wait for it for ever.
        Not by starting its stream again: a stream slower to come up than the
        detection time would be routed around again, and back, for ever."""
        link = self.peer(route.successor)
        needs_history = link.core.history is None
        if needs_history:
            link.core.carry_history(self.history)
        elif link.core.left_at is not None and link.core.up:
            for lognr in list(self.history.above(link.core.left_at)):
                link.send(self.history.get(lognr))
        link.core.left_at = None
        retired = None
        old = self.get(route.previous) if route.previous != route.successor else None
        if old is not None and route.retired is not None:
            if old.core.unacked:
                old.core.let_history_go()
            else:
                retired = self.links.pop(route.previous)
        elif old is not None and old.core.history is not None:
            old.core.left_at = self.history.holds_lognr
        return Rerouted(link, needs_history, retired)

    # -- a prepared handover --------------------------------------------------------

    def preparing(self, target: int) -> None:
        """A preparation began: the stream to ``target`` counts acknowledgements from now."""
        link = self.peer(target)
        self._acked_before_prepare = (link, link.core.counters.acked)

    def progress(self, core: ControllerCore, now: float) -> drone_pb2.PreparationProgress | None:
        """How far a prepared handover's target is behind us (``ControllerCore.progress``)."""
        link = self.get(core.protocol.preparing_for)
        if link is None:
            return core.progress(None)
        before, acked = self._acked_before_prepare
        return core.progress(
            link.core.outbox.unacked_bytes,
            link.core.outbox.waiting_for_ack_s(now),
            link.core.counters.acked - (acked if link is before else 0),
        )

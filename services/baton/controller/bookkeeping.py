"""The effects every controller driver carries out alike: those on its ring links, its
history and its timers.

``ControllerNode`` and the simulation's ``SimController`` each own their I/O (the
drone session, the program, the streams' transport); what one of
``ControllerCore.ready``'s effects does to the ``RingLinks``, the ``LogHistory`` and
the ``TimerTable`` is the same for both, and is done here once.
"""

from __future__ import annotations

from collections.abc import Callable

from baton.controller.core import (
    Arm,
    CoreEffect,
    Disarm,
    Keep,
    KeepMastership,
    Persist,
    Preparing,
    SayWord,
    SettleHandovers,
)
from baton.controller.history import LogHistory
from baton.controller.links import RingLinks
from baton.controller.protocol import ControllerProtocol, Fenced, Unqueued
from baton.controller.timers import TimerTable


class Bookkeeping:
    """Carries out a controller's effects on its ring links, history and timers."""

    def __init__(
        self,
        ring: RingLinks,
        history: LogHistory,
        timers: TimerTable,
        protocol: Callable[[], ControllerProtocol],
    ) -> None:
        self.ring = ring
        self.history = history
        self.timers = timers
        self._protocol = protocol  # the core's now: a rejoin replaces it
        self.fenced_messages = 0  # log messages dropped from a fenced master

    def apply(self, effect: CoreEffect) -> bool:
        """Carries out ``effect`` if it is one of these; False for the driver's own."""
        if isinstance(effect, Persist | Keep):
            self.ring.keep(effect.message, effect.proof)
        elif isinstance(effect, KeepMastership):
            self.history.keep_mastership_epoch(effect.epoch)
        elif isinstance(effect, Arm | Disarm):
            self.timers.apply(effect)
        elif isinstance(effect, SettleHandovers):
            self.ring.settle_handovers(self._protocol().handover_settled)
        elif isinstance(effect, Preparing):
            self.ring.preparing(effect.target)
        elif isinstance(effect, Fenced):
            self.fenced_messages += 1
        elif isinstance(effect, SayWord):
            self.ring.say_word()
        elif isinstance(effect, Unqueued):
            self.fenced_messages += 1
            self.ring.discard(effect.lognr, effect.epoch)
        else:
            return False
        return True

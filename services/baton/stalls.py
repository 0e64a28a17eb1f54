"""Waits that last too long, named: the one way a part says it is stuck. Pure.

A controller whose next log message does not come, a ring stream that stays
down, a drone whose master holds no stream: each is normal for a moment and
a stall after a few seconds. A part lists the conditions that hold now (a key
and a text for a person); ``StallWatch`` remembers since when each one
holds and reports those older than its threshold, with their age, for the
part's log (``due_for_log``) and its GetStatus ``waiting`` field. Times are
given by the caller, so the rules are tested with chosen times.
"""

from __future__ import annotations

from dataclasses import dataclass, field

# A condition that holds this long is a stall (seconds of wall time).
STALL_AFTER_S = 3.0
# A stall goes on being logged this often.
LOG_EVERY_S = 5.0


@dataclass
class StallWatch:
    """Since when each named condition has held; which ones are stalls."""

    threshold_s: float = STALL_AFTER_S
    log_every_s: float = LOG_EVERY_S
    _since: dict[str, float] = field(default_factory=dict)
    _logged_at: float | None = None

    def update(self, now: float, holding: dict[str, str]) -> list[str]:
        """The stalls now, as texts with their age; ``holding`` maps key -> text."""
        for key in [k for k in self._since if k not in holding]:
            del self._since[key]
        stalls = []
        for key, text in holding.items():
            since = self._since.setdefault(key, now)
            if now - since >= self.threshold_s:
                stalls.append(f"{text} for {now - since:.0f} s")
        if not stalls:
            self._logged_at = None
        return stalls

    def due_for_log(self, now: float, stalls: list[str]) -> bool:
        """True when there are stalls and they were not logged in the last ``log_every_s``."""
        if not stalls:
            return False
        if self._logged_at is None or now - self._logged_at >= self.log_every_s:
            self._logged_at = now
            return True
        return False

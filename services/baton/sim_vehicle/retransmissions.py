"""Which MAVLink commands are retransmissions of one the vehicle already acted on.

A ground station sends a command again when its COMMAND_ACK does not come
in time. MAVSDK 4.1 does it 0.5 s after each copy, 3 times, and leaves
COMMAND_LONG's ``confirmation`` at 0, so the field MAVLink meant for this
cannot be relied on; COMMAND_INT has no such field.
When the acknowledgement was lost (or the vehicle was too slow to send it),
not the command, the vehicle has already acted: acting and counting again
would fly a second takeoff and make the effects file report a double
execution that never left the drone service.

The rule (docs/design.md, "Counting side effects where they happen"). A
command is a copy of the flight command of the same kind (sender's system
and component id, command id) the vehicle last acted on if it is the same
message type with every parameter equal (``confirmation`` aside), and

1. it reached the vehicle before the vehicle acknowledged that one: the
   sender cannot have known it was acted on (a vehicle stopped or busy
   finds them queued together); or, if that one is also the latest flight
   command the vehicle acted on from this sender,
2. it came ``RETRY_AFTER_S`` to ``RETRANSMISSION_WINDOW_S`` after the
   previous copy: the sender's acknowledgement timeout ran out; or
3. it is a COMMAND_LONG with ``confirmation`` > 0, the sender's own mark,
   within ``RETRANSMISSION_WINDOW_S`` of the previous copy.

A copy is acknowledged ACCEPTED, as the original was, and neither acted on
nor counted again. Rules 2 and 3 hold for the sender's latest flight command
only: a sender re-sends a command while it waits for its ACK, and the drone
service sends one flight command at a time (telemetry requests aside, which
are not tracked), so once a newer one was acted on the older was answered:
an arm after a disarm, the cruise speed re-sent after a goto, are new. A
copy of a command the vehicle did not act on (refused, or its first
transmission lost) is handled as new. Times are when the
datagram reached the vehicle's socket (the kernel's stamp), so a vehicle
that was SIGSTOPped or slow to read does not blur them.

The limit: nothing in a MAVLink command tells a retransmission from the
sender asking for the same thing again. A sender that repeats an identical
command with no other flight command in between, 0.4 to 1 s after the
previous copy was acknowledged, is counted once and not acted on again (the
drone re-executing a goto at once is counted twice, and so is a goto
re-executed after the cruise speed went out; one re-executed alone after
such a pause is not caught). A retransmission whose ACK was lost is
counted twice if it comes later than 1 s after the previous copy (a sender
slower than MAVSDK) or after the same sender's next flight command (a
sender with several in flight).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

# MAVSDK re-sends an unacknowledged command 0.5 s after the previous copy
# (measured: 0.501 s); its retransmission comes no sooner than this ...
RETRY_AFTER_S = 0.4
# ... nor later than this after the previous copy (0.5 s plus slack for a
# loaded host); the band between them is the rule's blind spot.
RETRANSMISSION_WINDOW_S = 1.0


@dataclass(frozen=True)
class CommandKey:
    """What makes two command messages the same command: sender, type, every parameter."""

    sender: tuple[int, int]  # (system id, component id)
    message: str  # COMMAND_LONG or COMMAND_INT
    command: int
    params: tuple[float | str, ...]  # NaN as "nan": NaN != NaN


def command_key(msg: Any) -> CommandKey:
    """The key of a pymavlink COMMAND_LONG or COMMAND_INT (``confirmation`` left out)."""
    kind = msg.get_type()
    if kind == "COMMAND_LONG":
        values = [getattr(msg, f"param{n}") for n in range(1, 8)]
    else:
        values = [msg.param1, msg.param2, msg.param3, msg.param4, msg.frame, msg.x, msg.y, msg.z]
    params = tuple("nan" if isinstance(v, float) and math.isnan(v) else v for v in values)
    return CommandKey((msg.get_srcSystem(), msg.get_srcComponent()), kind, msg.command, params)


@dataclass
class _Acted:
    key: CommandKey
    effect_seq: int  # the effect the vehicle recorded for it
    acked_at: float  # when the vehicle sent its COMMAND_ACK
    last_arrival: float  # when its latest copy reached the vehicle


class Retransmissions:
    """The commands acted on recently, to recognise their retransmissions.

    Times are wall-clock seconds: arrivals as the kernel stamped them,
    acknowledgements as the vehicle sent them.
    """

    def __init__(
        self, retry_after_s: float = RETRY_AFTER_S, window_s: float = RETRANSMISSION_WINDOW_S
    ) -> None:
        self.retry_after_s = retry_after_s
        self.window_s = window_s
        # (sender, command id) -> the last command of that kind acted on.
        self._acted: dict[tuple[tuple[int, int], int], _Acted] = {}
        # Sender (system id, component id) -> its latest flight command acted on.
        self._latest: dict[tuple[int, int], CommandKey] = {}

    def original(self, key: CommandKey, confirmation: int | None, arrived_at: float) -> int | None:
        """The effect sequence number of the command this one copies; None if it is new.

        ``confirmation`` is COMMAND_LONG's field, None for COMMAND_INT.
        """
        self._forget_before(arrived_at - self.window_s)
        acted = self._acted.get((key.sender, key.command))
        if acted is None or acted.key != key:
            return None
        gap = arrived_at - acted.last_arrival
        latest = self._latest.get(key.sender) == key
        copy = arrived_at < acted.acked_at or (
            latest
            and (
                self.retry_after_s <= gap <= self.window_s
                or (confirmation is not None and confirmation > 0 and gap <= self.window_s)
            )
        )
        if not copy:
            return None
        acted.last_arrival = max(acted.last_arrival, arrived_at)
        return acted.effect_seq

    def acted(self, key: CommandKey, effect_seq: int, arrived_at: float, acked_at: float) -> None:
        """Notes that the vehicle acted on ``key`` (recorded as effect ``effect_seq``)."""
        self._acted[key.sender, key.command] = _Acted(key, effect_seq, acked_at, arrived_at)
        self._latest[key.sender] = key

    def _forget_before(self, cutoff: float) -> None:
        stale = [k for k, a in self._acted.items() if max(a.acked_at, a.last_arrival) < cutoff]
        for key in stale:
            del self._acted[key]

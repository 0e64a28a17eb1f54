"""Bugs the simulation found in the code it runs, and the scenarios that show them.

The default fault mix keeps each finding's scenario out where it can, so
that the CI run stays green until they are fixed; ``SimOptions.allow``
(``python -m baton.sim --allow F3``) puts a scenario back, and
``tests/sim/test_findings.py`` holds one strict xfail per finding.

What each finding was, how it was fixed and which seeds showed it is told in
docs/simulation.md, "Findings", "The findings registry (F1-F12)". Here: the
findings still open, and those whose keep-outs the fault mix keeps.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Finding:
    """One bug: what goes wrong, where, and what the default mix leaves out because of it."""

    code: str
    title: str
    where: str
    kept_out: str


# Fixed findings whose allow flag still changes the mix: F3's and F4's keep-outs
# stay (docs/simulation.md, "The findings registry"), and ``--allow F9`` makes
# kills prefer a controller owed the acknowledgement of a handover message.
STILL_ALLOWED = frozenset({"F3", "F4", "F9"})

FINDINGS = {
    f.code: f
    for f in (
        Finding(
            "F1",
            "a Handover decided before the old master was ever granted strands the mission: "
            "the old master, PASSIVE, ignores the notice; the new master, refused at start, "
            "never asks the drone again",
            "node.py on_stream_notice (closes the session when not ACTIVE); only the old "
            "master's handover message makes a new master connect. Narrowed: a handover "
            "from an initial master not connected, with nothing served, is a takeover "
            "(Sequencer.handover_must_take_over)",
            "Handover calls while the drone's master is not ACTIVE with its stream up, or "
            "while another Handover is queued",
        ),
    )
}

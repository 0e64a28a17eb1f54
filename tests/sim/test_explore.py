"""Every order of the events at small scope (baton.sim.explore): the figures are in
docs/simulation.md, "Exhaustive exploration"."""

from __future__ import annotations

import pytest

from baton.sim import SimOptions
from baton.sim.explore import FAULTS, Scope, explore, main
from baton.sim.mutations import mutated

# CI's share: two controllers, two calls, the handover between them, a message
# delivered twice at any moment (about 12 s on one core).
CI_SCOPE = Scope(controllers=2, calls=2, handover_after=1, fault="dup", window=0.0)


def test_every_order_of_a_handover_and_a_duplicated_message_holds() -> None:
    result = explore(CI_SCOPE)
    assert result.complete and result.terminal > 0
    assert result.distinct > 100, result.summary()
    assert not result.found, "\n".join(f.report() for f in result.found)


def test_the_explorer_finds_a_restarted_master_that_goes_active_on_its_own_word() -> None:
    """defect3-active, a patch of the shipped ``ControllerProtocol.start``: proof that
    the exploration can fail. The masterships' invariant sees it in the first state
    (ACTIVE as master in no epoch), before any kill: a restart only repeats it."""
    scope = Scope(controllers=2, calls=1, handover_after=1, fault="kill", window=0.0)
    with mutated("defect3-active"):
        result = explore(scope, options=SimOptions(kill_master=True))
    assert result.found, result.summary()
    found = result.found[0]
    assert any(v.oracle == "mastership-legal" for v in found.violations), found.report()
    assert any("master in no epoch" in v.detail for v in found.violations), found.report()


def test_the_command_line_reports_a_scope(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--controllers", "2", "--calls", "1", "--handover-after", "0"]) == 0
    assert "2 controllers, 1 calls, no handover, fault none" in capsys.readouterr().err


# Every fault with two controllers; with three, those measured to finish within
# about two minutes (docs/simulation.md, "Exhaustive exploration").
SLOW_SCOPES = [(2, fault) for fault in FAULTS] + [(3, "none"), (3, "dup"), (3, "kill")]


@pytest.mark.slow
@pytest.mark.parametrize(("controllers", "fault"), SLOW_SCOPES)
def test_every_order_at_small_scope_holds(controllers: int, fault: str) -> None:
    scope = Scope(controllers=controllers, calls=2, handover_after=1, fault=fault, window=0.0)
    result = explore(scope, max_states=200_000)
    assert result.complete, result.summary()
    assert not result.found, "\n".join(f.report() for f in result.found)

"""The invariants (baton.sim.invariants), checked after every event of a run."""

from __future__ import annotations

import pytest

from baton.controller.protocol import State
from baton.sim import SimOptions, run_seed
from baton.sim.invariants import INVARIANTS
from baton.sim.mutations import mutated
from baton.sim.world import World

# Seeds per mode checked at every event here; the sweeps of docs/simulation.md
# ("Invariants") check every event of 1,000 per mode.
SAMPLE = 25
MODES = {
    "default": SimOptions(),
    "lose-master": SimOptions(lose_master=True),
    "prepared": SimOptions(prepared=True),
    "lose-master prepared": SimOptions(lose_master=True, prepared=True),
    "policy nearest": SimOptions(policy="nearest"),
    "stall-new-master": SimOptions(stall_new_master=True),
}


@pytest.mark.parametrize("mode", sorted(MODES))
def test_every_invariant_holds_after_every_event_of_a_sample(mode: str) -> None:
    broken = []
    for seed in range(SAMPLE):
        outcome = run_seed(seed, MODES[mode])
        broken += [f"{outcome.replay}: {v}" for v in outcome.violations if v.oracle in INVARIANTS]
    assert not broken, "\n".join(broken)


def _started(seed: int, events: int) -> World:
    """A world of ``seed`` run for ``events`` events."""
    world = World(seed, SimOptions())
    world.begin()
    world.loop.run(world.deadline, events)
    return world


def test_two_masters_active_in_one_epoch_are_reported_with_the_event_and_the_time() -> None:
    world = _started(1, 300)
    try:
        master = world.controller(world.drone.seq.master)
        other = next(c for c in world.live_controllers() if c is not master)
        assert master.protocol.state is State.ACTIVE
        other.protocol.state, other.protocol.master = State.ACTIVE, True
        other.protocol.epoch = master.protocol.epoch
        assert world.invariants is not None
        world.invariants.after_event()
        [violation] = world.invariants.violations
        assert violation.oracle == "one-active-master-per-epoch"
        assert f"after event {world.loop.events}, t={world.loop.now:.4f}s" in violation.detail
    finally:
        world.close()


def test_a_drone_watermark_that_moves_back_is_reported() -> None:
    world = _started(1, 600)
    try:
        cache = world.drone.seq.cache
        assert cache.watermark > 0 and world.invariants is not None
        world.invariants.after_event()
        cache.watermark -= 1
        world.invariants.after_event()
        assert [v.oracle for v in world.invariants.violations] == ["drone-never-moves-back"]
    finally:
        world.close()


# defect10's first seed: the invariant fires where no oracle does (the oracles'
# first seed is 7).
DEFECT10_SEED = 1


def test_a_drone_restart_that_forgets_its_state_breaks_an_invariant_at_once() -> None:
    """defect10: the restarted drone starts as a new drone (epoch 1, reqnr 0)."""
    with mutated("defect10"):
        outcome = run_seed(DEFECT10_SEED)
    names = {v.oracle for v in outcome.violations}
    assert "drone-never-moves-back" in names, outcome.report()


def test_invariants_are_not_checked_when_turned_off() -> None:
    world = World(1, SimOptions(check_every=0))
    assert world.invariants is None and world.loop.after_event is None
    world.close()


def test_a_killed_programs_local_answer_the_drone_never_saw_is_not_a_lost_reply() -> None:
    """Default mix, seed 14407: master 0 answered a Clock call (request 9) that reached
    replica 2's program; 2 was killed, and 0, fenced by 2's takeover, dropped it. No
    live controller held 9 and the drone never saw it, but nothing depended on it: the
    taker frames it anew, and the oracle then holds the killed incarnation only to
    what the drone accepted. The invariant fired at the fence, before the framing."""
    outcome = run_seed(14407, SimOptions())
    assert outcome.ok, outcome.report()


def test_a_framing_in_an_older_epoch_that_shows_the_same_entries_is_the_ring_log() -> None:
    """--lose-master 10451: taker 3 held message 1 as lost master 6 framed it in epoch 1
    (a Clock.Sleep), controller 1 as master 4 framed it again in epoch 2, entry for
    entry the same. The invariant compared epochs and fired; what matters to the
    programs is what they see, which is the same (every oracle held)."""
    outcome = run_seed(10451, SimOptions(lose_master=True))
    assert outcome.ok, outcome.report()

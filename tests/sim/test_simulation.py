"""The deterministic simulation (issue 9): many seeds in CI, exact replays, mutations caught.

A failing seed's report ends with the command that replays it exactly,
e.g. ``.venv/bin/python -m baton.sim --seed 1234``; add ``--trace`` to see
every event. ``pytest tests/sim -m slow`` runs 100,000 seeds on every core.
"""

from __future__ import annotations

import functools
import multiprocessing
import os
import subprocess
import sys
from collections import Counter

import pytest

from baton.sim import SimOptions, run_seed
from baton.sim.cli import main
from baton.sim.lying import LIES
from baton.sim.mutations import MUTATIONS, mutated
from baton.sim.world import Outcome, World, run_seeds

# The default mix in CI: what fits CI's 25 minutes on 2 cores beside the end-to-end
# tests (the sweeps take both cores while they run); the wider ranges (every mode's
# 0-19999 in docs/simulation.md) are swept by hand with `baton.sim --seeds`.
CI_SEEDS = 500
SLOW_SEEDS = 100_000
# Each mutation must make some seed fail within this many.
MUTATION_BUDGET = 300
# Issue 10's scenario (--lose-master) in CI (docs/design.md, "The deterministic
# simulation", the lose-the-master scenario).
LOSE_MASTER_SEEDS = 300


def _sweep(seeds: range, options: SimOptions | None = None, chunk: int = 250) -> list[Outcome]:
    """Runs ``seeds`` on every core (``run_seeds``' share per worker process): the outcomes
    that failed or that a known finding struck. A seed runs the same in any process
    (``test_a_seed_replays_exactly_in_another_process``)."""
    chunks = [range(start, min(start + chunk, seeds.stop)) for start in seeds[::chunk]]
    # spawn, not fork: other tests in this process may have gRPC threads running.
    context = multiprocessing.get_context("spawn")
    with context.Pool(min(os.cpu_count() or 1, len(chunks))) as pool:
        parts = pool.imap_unordered(functools.partial(run_seeds, options=options), chunks)
        return [outcome for part in parts for outcome in part]


def _failures(outcomes: list[Outcome]) -> str:
    failed = [o for o in outcomes if o.failed]
    failed.sort(key=lambda o: o.seed)
    return f"{len(failed)} seeds failed:\n" + "\n".join(o.report() for o in failed[:10])


def test_a_seed_replays_exactly() -> None:
    first, again = (run_seed(11, SimOptions(trace=True)) for _ in range(2))
    assert first.trace and first.events > 100
    assert (again.digest, again.events, again.trace) == (first.digest, first.events, first.trace)


def test_a_seed_replays_exactly_in_another_process() -> None:
    """What the replay line does: a new interpreter, another hash seed, the same run."""
    outcome = run_seed(11)
    done = subprocess.run(
        [sys.executable, "-m", "baton.sim", "--seed", "11"],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONHASHSEED": "12345"},
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert f"{outcome.events} events" in done.stdout and outcome.digest in done.stdout


def test_ci_seeds_hold_every_oracle(sim_seeds: int | None) -> None:
    total = sim_seeds or CI_SEEDS
    outcomes = _sweep(range(total))
    assert not any(o.failed for o in outcomes), _failures(outcomes)
    # F7 (findings.py) strikes where the mix cannot keep it out: rarely.
    struck = [o.seed for o in outcomes if o.known]
    assert len(struck) <= total // 100, f"known finding struck in seeds {struck}"


def test_lose_master_seeds_hold_every_oracle() -> None:
    """The master killed for good or cut off at every point (mid-flush, right after a
    handover decision, any time, its drone link cut): every seed holds every oracle."""
    outcomes = _sweep(range(LOSE_MASTER_SEEDS), SimOptions(lose_master=True))
    assert not any(o.failed for o in outcomes), _failures(outcomes)


# Prepared handovers (--prepared: every scripted handover is prepared) in CI.
PREPARED_SEEDS = 150  # CI_SEEDS says why; wider ranges by hand


def test_prepared_handover_seeds_hold_every_oracle() -> None:
    """Every scripted handover prepared (docs/design.md, "Prepared handover"), under the
    default mix's faults: every oracle holds, every prepared handover's record is
    prepared or forced at the timeout, and both kinds happen."""
    outcomes = [run_seed(seed, SimOptions(prepared=True)) for seed in range(PREPARED_SEEDS)]
    assert not any(o.failed for o in outcomes), _failures(outcomes)
    carried_out = sum(o.prepared["prepared"] for o in outcomes)
    forced = sum(o.prepared["forced"] for o in outcomes)
    assert carried_out > PREPARED_SEEDS // 4, carried_out
    assert forced > PREPARED_SEEDS // 20, forced
    # Some moved on the master's word between requests (ReportPreparation), some at
    # a request: both interleavings are explored.
    on_the_word = sum(o.prepared["on the word"] for o in outcomes)
    assert 0 < on_the_word < carried_out, (on_the_word, carried_out)


def test_lose_master_prepared_seed_15328_holds_every_oracle() -> None:
    """Was a strict xfail: ring [2, 0, 1], watermark 4 (every controller held messages
    1-4); 0 restarted with nothing, master 1 killed for good, and 2, fenced by 1's
    takeover, dropped its log to rejoin with nothing; taker 2 waited for ever for
    requests the drone let go of. Since a master that does not serve is taken over
    whatever streams it holds (``Sequencer.takeover_due``), the seed no longer takes
    that path (with that rule turned off it still fails). The pattern,
    a watermark from a controller routing around another, stays open in principle
    (docs/simulation.md, the open findings)."""
    outcome = run_seed(15328, SimOptions(lose_master=True, prepared=True))
    assert outcome.ok, outcome.report()


def test_lose_master_seed_14453_a_taker_does_not_wait_on_a_word_its_sender_lost() -> None:
    """Master 2's message 3 was on a reordering link when taker 3 re-opened the stream;
    2, fenced, rejoined with nothing, and 3 waited for ever for the 3 that 2's earlier
    word had promised (every controller then held 1-2 and queued 4)."""
    outcome = run_seed(14453, SimOptions(lose_master=True))
    assert outcome.ok, outcome.report()


def test_lose_master_seed_13253_a_fenced_master_keeps_what_the_drone_let_go() -> None:
    """Master 1 was taken over (watermark 3, which its call carried though the reply was
    lost), the taker died for good, and the replica restarted with nothing: 1, fenced,
    dropped its whole log, and the next taker waited for ever for requests 1-3 that no
    live controller held. A fenced master now keeps its log up to the drone's watermark
    at the takeover (``kept_when_fenced``, ``baton-takeover-watermark``)."""
    outcome = run_seed(13253, SimOptions(lose_master=True))
    assert outcome.ok, outcome.report()


def test_lose_master_prepared_seed_198_a_takeover_back_to_us_keeps_our_log() -> None:
    """Master 1, ACTIVE in epoch 5, never heard of the forced handover to the dead 0; the
    drone took the role back to it (epoch 7), and it rejoined with nothing, dropping the
    only copy of the log (``ControllerProtocol.taken_back``)."""
    outcome = run_seed(198, SimOptions(lose_master=True, prepared=True))
    assert outcome.ok, outcome.report()


def test_lose_master_lying_seeds_a_takers_own_handover_message_is_believed() -> None:
    """On a signed ring, a taker's own handover message sent on in its own name was
    refused by every replica (``authenticity._made_by_the_granted``)."""
    outcomes = [run_seed(seed, SimOptions(lose_master=True, lying=True)) for seed in (22, 100)]
    assert not any(o.failed for o in outcomes), _failures(outcomes)


# Beyond CI's range, fixed: a new master's give-up of a retained reply (2456, 2707),
# killed replicas held to a framing a takeover replaced (the oracle), the drone's watch
# stopped while a program still had a given-up call to settle (2957, the sim).
LOSE_MASTER_BEYOND = (2260, 2342, 2398, 2456, 2566, 2707, 2957, 3231, 3518)


def test_lose_master_seeds_beyond_ci_that_were_fixed_hold_every_oracle() -> None:
    outcomes = [run_seed(seed, SimOptions(lose_master=True)) for seed in LOSE_MASTER_BEYOND]
    assert not any(o.failed for o in outcomes), _failures(outcomes)


@pytest.mark.slow
@pytest.mark.timeout(3 * 3600)
def test_many_seeds_hold_every_oracle(sim_seeds: int | None) -> None:
    total = sim_seeds or SLOW_SEEDS
    outcomes = _sweep(range(total), chunk=500)
    assert not any(o.failed for o in outcomes), _failures(outcomes)
    struck = [o.seed for o in outcomes if o.known]
    assert len(struck) <= total // 100, f"known finding struck in {len(struck)} seeds"


def test_the_oracles_catch_every_mutation(monkeypatch: pytest.MonkeyPatch) -> None:
    """Known defects of issues 9 and 10, put back one at a time, each make some seed fail.

    A mutation that needs a scenario outside the default mix (``Mutation.options``,
    e.g. --lose-master, where known findings strike) counts only seeds that hold
    every oracle without it."""
    rows = []
    for name, mutation in MUTATIONS.items():
        options = SimOptions(mutation=name, **mutation.options)
        first: Outcome | None = None
        tried = 0
        for seed in range(MUTATION_BUDGET):
            tried += 1
            for target, attribute, value in mutation.patches():
                monkeypatch.setattr(target, attribute, value)
            outcome = run_seed(seed, options)
            monkeypatch.undo()
            if outcome.failed and (
                not mutation.options or _holds(run_seed(seed, SimOptions(**mutation.options)))
            ):
                first = outcome
                break
        oracles = sorted({v.oracle for v in first.violations}) if first else []
        rows.append((name, first.seed if first else None, tried, ", ".join(oracles)))
    table = ["| mutation | first failing seed | seeds tried | oracle that fired |", "|-|-|-|-|"]
    table += [f"| {name} | {seed} | {tried} | {oracles} |" for name, seed, tried, oracles in rows]
    print("\n" + "\n".join(table))
    missed = [name for name, seed, _, _ in rows if seed is None]
    assert not missed, f"no seed in {MUTATION_BUDGET} caught {missed}"
    # Undone: the real code passes the same seeds again.
    assert all(
        _holds(run_seed(seed, SimOptions(**MUTATIONS[name].options)))
        for name, seed, _, _ in rows
        if seed is not None
    )


def _holds(outcome: Outcome) -> bool:
    return outcome.ok and not outcome.known


def test_a_failing_seed_prints_the_command_that_replays_it(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with mutated("defect10"):
        seed = next(s for s in range(MUTATION_BUDGET) if run_seed(s).failed)
    assert main(["--seed", str(seed), "--mutation", "defect10"]) == 1
    report = capsys.readouterr().out
    assert f"replay: .venv/bin/python -m baton.sim --seed {seed} --mutation defect10" in report
    assert main(["--seed", str(seed)]) == 0
    assert f"seed {seed}: ok" in capsys.readouterr().out


# The handover policy (--policy: a corridor of stations with radio range, the drone's
# pure policy deciding at its ticks, its handovers prepared) in CI.
POLICY_SEEDS = 100


def test_policy_seeds_hold_the_oracles_and_prepare_their_handovers() -> None:
    """--policy nearest over POLICY_SEEDS seeds: every oracle holds (every command and
    picture acted on once, one master per epoch, every controller done with the same
    replies, nothing held, no stall); the policy's prepared handovers happen and end both
    ways (on the master's word or at a request, and forced at the timeout). A master
    taken over out of radio range follows the ring as a replica (before, it stayed
    ACTIVE: seeds 3, 48 and 93 stalled), one regranted while ACTIVE in a mastership a
    takeover replaced rejoins first (seed 71 held a handover message queued for ever),
    and a master's fresh self is granted a new epoch, whose word drops its earlier
    self's message queued everywhere (seed 48, bounded until then: docs/design.md,
    "Wider sweeps")."""
    outcomes = [run_seed(seed, SimOptions(policy="nearest")) for seed in range(POLICY_SEEDS)]
    failed = [o for o in outcomes if o.failed]
    assert not failed, _failures(failed)
    ended = Counter[str]()
    for o in outcomes:
        ended.update(o.policy_switches)
    # How the handovers end is a share that moves with the timing (message sizes set
    # the virtual network's delays: a field added to the drone's notice moved it from
    # 55 to 50 of 100); what must hold is that each way is common.
    assert ended["prepared on the word"] > POLICY_SEEDS // 4, ended
    assert ended["prepared at a request"] > 0, ended
    assert ended["forced at the timeout"] > POLICY_SEEDS // 10, ended


def test_a_master_regranted_while_active_in_a_replaced_mastership_rejoins_first() -> None:
    """--policy nearest seeds 71 and 177: a master cut off before it heard of a forced
    handover; the new master is taken over, and the role comes back to the old master by
    a handover message while its link is up again. The drone's Connected says the newest
    takeover's epoch, above the one the old master is ACTIVE in: it rejoins with nothing
    and takes the role from the handover message (before, it went on ACTIVE in the old
    mastership with the message queued for ever: bounded)."""
    for seed in (71, 177):
        outcome = run_seed(seed, SimOptions(policy="nearest"))
        assert not outcome.failed, _failures([outcome])


def test_a_taker_after_a_drone_restart_holds_what_the_drone_let_go() -> None:
    """--policy nearest seed 201: the drone restarted and forgot its watermark (3), and
    said 0 to a taker restarted with nothing, which went ACTIVE at once and waited for
    ever for request 1's retained reply (the cache had let 1-3 go). The store keeps the
    watermark: the taker waits until the ring gave it request 3."""
    outcome = run_seed(201, SimOptions(policy="nearest"))
    assert not outcome.failed, _failures([outcome])


def test_the_programs_start_once_a_station_that_never_answered_leaves_radio_range() -> None:
    """--policy nearest 6960, --policy predictive 6651 (liveness, the simulation's own):
    a controller restarted while cut from the drone never asked it, then left radio
    range; the programs wait for the stations in range, but nothing asked again when
    the range changed, so they never started."""
    for seed, policy in ((6960, "nearest"), (6651, "predictive")):
        outcome = run_seed(seed, SimOptions(policy=policy))
        assert outcome.ok, outcome.report()


def test_a_killed_replica_is_held_to_the_calls_the_drone_had_seen_when_it_died() -> None:
    """--policy predictive 3569 (same-replies, the oracle's): replica 2 consumed master
    4's Clock reading of request 16 and was killed; 4, fenced, died with it, and taker
    0 framed 16 anew under another log number. The drone had executed nothing above 15:
    the reading never left the dead replica, and nothing acted on it."""
    outcome = run_seed(3569, SimOptions(policy="predictive"))
    assert outcome.ok, outcome.report()


def test_an_old_master_whose_log_a_takeover_replaced_hands_nothing_over() -> None:
    """--policy predictive 7057 (a ProtocolError stopped controller 2): master 2, ACTIVE
    in epoch 1 with requests unflushed, never heard the drone hand over from it; a
    takeover (epoch 3) framed those requests anew, and the role came back to 2 by a
    handover message queued behind the ring's log. The notice of the next switch made 2
    hand its epoch-1 log over as the new master's. The notice now carries the drone's
    newest takeover epoch, and 2 rejoins with nothing."""
    outcome = run_seed(7057, SimOptions(policy="predictive"))
    assert outcome.ok, outcome.report()


def test_policy_seed_132_holds_every_oracle() -> None:
    """--policy nearest seed 132 (same-replies): master 4, cut off by a forced handover
    it never heard, answered Clock calls 7-10 itself and flushed them to 2; a takeover
    (3, epoch 3) framed 8-10 anew with another reading of request 9. Before those
    messages reached 2, the policy made 2 master by takeover: it went ACTIVE on 4's
    reading (the drone sent it only the replies above what it holds), and the drone
    executed its requests 16 and 17. Now the taker is given the retained replies it
    holds too, with their epochs, finds request 9 of epoch 3 other than its epoch-1
    framing, and rejoins with nothing before it sends a request."""
    outcome = run_seed(132, SimOptions(policy="nearest"))
    assert outcome.ok, outcome.report()


def test_lose_master_seed_3166_holds_every_oracle() -> None:
    """--lose-master seed 3166. First (liveness), broken by seed 132's fix: a taker
    holding a request framed in an older epoch than the one the drone keeps rejoined,
    got the same old framing again from the ring, for ever; its fresh self now refuses
    that framing. Since the sync frames that say the master's word on (SayWord) moved
    its events (same-replies): taker 3 adopted requests 11-12 from the drone's retained
    replies in epoch 3, but its one call saying so was refused (a handover overtook
    it); its next mastership (epoch 5) did not say it, and a later taker took the lost
    master's give-up of 12 for the ring's. An adoption is now said until the drone
    answered a call that carried it."""
    outcome = run_seed(3166, SimOptions(lose_master=True))
    assert outcome.ok, outcome.report()


def test_lose_master_seed_3872_holds_every_oracle() -> None:
    """--lose-master seed 3872 (liveness): controller 3 routed around 2 to 6 and back;
    its link to 6, which still owed an acknowledgement, kept carrying the history and
    gave 6 a fenced master's message 1 again at every new stream, so 6 rejoined on
    seeing the ring's message 1 for ever, and message 2 never got past it. A link
    routed away from now carries only what it owes."""
    outcome = run_seed(3872, SimOptions(lose_master=True))
    assert outcome.ok, outcome.report()


def test_lose_master_prepared_seed_8669_holds_every_oracle() -> None:
    """--lose-master --prepared seed 8669 (liveness): controller 3 routed around 0 to 2,
    around 0 and 2 to 1, back to 0, and (0 lost for good) around 0 to 2 again. Its
    stream to 2, up since before 3 held anything, still carried the history (kept
    while 2 was skipped), so it was taken for the successor's and not started again:
    2, the drone's taker, never got messages 1-3 and waited for them for ever. A link
    the route leaves notes the history's top (``LinkCore.left_at``); routed back to
    while up, it is sent every message kept since."""
    outcome = run_seed(8669, SimOptions(lose_master=True, prepared=True))
    assert outcome.ok, outcome.report()


def test_policy_predictive_seed_19072_holds_every_oracle() -> None:
    """--policy predictive seed 19072 (bounded): taker 1 (epoch 8) held a framing of
    requests 17-19 (messages 13-15 of epoch 3) that the takeover of epoch 4 had
    numbered otherwise (13 of epoch 4, then 14 of epoch 7), and handed over in message
    16 (after request 19), then rejoined. Every controller held the ring's 14 (through
    request 23) with 16 queued above a gap at 15 that only the other framing had, and
    repaired it every 8 s for ever. A queued message that follows fewer requests than
    our log holds is dropped."""
    outcome = run_seed(19072, SimOptions(policy="predictive"))
    assert outcome.ok, outcome.report()


def test_policy_nearest_seed_13594_holds_every_oracle() -> None:
    """--policy nearest seed 13594 (liveness), found by the sweep of the drone's first
    rule on replaced numberings: taker 1 (epoch 8) framed from message 6 and was fenced
    before its messages left; taker 3 (epoch 9) built on the ring's 6-7 of epoch 6.
    The drone still judged by epoch 8's start, refused the next taker that held them,
    and it refused the ring's 6-7 and waited for them for ever. A start that a later
    taker's base contradicts no longer counts."""
    outcome = run_seed(13594, SimOptions(policy="nearest"))
    assert outcome.ok, outcome.report()


def test_lose_master_seeds_of_two_switches_at_once_hold_every_oracle() -> None:
    """--lose-master seeds 2407, 2535, 5120, 6027 (liveness, F1's pattern): the drone
    switched twice at one instant (the script's handover, then an RPC's: 0 -> 2 -> 4 in
    2407) and the first old master was lost before its handover message left. The middle
    master never went ACTIVE, so it never handed over to the last, whose old master was
    alive: no takeover, a stall. A lost old master of any cooperative switch whose new
    master sent nothing since now has the master granted again, by takeover."""
    for seed in (2407, 2535, 5120, 6027):
        outcome = run_seed(seed, SimOptions(lose_master=True))
        assert outcome.ok, outcome.report()


def test_lose_master_seeds_10688_11795_and_11002_hold_every_oracle() -> None:
    """--lose-master seeds 10688, 11795 (liveness, a ring of two): taker 1's program gave
    up on a call whose retained reply a lost master's program acted on, and started
    again by a rejoin with nothing; the other controller was lost, and nobody held the
    requests below the drone's watermark. The master now flushes its log and its fresh
    self keeps it. Seed 11002: a replica whose program started again handled, before
    the rejoin, the handover message that made it master, and its fresh self was no
    master; now nothing is handled after the decision, and the message is kept."""
    for seed in (10688, 11795, 11002):
        outcome = run_seed(seed, SimOptions(lose_master=True))
        assert outcome.ok, outcome.report()


def test_lose_master_seeds_4097_5631_10175_hold_every_oracle() -> None:
    """--lose-master seeds 4097, 5631, 10175 (liveness): a controller routing around its
    dead successor to one whose stream takes longer than the detection time to come up
    (a slow direction) found every one down and went back to the dead one, dropping
    that stream; tried again from nothing, it never came up, and the taker was never
    given the log. With every one down, the ring stays with the one it sends to."""
    for seed in (4097, 5631, 10175):
        outcome = run_seed(seed, SimOptions(lose_master=True))
        assert outcome.ok, outcome.report()


def test_policy_seeds_that_took_a_replaced_framings_word_hold_every_oracle() -> None:
    """--policy nearest seeds 1122 and 3283, predictive 408 (same-replies): a taker's
    predecessor still held the lost master's framing of the taker's first messages (a
    Clock reading in 408 and 1122, a give-up of a request the drone executed in 3283)
    and said so in its sync frame; the taker took that word for its own messages and
    moved the watermark, the drone let those replies go, and the next taker, holding
    the older framing, found nothing retained to compare it with and built on it. A
    word of an older framing than ours for our number no longer moves the watermark."""
    for seed, policy in ((1122, "nearest"), (3283, "nearest"), (408, "predictive")):
        outcome = run_seed(seed, SimOptions(policy=policy))
        assert outcome.ok, outcome.report()


def test_policy_seeds_of_a_taker_given_a_replaced_framing_after_its_grant() -> None:
    """--policy predictive seeds 3536 and 7190 (same-replies): taker 2 restarted with
    nothing and was granted holding no request, the drone retaining requests 10-12 for
    it as taker 3 had them in epoch 2. The ring then gave it the cut-off master 1's
    give-ups of 10-12, framed in epoch 1; its program replayed them from the log, never
    comparing them with the retained replies, and 2 built on them. A taker checks the
    log's entry against the reply the drone retains for it as its program reaches it
    (``ControllerCore.answer``), as the grant's batch does (``retained_batch``)."""
    for seed in (3536, 7190):
        outcome = run_seed(seed, SimOptions(policy="predictive"))
        assert outcome.ok, outcome.report()


def test_policy_seed_4287_counts_the_replies_a_taker_adopted_as_brought_in_its_epoch() -> None:
    """--policy nearest seed 4287 (same-replies): master 0's program gave up on request
    2, which the drone executed; 0 handed over to 4 with the give-up (epoch 2), and 4 was
    taken over by 1 (epoch 3), which answered its program from the drone's reply. The
    drone said that reply was brought in epoch 1, older than the give-up, so taker 3,
    holding 4's message, took its give-up for the ring's and built on it. A taker's
    requests now say which retained replies it adopted, and the drone counts them as
    brought in its epoch. (Counted from the Connect's holds_reqnr instead, --lose-master
    2720 and --lose-master --prepared 7588 never finished: it is stale by then.)"""
    for seed, options in (
        (4287, SimOptions(policy="nearest")),
        (2720, SimOptions(lose_master=True)),
        (7588, SimOptions(lose_master=True, prepared=True)),
    ):
        outcome = run_seed(seed, options)
        assert outcome.ok, outcome.report()


def test_policy_seed_882_keeps_the_takers_messages_a_fenced_master_queued() -> None:
    """--policy nearest and predictive seed 882 (liveness, a ring of two): master 0, out of
    range, was taken over by 1 and queued 1's messages 4-12, still ACTIVE; 1 handed the
    role back and died, and the drone had let go of those replies. Fenced when the
    handover message's grant showed its own mastership replaced, 0 rejoined with
    messages 1-3 only, and nobody held 4-12. It keeps the taker's lineage now."""
    for policy in ("nearest", "predictive"):
        outcome = run_seed(882, SimOptions(policy=policy))
        assert outcome.ok, outcome.report()


def test_policy_seeds_fence_a_master_whose_takeover_came_before_its_link_fell() -> None:
    """--policy nearest seed 2921 (same-replies, liveness): master 1 flew out of range and
    0 took over; 0's message came while 1's drone stream still looked up, so 1 queued it
    and stayed ACTIVE for ever, its program answered by itself past the drone's last
    request. The queued message now fences it once both its streams are down. Seeds
    2784, 3302, 3607 and 3611 (liveness) were the same."""
    for seed in (2921, 2784, 3302, 3607, 3611):
        outcome = run_seed(seed, SimOptions(policy="nearest"))
        assert outcome.ok, outcome.report()


# The stall scenario (--stall-new-master) in CI: the ring cut from a new master right
# after a cooperative switch, for about as long as the drone lets a master go without
# serving, so that it is taken over while it keeps its standby stream.
STALL_SEEDS = 150


def test_stall_new_master_seeds_hold_every_oracle() -> None:
    outcomes = _sweep(range(STALL_SEEDS), SimOptions(stall_new_master=True))
    assert not any(o.failed for o in outcomes), _failures(outcomes)


def test_a_fenced_new_masters_fresh_self_takes_no_role_its_earlier_self_lost() -> None:
    """Seed 680 (--stall-new-master): the new master 4, cut from the ring, was taken over;
    fenced when the ring came back, its fresh self got its old handover message again
    from the old master's direct link, took the role, was fenced at the Connect, and
    rejoined again, for the rest of the run. Seeds 8 and 422: the same handover message
    re-sent to a fresh self once the drone had moved past its epoch was taken for F7."""
    options = SimOptions(stall_new_master=True)
    outcomes = [run_seed(seed, options) for seed in (680, 8, 422)]
    assert not any(o.failed for o in outcomes), _failures(outcomes)
    assert all("stall" in o.faults for o in outcomes)


# Issue 32's every-station-lost scenario (--failsafe) in CI.
FAILSAFE_SEEDS = 100


def test_failsafe_seeds_hold_every_oracle_and_fail_safe() -> None:
    """Every station cut from the drone at a drawn moment, and the battery at its reserve
    in about half the seeds: exactly once and the replicas' replies hold, nothing reaches
    the vehicle from a failsafe until the operator's resume (the nothing-in-failsafe
    oracle), and both failsafes do act, each in many seeds."""
    options = SimOptions(failsafe=True)
    outcomes = []
    causes: Counter[str] = Counter()
    for seed in range(FAILSAFE_SEEDS):
        world = World(seed, options)
        outcomes.append(world.run())
        causes.update(what.split()[0] for _, what in world.drone.vehicle.failsafes)
    assert not any(o.failed for o in outcomes), _failures(outcomes)
    assert (
        causes["lost_link"] >= FAILSAFE_SEEDS // 4 and causes["battery"] >= FAILSAFE_SEEDS // 10
    ), causes


# Issue 32's operator commands (--operator) in CI.
OPERATOR_SEEDS = 120


def test_operator_seeds_hold_every_oracle_and_the_commands_act() -> None:
    """An operator's pause then resume or abort, abort, land-now at a drawn moment: exactly
    once and the replicas' replies hold, nothing reaches the vehicle while paused or after
    the mission ended (nothing-while-paused, nothing-after-abort), and requests do wait."""
    options = SimOptions(operator=True)
    outcomes = []
    taken: Counter[str] = Counter()
    waited = 0
    for seed in range(OPERATOR_SEEDS):
        world = World(seed, options)
        outcomes.append(world.run())
        taken.update(command for _, command, _ in world.drone.vehicle.operator)
        waited += world.drone.waited
    assert not any(o.failed for o in outcomes), _failures(outcomes)
    assert min(taken[c] for c in ("pause", "resume", "abort", "land_now")) >= 3, taken
    assert waited >= 10


# Issue 33's lying station (--lying) in CI: about 20 s on one core (60 seeds: the rarest
# lie, a borrowed handover grant, is told 3 times by seed 50).
LYING_SEEDS = 60


def test_lying_seeds_hold_every_oracle_and_refuse_every_forged_frame() -> None:
    """Every part signs and checks with its key, and one station forges frames at drawn
    moments: every oracle holds, each forged frame of every kind is refused by its
    receiver's core (lies-refused), and the mission completes exactly once."""
    options = SimOptions(lying=True)
    outcomes = []
    told: Counter[str] = Counter()
    for seed in range(LYING_SEEDS):
        world = World(seed, options)
        outcomes.append(world.run())
        told.update(lie.kind for lie in world.lies if lie.refused)
    assert not any(o.failed for o in outcomes), _failures(outcomes)
    assert min(told[kind] for kind in LIES) >= 3, told


# Issue 32's autopilot taking the vehicle over (--autopilot) in CI.
AUTOPILOT_SEEDS = 120


def test_autopilot_seeds_hold_every_oracle_and_the_takeover_fails_safe() -> None:
    """The autopilot switches the vehicle to a return, a landing or a pilot's mode at a
    drawn moment: exactly once and the replicas' replies hold, nothing reaches the vehicle
    from the takeover until the operator's resume (nothing-in-failsafe), and the drone
    takes the takeover for a failsafe in many seeds (not in those where the switch came
    before the mission's first command or after its end). Its own GCS failsafe: a drone
    dead longer than the GCS time finds the vehicle returning or landed when it restarts,
    and ends the mission with the autopilot failsafe."""
    options = SimOptions(autopilot=True)
    outcomes = []
    taken: Counter[str] = Counter()
    after_gcs: Counter[str] = Counter()
    for seed in range(AUTOPILOT_SEEDS):
        world = World(seed, options)
        outcomes.append(world.run())
        vehicle = world.drone.vehicle
        taken.update(what for _, what in vehicle.failsafes)
        if vehicle.gcs_failsafes:
            after_gcs["seeds"] += 1
            since = vehicle.gcs_failsafes[0]
            after_gcs.update(what for at, what in vehicle.failsafes if at >= since)
    assert not any(o.failed for o in outcomes), _failures(outcomes)
    modes = {what.removeprefix("autopilot ") for what in taken if what.startswith("autopilot ")}
    # "landed": the vehicle its GCS failsafe landed while the drone was dead.
    assert modes == {"RETURN_TO_LAUNCH", "LAND", "POSCTL", "landed"}, taken
    assert sum(taken.values()) >= 15, taken
    assert after_gcs["seeds"] >= 5, after_gcs
    assert after_gcs["autopilot landed"] >= 1, after_gcs
    assert after_gcs["autopilot RETURN_TO_LAUNCH"] >= 1, after_gcs

"""A deterministic simulation of baton, in the spirit of FoundationDB's (issue 9).

It runs the project's own decision code, the controller's Algorithm 1
state machine (``ControllerProtocol``) and the drone's ``Sequencer`` with
its ``ReplyCache``, on a seeded, single-threaded loop in virtual time,
with an in-memory network and a simulated vehicle and camera, injects
faults chosen by the seed, and checks oracles that count what happened
at the vehicle instead of trusting the code. A failing seed prints the
one command that replays it exactly.

- ``loop``: virtual time, the event heap.
- ``mission``: random deterministic mission programs.
- ``network``: ring streams (driving the shipped ``LinkCore``) and drone links.
- ``controller``: a driver of the shipped controller cores, as node.py is.
- ``drone``: service.py's decisions around the sequencer; vehicle, camera.
- ``faults``: what breaks, per seed.
- ``oracles``: what must hold.
- ``findings``: bugs it found in the code it runs; the default mix keeps
  their scenarios out (``--allow F4`` lets one in).
- ``mutations``: known defects put back, to show the oracles catch them.
- ``world``: one seed, end to end (``run_seed``); ``cli``: ``python -m baton.sim``.
"""

from baton.sim.world import Outcome, SimOptions, run_seed

__all__ = ["Outcome", "SimOptions", "run_seed"]

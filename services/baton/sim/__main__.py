"""``python -m baton.sim``: see ``baton.sim.cli``."""

import sys

from baton.sim.cli import main

sys.exit(main())

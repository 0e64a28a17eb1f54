"""Child processes that do not outlive their parent, and files they announce with."""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import tempfile
from pathlib import Path

_PR_SET_PDEATHSIG = 1


def die_with_parent(parent: int) -> None:
    """Asks Linux to send this process SIGTERM when its parent, ``parent``, dies.

    Called at start by every process baton starts itself (the testbed's
    parts, a controller's mission program: ``--die-with-parent PID``), so
    that a parent killed outright leaves nothing running. Not a
    ``preexec_fn``: forking a process that runs gRPC threads is unsafe. If
    the parent died before this process got here, it ends at once. A no-op
    where there is no prctl.
    """
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != parent:
        os.kill(os.getpid(), signal.SIGTERM)


def write_atomically(path: str | Path, text: str) -> None:
    """Writes ``text`` to ``path`` so that a reader sees all of it or nothing.

    The one way a part announces itself (its address or URL file, which the
    testbed and the tests wait for) and writes any file another process polls.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.")
    try:
        with os.fdopen(fd, "w") as out:
            out.write(text)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise

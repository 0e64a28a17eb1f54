"""Starting, watching and stopping baton's processes: one way, for the testbed and the tests.

Each part (sim vehicle, drone service, controllers, links) is a real process
of the ``baton`` command. Its output goes to a log file; it announces where it
listens by writing a ready file (``--address-file`` / ``--url-file``).
``Supervisor`` waits for those files with a deadline, notices when a part
dies (and shows its last log lines), and stops everything on exit, SIGKILL
after a grace period, so no process is left behind. Parts that do not need
each other start together (``together``: one wave) and stop together, the
last wave first.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import sys
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path


class PartDied(RuntimeError):
    """A supervised process exited when it should not have."""

    def __init__(self, part: ManagedProcess) -> None:
        self.part = part
        tail = "\n".join(f"    {line}" for line in part.tail(15))
        super().__init__(
            f"{part.name} exited with code {part.returncode}; its last log lines "
            f"({part.log_path}):\n{tail}"
        )


class PartNotReady(RuntimeError):
    """A supervised process did not announce itself in time."""


@dataclass
class ManagedProcess:
    """One process of the testbed."""

    name: str
    argv: list[str]
    log_path: Path
    ready_file: Path | None = None
    expect_exit: bool = False
    # Killed on purpose (a fault injected): its exit is not a failure.
    killed: bool = False
    frozen: bool = False  # SIGSTOPped (a fault injected)
    wave: int = 0  # parts of one wave were started together and stop together
    process: asyncio.subprocess.Process | None = None
    ready_text: str = ""
    env: Mapping[str, str] | None = None  # its whole environment; None: the supervisor's
    _log_handle: object = field(default=None, repr=False)

    @property
    def returncode(self) -> int | None:
        """The exit code, or None while running."""
        return None if self.process is None else self.process.returncode

    def tail(self, lines: int = 15) -> list[str]:
        """The last lines of the process's log."""
        try:
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return []
        return text.splitlines()[-lines:]


def baton_argv(*args: str) -> list[str]:
    """The command line of a ``baton`` subcommand, with this interpreter."""
    return [sys.executable, "-m", "baton.cli", "--die-with-parent", str(os.getpid()), *args]


class Supervisor:
    """Starts processes, waits until they are ready, and stops them all."""

    def __init__(self, workdir: Path) -> None:
        self.workdir = workdir
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.parts: dict[str, ManagedProcess] = {}
        self._waves = 0
        self._together: int | None = None

    @contextlib.contextmanager
    def together(self) -> Iterator[None]:
        """The parts started inside are one wave: ``stop_all`` stops them together."""
        self._waves += 1
        self._together = self._waves
        try:
            yield
        finally:
            self._together = None

    async def start(
        self,
        name: str,
        argv: Sequence[str],
        ready_file: Path | None = None,
        expect_exit: bool = False,
        env: Mapping[str, str] | None = None,
        append: bool = False,
    ) -> ManagedProcess:
        """Starts ``argv`` as part ``name``; its stdout and stderr go to ``workdir/name.log``.

        ``env``: its whole environment (default: this process's); ``append``: a restart
        continues the log of the part's earlier run instead of replacing it.
        """
        if ready_file is not None:
            with contextlib.suppress(FileNotFoundError):
                ready_file.unlink()
        if self._together is None:
            self._waves += 1
        part = ManagedProcess(
            name,
            list(argv),
            self.workdir / f"{name}.log",
            ready_file,
            expect_exit,
            wave=self._waves if self._together is None else self._together,
            env=env,
        )
        handle = part.log_path.open("ab" if append else "wb")
        part._log_handle = handle
        part.process = await asyncio.create_subprocess_exec(
            *argv,
            stdin=asyncio.subprocess.DEVNULL,
            stdout=handle,
            stderr=asyncio.subprocess.STDOUT,
            start_new_session=True,  # Ctrl-C in a terminal reaches the supervisor only
            env=env,
        )
        self.parts[name] = part
        return part

    async def wait_ready(self, part: ManagedProcess, timeout: float = 30.0) -> str:
        """The content of the part's ready file, once written; raises if it dies or is late."""
        assert part.ready_file is not None
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            if part.ready_file.exists():
                text = part.ready_file.read_text().strip()
                if text:
                    part.ready_text = text
                    return text
            if part.returncode is not None:
                raise PartDied(part)
            if loop.time() > deadline:
                tail = "\n".join(part.tail(10))
                raise PartNotReady(f"{part.name} not ready after {timeout:.0f} s; log:\n{tail}")
            await asyncio.sleep(0.02)

    async def wait_all_ready(
        self, parts: Sequence[ManagedProcess], timeout: float = 30.0
    ) -> list[str]:
        """``wait_ready`` for several parts at once; the first failure is raised as it is."""
        waits = [asyncio.ensure_future(self.wait_ready(part, timeout)) for part in parts]
        try:
            return list(await asyncio.gather(*waits))
        finally:
            for wait in waits:
                wait.cancel()

    async def start_ready(
        self, name: str, argv: Sequence[str], ready_file: Path, timeout: float = 30.0
    ) -> str:
        """Starts a part and waits for its ready file; returns what it announced."""
        part = await self.start(name, argv, ready_file)
        return await self.wait_ready(part, timeout)

    async def start_ready_together(
        self, parts: Sequence[tuple[str, Sequence[str], Path]], timeout: float = 30.0
    ) -> list[str]:
        """Starts parts (name, argv, ready file) that do not need each other as one wave,
        then waits for all their ready files; returns what each announced, in order."""
        with self.together():
            started = [await self.start(name, argv, ready) for name, argv, ready in parts]
        return await self.wait_all_ready(started, timeout)

    def check(self) -> None:
        """Raises PartDied for the first part that exited unexpectedly."""
        for part in self.parts.values():
            if part.killed:
                continue
            if part.returncode is not None and not (part.expect_exit and part.returncode == 0):
                raise PartDied(part)

    async def kill(self, name: str) -> ManagedProcess:
        """kill -9 of part ``name`` (a fault injected), once it is gone; ``check`` ignores it."""
        part = self.parts[name]
        assert part.process is not None
        part.killed = True
        with contextlib.suppress(ProcessLookupError):
            part.process.send_signal(signal.SIGKILL)
        await part.process.wait()
        return part

    def freeze(self, name: str) -> None:
        """SIGSTOP of part ``name`` (a fault injected): it says nothing, yet its sockets
        stay open and the kernel still acknowledges what reaches them. Through a
        frozen link emulator that is a silent, blackholed link (no reset to notice)."""
        part = self.parts[name]
        assert part.process is not None and part.process.returncode is None
        part.process.send_signal(signal.SIGSTOP)
        part.frozen = True

    def send_signal(self, name: str, signum: signal.Signals) -> None:
        """Sends ``signum`` to live part ``name`` (SIGHUP: a link emulator reshapes)."""
        part = self.parts[name]
        assert part.process is not None and part.process.returncode is None
        part.process.send_signal(signum)

    def thaw(self, name: str) -> None:
        """SIGCONT of a frozen part: it goes on where it stopped."""
        part = self.parts[name]
        assert part.process is not None
        with contextlib.suppress(ProcessLookupError):
            part.process.send_signal(signal.SIGCONT)
        part.frozen = False

    async def restart(self, name: str) -> ManagedProcess:
        """Starts a killed part again with its command line and environment; returns once it
        is ready."""
        old = self.parts[name]
        part = await self.start(
            name, old.argv, old.ready_file, old.expect_exit, old.env, append=True
        )
        if part.ready_file is not None:
            await self.wait_ready(part)
        return part

    async def stop_part(self, name: str, grace: float = 5.0) -> int | None:
        """SIGTERM, then SIGKILL after ``grace`` seconds; returns the exit code."""
        part = self.parts[name]
        process = part.process
        if process is None:
            return None
        if process.returncode is None:
            if part.frozen:
                self.thaw(name)  # a frozen process would not act on SIGTERM
            with contextlib.suppress(ProcessLookupError):
                process.send_signal(signal.SIGTERM)
            try:
                await asyncio.wait_for(process.wait(), grace)
            except TimeoutError:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, signal.SIGKILL)
                await process.wait()
        handle = part._log_handle
        if handle is not None:
            handle.close()  # type: ignore[attr-defined]
            part._log_handle = None
        return process.returncode

    async def stop_all(self, grace: float = 5.0) -> None:
        """Stops every part, the most recent wave first, the parts of a wave together
        (a controller takes its gRPC grace, 1 s, to stop: not once per controller)."""
        for wave in sorted({part.wave for part in self.parts.values()}, reverse=True):
            names = [name for name, part in self.parts.items() if part.wave == wave]
            await asyncio.gather(*(self.stop_part(name, grace) for name in names))

    async def __aenter__(self) -> Supervisor:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop_all()

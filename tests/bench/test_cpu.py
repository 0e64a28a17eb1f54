"""The cores' busy share beside a benchmark's numbers (baton.bench.cpu)."""

from __future__ import annotations

import time
from pathlib import Path

from waiting import eventually

from baton.bench.cpu import CpuSampler, read_cpu_ticks


def test_the_kernels_count_is_read_as_busy_and_total_ticks(tmp_path: Path) -> None:
    stat = tmp_path / "stat"
    # user nice system idle iowait irq softirq steal guest guest_nice
    stat.write_text("cpu  100 5 50 800 40 3 2 0 7 0\ncpu0 50 2 25 400 20 1 1 0 0 0\n")
    busy, total = read_cpu_ticks(stat) or (0, 0)
    assert (busy, total) == (160, 1000)  # idle and iowait are not busy; guest is in user
    assert read_cpu_ticks(tmp_path / "absent") is None
    stat.write_text("intr 1 2 3\n")
    assert read_cpu_ticks(stat) is None


def test_busy_is_the_share_between_the_samples_around_a_window() -> None:
    cpu = CpuSampler()
    for at, ticks in ((10.0, (0, 0)), (11.0, (50, 200)), (12.0, (150, 400))):
        cpu.record(at, ticks)
    assert cpu.busy(10.5, 11.5) == 150 / 400  # from the sample at 10 to the one at 12
    assert cpu.busy(11.0, 12.0) == 100 / 200
    assert cpu.busy(11.0, 11.1) is None  # too short to count ticks in
    assert cpu.busy(9.0, 11.0) is None  # before the first sample
    assert cpu.busy(11.5, 12.5) is None  # after the last


async def test_the_sampler_samples_this_machine_while_entered() -> None:
    with CpuSampler(every_s=0.01) as cpu:
        start = time.time()
        while time.time() - start < 0.3:  # keeps one core busy: an idle machine reads 0.0
            pass
        end = time.time()
        busy = await eventually(
            lambda: cpu.busy(start, end) is not None, "a sample after the window"
        )
        busy = cpu.busy(start, end)
    # One core was busy all through the window; how large a share of the machine that
    # is depends on how many cores /proc/stat counts (a container may see the host's).
    assert busy is not None and 0 < busy <= 1


def test_a_process_usage_is_read_from_its_stat_and_status(tmp_path: Path) -> None:
    from baton.bench.cpu import CLOCK_TICKS, process_usage

    folder = tmp_path / "42"
    folder.mkdir()
    # A command name with spaces and a parenthesis: the fields are counted after its end.
    before = "42 (a (b) c) S " + " ".join(["0"] * 10)
    (folder / "stat").write_text(f"{before} {3 * CLOCK_TICKS} {CLOCK_TICKS} 0 0\n")
    (folder / "status").write_text("Name:\tx\nVmRSS:\t   2048 kB\n")
    (folder / "smaps_rollup").write_text("Rss:  2048 kB\nPss:   512 kB\n")
    usage = process_usage(42, tmp_path)
    assert usage is not None
    assert (usage.cpu_s, usage.rss_bytes, usage.pss_bytes) == (4.0, 2048 * 1024, 512 * 1024)
    assert process_usage(43, tmp_path) is None  # gone


async def test_this_process_and_its_children_are_found_in_proc() -> None:
    import asyncio
    import os

    from baton.bench.cpu import child_pids, process_usage

    usage = process_usage(os.getpid())
    assert usage is not None and usage.cpu_s > 0 and usage.pss_bytes > 0
    assert usage.rss_bytes >= usage.pss_bytes
    child = await asyncio.create_subprocess_exec("sleep", "30")
    try:
        assert child.pid in child_pids(os.getpid())
    finally:
        child.kill()
        await child.wait()
    assert child.pid not in child_pids(os.getpid())

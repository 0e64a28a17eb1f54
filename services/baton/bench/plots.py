"""The benchmark figures (matplotlib, Agg backend: no display needed)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, BinaryIO

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt

from baton.bench.model import MB


def plot_timeline(
    reqnrs: Sequence[int],
    inter_arrival_s: Sequence[float],
    log_bytes: Sequence[int],
    handovers: Sequence[int],
    flush_limit: int,
    path: Path | BinaryIO,
    title: str | None = None,
) -> None:
    """Figure 5: request inter-arrival time and the master's log size over reqnr (as a PNG,
    to a file or a binary stream)."""
    fig, ax = plt.subplots(figsize=(10, 4.5))
    ax.plot(reqnrs, inter_arrival_s, color="tab:red", linewidth=1, label="inter-arrival time")
    ax.set_xlabel("request number (reqnr)")
    ax.set_ylabel("inter-arrival time at the drone (s)", color="tab:red")
    log_axis = ax.twinx()
    log_axis.plot(
        reqnrs, [b / MB for b in log_bytes], color="tab:blue", linewidth=1, label="master's log"
    )
    log_axis.set_ylabel("master's log size (MB)", color="tab:blue")
    for k, reqnr in enumerate(handovers):
        ax.axvline(
            reqnr, color="black", linestyle="--", linewidth=1, label="handover" if k == 0 else None
        )
    ax.set_title(
        title or f"Request inter-arrival time and log growth (flush limit {flush_limit / MB:g} MB)"
    )
    lines = ax.get_legend_handles_labels()
    more = log_axis.get_legend_handles_labels()
    ax.legend(
        lines[0] + more[0],
        lines[1] + more[1],
        loc="upper center",
        bbox_to_anchor=(0.5, -0.14),
        ncol=3,
        frameon=False,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120, format="png")
    plt.close(fig)


def plot_worst_case(rows: Sequence[dict[str, Any]], path: Path, controllers: int) -> None:
    """Figure 6, one panel per hop count: the paper's model, the physical limit, and the
    measured delay (mean, min-max) of each forwarding mode."""
    hop_counts = sorted({r["hops"] for r in rows})
    fig, axes = plt.subplots(
        1, len(hop_counts), figsize=(4.2 * len(hop_counts), 4.2), sharey=True, squeeze=False
    )
    styles = {"store-and-forward": ("tab:blue", "o"), "cut-through": ("tab:red", "s")}
    for ax, hops in zip(axes[0], hop_counts, strict=True):
        mine = [r for r in rows if r["hops"] == hops]
        for forwarding in sorted({r.get("forwarding", "store-and-forward") for r in mine}):
            measured = sorted(
                (r for r in mine if r.get("forwarding", "store-and-forward") == forwarding),
                key=lambda r: r["flush_limit"],
            )
            color, marker = styles.get(forwarding, ("tab:green", "^"))
            ax.errorbar(
                [r["flush_limit"] / MB for r in measured],
                [r["mean_s"] for r in measured],
                yerr=[
                    [r["mean_s"] - r["min_s"] for r in measured],
                    [r["max_s"] - r["mean_s"] for r in measured],
                ],
                color=color,
                marker=marker,
                capsize=3,
                label=f"{forwarding}: measured",
            )
        reference = sorted(
            {r["flush_limit"]: r for r in mine}.values(), key=lambda r: r["flush_limit"]
        )
        x = [r["flush_limit"] / MB for r in reference]
        ax.plot(x, [r["model_s"] for r in reference], "k--", label="paper's model")
        if all("limit_s" in r for r in reference):
            ax.plot(x, [r["limit_s"] for r in reference], "k:", label="physical limit")
        ax.set_title(f"{hops} hop{'s' if hops > 1 else ''}")
        ax.set_xlabel("flush limit (MB)")
        ax.grid(True, alpha=0.3)
    axes[0][0].set_ylabel("handover delay (s)")
    axes[0][0].legend(fontsize=8)
    fig.suptitle(f"Worst-case handover delay, {controllers} controllers")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_failover(runs: Sequence[dict[str, Any]], detection_s: float, path: Path) -> None:
    """Per kill: detection, connect and catch-up (with the missing replies) stacked, and the
    physical limit above detection."""
    measured = [r for r in runs if "total_s" in r]
    fig, ax = plt.subplots(figsize=(10, 4.5))
    labels = [
        f"{r['controllers']}c@{r['kill_reqnr']}{'h' if r['in_handover'] else ''}" for r in measured
    ]
    x = range(len(measured))
    detection = [r["detection_s"] for r in measured]
    connect = [r["connect_s"] for r in measured]
    catch_up = [r["catch_up_s"] for r in measured]
    ax.bar(x, detection, color="tab:gray", label="detection")
    ax.bar(x, connect, bottom=detection, color="tab:orange", label="connect")
    ax.bar(
        x,
        catch_up,
        bottom=[d + c for d, c in zip(detection, connect, strict=True)],
        color="tab:blue",
        label="catch-up (the missing replies, the program)",
    )
    ax.scatter(
        x,
        [d + r["physical_s"] for d, r in zip(detection, measured, strict=True)],
        color="black",
        marker="_",
        s=200,
        label="detection + physical limit",
        zorder=3,
    )
    ax.axhline(detection_s, color="tab:gray", linestyle=":", linewidth=1)
    ax.set_xticks(list(x), labels, rotation=60, fontsize=7)
    ax.set_ylabel("kill -9 to the new master's first new call (s)")
    ax.set_title("Takeover after kill -9 of the master (controllers@kill reqnr, h: in a handover)")
    ax.legend(loc="lower right", fontsize=8, framealpha=0.9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_fleet(result: dict[str, Any], path: Path) -> None:
    """``baton bench fleet``: the measured station's CPU and memory per hosted mission,
    and the probe's handover delay and round trip against the lone mission's."""
    from baton.bench.fleet import HANDOVER_RATIO_TARGET, REPLICA_MB_TARGET

    levels = result["levels"]
    n = [level["missions"] for level in levels]
    fig, (cpu, memory, ratio) = plt.subplots(1, 3, figsize=(14, 4.2))
    cpu.plot(n, [lv["as_master"]["station_cpu"] for lv in levels], "o-", label="as master")
    cpu.plot(n, [lv["as_replica"]["station_cpu"] for lv in levels], "s-", label="as replica")
    cpu.plot(
        n,
        [lv["as_master"]["programs_cpu"] for lv in levels],
        "^:",
        label="its mission programs (master window)",
    )
    for key, label in (("drones_cpu", "all drones"), ("vehicles_cpu", "all sim vehicles")):
        if all(key in lv["as_master"] for lv in levels):  # runs before they were measured
            cpu.plot(n, [lv["as_master"][key] for lv in levels], ".--", label=label)
    cpu.axhline(result["machine"]["nproc"] or 2, color="black", linestyle="--", linewidth=1)
    cpu.set_title("CPU (s of CPU per s; dashed: all cores)")
    cpu.set_xlabel("missions hosted")
    memory.plot(n, [lv["station_mb_per_mission"] for lv in levels], "o-", label="station")
    memory.plot(
        n, [lv["as_replica"]["program_pss_mb"] or 0 for lv in levels], "s-", label="program (PSS)"
    )
    memory.plot(n, [lv["replica_mb"] for lv in levels], "k^-", label="replica: both")
    memory.plot(n, [lv["replica_rss_mb"] for lv in levels], "k^:", label="replica, program RSS")
    memory.axhline(REPLICA_MB_TARGET, color="tab:red", linestyle="--", linewidth=1, label="target")
    memory.set_title("Memory per hosted mission (MB)")
    memory.set_xlabel("missions hosted")
    ratio.plot(n, [lv["handover_ratio"] for lv in levels], "o-", label="handover p50")
    ratio.plot(n, [lv["handover_max_ratio"] for lv in levels], "o:", label="handover max")
    ratio.plot(n, [lv["round_trip_ratio"] for lv in levels], "s-", label="round trip p50")
    ratio.axhline(
        HANDOVER_RATIO_TARGET, color="tab:red", linestyle="--", linewidth=1, label="target"
    )
    ratio.set_yscale("log")
    ratio.set_title("Probe mission against a lone mission (x, log)")
    ratio.set_xlabel("missions hosted besides the probe")
    for ax in (cpu, memory, ratio):
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    cpu.set_ylim(bottom=0)
    memory.set_ylim(bottom=0)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

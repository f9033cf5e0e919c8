"""The latency-vs-payload plot: log-log, one line per path (p50, with p90..p99 as a band)."""

from __future__ import annotations

from typing import Any

from benchmarks.stats import format_size


def plot_latency(report: dict[str, Any], path: str) -> None:
    """Write the PNG of ``report``'s latencies to ``path`` (matplotlib, Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(9, 6), dpi=110)
    for entry in report["paths"].values():
        latency = entry.get("latency_us") or {}
        sizes = sorted(int(s) for s in latency)
        if not sizes:
            continue
        p50 = [latency[str(s)]["p50_us"] for s in sizes]
        style = "-" if entry["kind"] == "ours" else "--"
        (line,) = axes.plot(sizes, p50, style, marker="o", linewidth=2 if entry["kind"] == "ours"
                            else 1.3, label=entry["label"])
        axes.fill_between(sizes, p50, [latency[str(s)]["p99_us"] for s in sizes],
                          color=line.get_color(), alpha=0.12)
    axes.set_xscale("log", base=2)
    axes.set_yscale("log")
    ticks = sorted({int(s) for e in report["paths"].values() for s in (e.get("latency_us") or {})})
    if ticks:
        axes.set_xticks(ticks)
        axes.set_xticklabels([format_size(t) for t in ticks], rotation=30)
    axes.set_xlabel("payload size")
    axes.set_ylabel("one-way latency, p50 (line) to p99 (band) [us]")
    axes.set_title("ExperimentalTensor one-way latency by path (two processes; intra: one)\n"
                   + report["machine_line"], fontsize=9)
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)

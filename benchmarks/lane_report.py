"""The fast lane's targets (issue 15), measured side by side with its peers in one run.

- lane p50 <= 1.5x iceoryx2's own zero-copy path with a blocking listener, at 4 KiB;
- lane p50 below a raw Zenoh put (copy) of 4 KiB;
- lane p50 <= 40 us and p99 <= 120 us at every size measured.
The lane path carries the descriptor only; what a full message adds (descriptor build, CDR,
import) is in ``benchmarks/lane_stages.py``.
"""

from __future__ import annotations

from typing import Any, Callable

from benchmarks.stats import ratio

LANE = "lane"
SIZE_4K = 4 << 10


def _worst(paths: dict[str, Any], stat: str) -> float | None:
    latency = paths.get(LANE, {}).get("latency_us") or {}
    values = [figures[f"{stat}_us"] for figures in latency.values()]
    return max(values) if values else None


def lane_ratios(paths: dict[str, Any], verdict: Callable[..., dict],
                missing: Callable[..., str]) -> dict[str, dict[str, Any]]:
    """The lane's ratios and absolute targets, in the report's ratio format."""
    def p50_4k(name: str) -> float | None:
        figures = (paths.get(name, {}).get("latency_us") or {}).get(str(SIZE_4K))
        return None if figures is None else figures["p50_us"]

    vs_iox = ratio(p50_4k(LANE), p50_4k("iceoryx2_listener"))
    vs_zenoh = ratio(p50_4k(LANE), p50_4k("zenoh_copy"))
    why = missing(paths, (LANE,), (SIZE_4K,))
    return {
        "lane_vs_iceoryx2_listener_4KiB": {
            "description": "lane p50 / iceoryx2 (blocking listener) p50 at 4 KiB (lower is better)",
            **verdict(vs_iox, 1.5, False,
                      missing(paths, (LANE, "iceoryx2_listener"), (SIZE_4K,)))},
        "lane_vs_zenoh_copy_4KiB": {
            "description": "lane p50 / raw Zenoh put p50 at 4 KiB (lower is better)",
            **verdict(vs_zenoh, 1.0, False, missing(paths, (LANE, "zenoh_copy"), (SIZE_4K,)))},
        "lane_worst_p50_over_40us": {
            "description": "lane worst p50 over all sizes / 40 us (lower is better)",
            **verdict(ratio(_worst(paths, "p50"), 40.0), 1.0, False, why)},
        "lane_worst_p99_over_120us": {
            "description": "lane worst p99 over all sizes / 120 us (lower is better)",
            **verdict(ratio(_worst(paths, "p99"), 120.0), 1.0, False, why)},
    }

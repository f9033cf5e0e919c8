"""The fast lane's targets (issue 15), measured side by side with its peers in one run.

For the bare ``lane`` path (the descriptor only) and for the full warp zero-copy path, which
the transport now carries over the lane between two processes of this host:

- p50 <= 1.5x iceoryx2's own zero-copy path with a blocking listener, at 4 KiB;
- p50 below a raw Zenoh put (copy) of 4 KiB;
- p50 <= 40 us and p99 <= 120 us at every size measured;
- warp zero-copy: the 4 KiB message rate at least 3x the figure before the lane
  (:data:`RATE_BEFORE`, docs/benchmarks/bench.json before issue 15).
What a full message adds to the lane (allocation, views, descriptor build, CDR, import) is shown
stage by stage by ``python -m benchmarks.lane_stages``.
"""

from __future__ import annotations

from typing import Any, Callable

from benchmarks.stats import ratio

LANE = "lane"
WARP = "warp_zero_copy"
SIZE_4K = 4 << 10
#: The warp zero-copy 4 KiB rate (msg/s) before the lane, docs/benchmarks/bench.json (main).
RATE_BEFORE = 2445.0


def _worst(paths: dict[str, Any], stat: str, path: str = LANE) -> float | None:
    latency = paths.get(path, {}).get("latency_us") or {}
    values = [v for figures in latency.values() if (v := figures.get(f"{stat}_us")) is not None]
    return max(values) if values else None


def lane_ratios(paths: dict[str, Any], verdict: Callable[..., dict],
                missing: Callable[..., str]) -> dict[str, dict[str, Any]]:
    """The lane's ratios and absolute targets, in the report's ratio format."""
    def p50_4k(name: str) -> float | None:
        figures = (paths.get(name, {}).get("latency_us") or {}).get(str(SIZE_4K))
        return None if figures is None else figures["p50_us"]

    result = _targets(paths, LANE, "lane", p50_4k, verdict, missing)
    warp = _targets(paths, WARP, "warp zero-copy", p50_4k, verdict, missing)
    # Each warp bar beside the lane alone's figure in this run: the wake-up and doorbell with
    # no message work, the floor under that bar (issue 26: a missed bar, shown at its floor).
    for key, entry in warp.items():
        floor = result[key.removeprefix("warp_")]  # (the lane's bar of the same name)
        if floor["value"] is not None and entry["value"] is not None:
            entry["detail"] = f"the lane alone, its floor here: {floor['value']:.2f}x"
    result.update(warp)
    rate = (paths.get(WARP, {}).get("rate") or {}).get("msgs_per_s")
    result["warp_rate_4KiB_over_before"] = {
        "description": f"warp zero-copy msg/s at 4 KiB / {RATE_BEFORE:,.0f} msg/s before the lane "
                       "(higher is better)",
        **verdict(ratio(rate, RATE_BEFORE), 3.0, True,
                  "" if rate is not None else f"{WARP} has no rate figure")}
    return result


def _targets(paths: dict[str, Any], path: str, label: str, p50_4k: Callable[[str], Any],
             verdict: Callable[..., dict], missing: Callable[..., str]
             ) -> dict[str, dict[str, Any]]:
    vs_iox = ratio(p50_4k(path), p50_4k("iceoryx2_listener"))
    vs_zenoh = ratio(p50_4k(path), p50_4k("zenoh_copy"))
    why = missing(paths, (path,), (SIZE_4K,))
    key = "lane" if path == LANE else "warp_lane"
    return {
        f"{key}_vs_iceoryx2_listener_4KiB": {
            "description": f"{label} p50 / iceoryx2 (blocking listener) p50 at 4 KiB "
                           "(lower is better)",
            **verdict(vs_iox, 1.5, False,
                      missing(paths, (path, "iceoryx2_listener"), (SIZE_4K,)))},
        f"{key}_vs_zenoh_copy_4KiB": {
            "description": f"{label} p50 / raw Zenoh put p50 at 4 KiB (lower is better)",
            **verdict(vs_zenoh, 1.0, False, missing(paths, (path, "zenoh_copy"), (SIZE_4K,)))},
        f"{key}_worst_p50_over_40us": {
            "description": f"{label} worst p50 over all sizes / 40 us (lower is better)",
            **verdict(ratio(_worst(paths, "p50", path), 40.0), 1.0, False, why)},
        f"{key}_worst_p99_over_120us": {
            "description": f"{label} worst p99 over all sizes / 120 us (lower is better)",
            **verdict(ratio(_worst(paths, "p99", path), 120.0), 1.0, False, why)},
    }

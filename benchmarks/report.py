"""Turn raw path results into the report: figures per path, copies, ratios vs targets, table."""

from __future__ import annotations

import statistics
from typing import Any

from benchmarks.stats import format_size, ratio

ZERO_COPY = "warp_zero_copy"
SIZE_16M = 16 << 20
SIZE_64M = 64 << 20
SIZE_4K = 4 << 10


def path_entry(name: str, module: Any, raw: dict[str, Any]) -> dict[str, Any]:
    """The report entry of one path from what its child printed."""
    entry: dict[str, Any] = {"label": module.LABEL, "kind": module.KIND,
                             "topology": module.TOPOLOGY, "wall_s": raw.get("wall_s")}
    if "unavailable" in raw:
        entry.update(status="unavailable", reason=raw["unavailable"])
        return entry
    if "latency" not in raw:
        entry.update(status="error", reason=raw.get("error", "no result"))
        return entry
    entry.update(status="ok" if not raw.get("errors") else "partial",
                 errors=raw.get("errors", []), latency_us=raw["latency"], rate=raw.get("rate"),
                 shm_removed=raw.get("shm_removed", []))
    if module.KIND == "ours":
        entry["copies"] = copies_per_size(raw.get("sender_report", {}),
                                          raw.get("receiver_report", {}))
    return entry


def merge_rounds(entries: list[dict[str, Any]]) -> dict[str, Any]:
    """One path's entry from its rounds (see ``--rounds``): every latency percentile is the
    median over the rounds that measured it (min and max: of all samples), the rate is the
    median round's; ``rounds_p50_us`` keeps each round's p50, ``errors`` each failed round's
    reason."""
    measured = [e for e in entries if e.get("latency_us") is not None]
    if len(entries) == 1 or not measured:
        return entries[-1]
    merged = dict(measured[0])
    merged["errors"] = [error for e in entries for error in e.get("errors", [])] + [
        f"round {i}: {e['status']}: {e.get('reason')}" for i, e in enumerate(entries, 1)
        if e.get("latency_us") is None]
    merged["status"] = "ok" if all(e["status"] == "ok" for e in entries) else "partial"
    merged["wall_s"] = sum(e.get("wall_s") or 0.0 for e in entries)
    merged["shm_removed"] = [path for e in entries for path in e.get("shm_removed", [])]
    latency: dict[str, dict[str, float]] = {}
    per_round: dict[str, list[float]] = {}
    for size in sorted({s for e in measured for s in e["latency_us"]}, key=int):
        figures = [e["latency_us"][size] for e in measured if size in e["latency_us"]]
        latency[size] = {key: statistics.median(f[key] for f in figures)
                         for key in figures[0] if key not in ("samples", "min_us", "max_us")}
        for key, pick in (("min_us", min), ("max_us", max)):  # extremes of all the samples
            if key in figures[0]:
                latency[size][key] = pick(f[key] for f in figures)
        latency[size]["samples"] = sum(f["samples"] for f in figures)
        per_round[size] = [f["p50_us"] for f in figures]
    merged["latency_us"] = latency
    merged["rounds_p50_us"] = per_round
    rates = sorted((e["rate"] for e in measured if e.get("rate")),
                   key=lambda r: r["msgs_per_s"])
    if rates:  # the median round's own figures (its count and seconds go with its rate)
        merged["rate"] = rates[(len(rates) - 1) // 2]
    return merged


def copies_per_size(sender: dict[str, Any], receiver: dict[str, Any]) -> dict[str, Any]:
    """Bytes copied per message on each size, from the counts both sides made."""
    result = {}
    sent = sender.get("per_size", {})
    received = receiver.get("per_size", {})
    for size in sorted(set(sent) | set(received), key=int):
        s, r = sent.get(size, {}), received.get(size, {})
        serialized = int(s.get("serialized_bytes_per_message", 0))
        wire = int(r.get("received_wire_bytes", 0))
        materialized = int(r.get("materialized_bytes", 0))
        result[size] = {
            "serialized_bytes": serialized, "received_wire_bytes": wire,
            "materialized_bytes": materialized,
            "bytes_copied_per_message": serialized + wire + materialized,
            "payload_copies": (serialized + wire + materialized) / int(size),
            "delivered_backend": r.get("backend"), "tensor_lives_in": r.get("tensor_lives_in"),
        }
    return result


def p50(paths: dict[str, Any], name: str, nbytes: int) -> float | None:
    """Median one-way latency (us) of a path at a size, or None."""
    latency = paths.get(name, {}).get("latency_us") or {}
    figures = latency.get(str(nbytes))
    return None if figures is None else figures["p50_us"]


def _verdict(value: float | None, target: float, at_least: bool, why_missing: str) -> dict:
    if value is None:
        return {"value": None, "target": target, "verdict": "N/A", "detail": why_missing,
                "at_least": at_least}
    ok = value >= target if at_least else value <= target
    return {"value": value, "target": target, "verdict": "PASS" if ok else "MISS", "detail": "",
            "at_least": at_least}


def _missing(paths: dict[str, Any], names: tuple[str, ...], sizes: tuple[int, ...]) -> str:
    for name in names:
        entry = paths.get(name)
        if entry is None:
            return f"{name} not run"
        if entry.get("status") in ("unavailable", "error"):
            return f"{name} {entry['status']}: {entry.get('reason')}"
        for size in sizes:
            if p50(paths, name, size) is None:
                return f"{name} has no {format_size(size)} figure"
    return "missing figures"


def ratios(paths: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The ratios that matter, with their targets and PASS / MISS / N/A."""
    zc = ZERO_COPY
    speedup = ratio(p50(paths, "zenoh_copy", SIZE_16M), p50(paths, zc, SIZE_16M))
    vs_iox = ratio(p50(paths, zc, SIZE_16M), p50(paths, "iceoryx2", SIZE_16M))
    flat = ratio(p50(paths, zc, SIZE_64M), p50(paths, zc, SIZE_4K))
    result = {
        "speedup_vs_zenoh_copy_16MiB": {
            "description": "Zenoh copy p50 / warp zero-copy p50 at 16 MiB (higher is better)",
            **_verdict(speedup, 50.0, True, _missing(paths, ("zenoh_copy", zc), (SIZE_16M,)))},
        "slowdown_vs_iceoryx2_16MiB": {
            "description": "warp zero-copy p50 / iceoryx2 p50 at 16 MiB (lower is better)",
            **_verdict(vs_iox, 3.0, False, _missing(paths, ("iceoryx2", zc), (SIZE_16M,)))},
        "flatness_64MiB_over_4KiB": {
            "description": "warp zero-copy p50 at 64 MiB / p50 at 4 KiB (lower is better)",
            **_verdict(flat, 1.2, False, _missing(paths, (zc,), (SIZE_64M, SIZE_4K)))},
    }
    result.update(transport_ratios(paths))
    from benchmarks.lane_report import lane_ratios

    result.update(lane_ratios(paths, _verdict, _missing))
    largest = max((int(s) for s in (paths.get(zc, {}).get("latency_us") or {})), default=None)
    if largest is not None and largest > SIZE_64M:
        result[f"flatness_{format_size(largest).replace(' ', '')}_over_4KiB"] = _info(
            f"warp zero-copy p50 at {format_size(largest)} / p50 at 4 KiB",
            ratio(p50(paths, zc, largest), p50(paths, zc, SIZE_4K)))
    return result


def transport_ratios(paths: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The transport's own goals: in-process hand-off and CPU fallback against their floors."""
    intra, handoff, cpu, raw = "intra_prepared", "thread_handoff", "cpu_fallback", "zenoh_copy"
    floor = "cpu_codec_floor"
    one_way = p50(paths, intra, SIZE_4K)
    return {
        "intra_one_way_4KiB": {
            "description": "ours in-process one-way p50 at 4 KiB, prepared message (us)",
            "unit": "us",
            **_verdict(one_way, 20.0, False, _missing(paths, (intra,), (SIZE_4K,)))},
        "intra_over_thread_handoff_4KiB": {
            "description": "ours in-process p50 / bare thread hand-off p50 at 4 KiB",
            **_verdict(ratio(one_way, p50(paths, handoff, SIZE_4K)), 1.5, False,
                       _missing(paths, (intra, handoff), (SIZE_4K,)))},
        "cpu_fallback_over_zenoh_16MiB": {
            "description": "ours CPU fallback p50 / raw Zenoh put p50 at 16 MiB",
            **_verdict(ratio(p50(paths, cpu, SIZE_16M), p50(paths, raw, SIZE_16M)), 1.1, False,
                       _missing(paths, (cpu, raw), (SIZE_16M,)))},
        "cpu_fallback_over_zenoh_4KiB": {
            "description": "ours CPU fallback p50 / raw Zenoh put p50 at 4 KiB",
            **_verdict(ratio(p50(paths, cpu, SIZE_4K), p50(paths, raw, SIZE_4K)), 1.3, False,
                       _missing(paths, (cpu, raw), (SIZE_4K,)))},
        # Where the 4 KiB goal's time goes: the codec and view alone (no transport) against raw
        # Zenoh, and our transport against that floor.
        "cpu_codec_floor_over_zenoh_4KiB": _info(
            "floor (raw Zenoh carrying our CDR: codec + view only) / raw Zenoh put p50 at 4 KiB",
            ratio(p50(paths, floor, SIZE_4K), p50(paths, raw, SIZE_4K))),
        "cpu_fallback_over_codec_floor_4KiB": _info(
            "ours CPU fallback p50 / that floor at 4 KiB (our transport's own share)",
            ratio(p50(paths, cpu, SIZE_4K), p50(paths, floor, SIZE_4K))),
    }


def _info(description: str, value: float | None) -> dict[str, Any]:
    """A figure shown beside the goals without a verdict of its own."""
    return {"description": f"{description} (info)", "value": value, "target": None,
            "verdict": "INFO", "detail": ""}


# ----------------------------------------------------------------------------------- table


def _cell(value: float | None) -> str:
    if value is None:
        return "-"
    return f"{value:,.0f}" if value >= 100 else f"{value:.1f}"


def _grid(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) if i == 0 else c.rjust(w)
                       for i, (c, w) in enumerate(zip(row, widths))) for row in [header, *rows]]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def format_table(report: dict[str, Any]) -> str:
    """Latency (p50/p90/p99 per size), rate and copies per path; the ratios; the machine."""
    paths: dict[str, Any] = report["paths"]
    sizes = report["plan"]["sizes"]
    out = [f"Machine: {report['machine_line']}", f"Latency: {report['method']}"]
    rounds = report["plan"].get("rounds", 1)
    if rounds > 1:
        out.append(f"Rounds: {rounds}, every path in turn; each figure is the median over the "
                   "rounds (each round's p50 in bench.json)")
    out.append("")
    for stat in ("p50", "p90", "p99"):
        header = [f"one-way {stat} (us)"] + [format_size(s) for s in sizes]
        rows = []
        for entry in paths.values():
            latency = entry.get("latency_us") or {}
            if entry["status"] in ("unavailable", "error"):
                rows.append([entry["label"]] + [entry["status"]] * len(sizes))
                continue
            rows.append([entry["label"]] + [
                _cell(latency.get(str(s), {}).get(f"{stat}_us")) for s in sizes])
        out += [_grid(header, rows), ""]
    rate_rows = []
    for entry in paths.values():
        rate = entry.get("rate") or {}
        copies = entry.get("copies") or {}
        copied = "; ".join(f"{format_size(int(s))}: {c['bytes_copied_per_message']:,} B"
                           for s, c in copies.items()) if copies else "-"
        rate_rows.append([entry["label"], _cell(rate.get("msgs_per_s")), copied])
    out += [_grid(["path", "msg/s (4 KiB)", "bytes copied per message (ours, counted)"],
                  rate_rows), ""]
    notes = [f"  {e['label']}: {e['status']}: {e['reason']}" for e in paths.values()
             if e["status"] in ("unavailable", "error")]
    notes += [f"  {e['label']}: {error}" for e in paths.values() for error in e.get("errors", [])]
    if notes:
        out += ["Not measured:", *notes, ""]
    out.append("Ratios and targets:")
    for name, r in report["ratios"].items():
        unit = r.get("unit", "x")
        unit = " us" if unit == "us" else unit
        value = "n/a" if r["value"] is None else f"{r['value']:.2f}{unit}"
        target = "" if r["target"] is None else f" (target {'>=' if r.get('at_least') else '<='} "\
                                                 f"{r['target']:g}{unit})"
        detail = f"  [{r['detail']}]" if r.get("detail") else ""
        out.append(f"  {r['verdict']:<5} {r['description']}: {value}{target}{detail}")
    stages = report.get("stages")
    if stages and stages.get("status") == "ok":
        from benchmarks.stages import format_stages

        out += ["", format_stages(stages)]
    elif stages:
        out += ["", f"Stages: {stages.get('status')}: {stages.get('reason', '')}"]
    ipc_core = report.get("ipc_core", {})
    if ipc_core.get("status") == "ok" and ipc_core.get("text"):
        out += ["", ipc_core["text"]]
    elif ipc_core:
        out += ["", f"IPC core: {ipc_core.get('status')}: {ipc_core.get('reason', '')}"]
    bandwidth = report.get("copy_bandwidth", {})
    if bandwidth.get("status") == "ok" and bandwidth.get("text"):
        out += ["", "Copy kernels (benchmarks.copy_bandwidth --quick):", bandwidth["text"]]
    elif bandwidth:
        out += ["", f"Copy kernels: {bandwidth.get('status')}: {bandwidth.get('reason', '')}"]
    conversions = report.get("conversions", {})
    if conversions.get("status") == "ok" and conversions.get("text"):
        out += ["", "Tensor conversions (benchmarks.conversions):", conversions["text"]]
    elif conversions:
        out += ["", f"Tensor conversions: {conversions.get('status')}: "
                    f"{conversions.get('reason', '')}"]
    loans = report.get("loans", {})
    if loans.get("status") == "ok" and loans.get("text"):
        out += ["", "Loaned messages (benchmarks.loans):", loans["text"]]
    elif loans:
        out += ["", f"Loaned messages: {loans.get('status')}: {loans.get('reason', '')}"]
    return "\n".join(out)

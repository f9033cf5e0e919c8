"""Summary statistics of latency samples and message rates."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

PERCENTILES = (50, 90, 99)


def summarize_latency(samples_ns: Sequence[int]) -> dict[str, float]:
    """p50/p90/p99/mean/min/max in microseconds of one-way latency samples given in nanoseconds."""
    if not samples_ns:
        raise ValueError("no latency samples")
    us = np.asarray(samples_ns, dtype=np.float64) / 1e3
    summary = {f"p{p}_us": float(np.percentile(us, p)) for p in PERCENTILES}
    summary.update(
        mean_us=float(us.mean()), min_us=float(us.min()), max_us=float(us.max()), samples=len(us)
    )
    return summary


def ratio(numerator: float | None, denominator: float | None) -> float | None:
    """``numerator / denominator`` or None when either is missing, zero or not finite."""
    if numerator is None or denominator is None:
        return None
    if not (math.isfinite(numerator) and math.isfinite(denominator)) or denominator <= 0:
        return None
    return numerator / denominator


def format_size(nbytes: int) -> str:
    """Human size with binary units: 4096 -> '4 KiB'."""
    for unit, shift in (("GiB", 30), ("MiB", 20), ("KiB", 10)):
        if nbytes >= 1 << shift and nbytes % (1 << shift) == 0:
            return f"{nbytes >> shift} {unit}"
    return f"{nbytes} B"


def parse_size(text: str) -> int:
    """Parse '4K', '4KiB', '16M', '1G', '4096' into bytes (binary units)."""
    cleaned = text.strip().upper().replace("IB", "").replace("B", "")
    factors = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}
    if cleaned and cleaned[-1] in factors:
        value = int(float(cleaned[:-1]) * factors[cleaned[-1]])
    else:
        value = int(cleaned)
    if value <= 0:
        raise ValueError(f"size must be positive: {text!r}")
    return value

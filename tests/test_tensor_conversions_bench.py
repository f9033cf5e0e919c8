"""benchmarks.conversions keeps working (structure only: speed targets live in the benchmark)."""

from __future__ import annotations

import pytest

from benchmarks import conversions

pytestmark = pytest.mark.usefixtures("warp_pool_drained")


def test_conversions_benchmark_reports_every_framework_and_storage():
    rows = conversions.measure(repeat=2)
    assert {(r["framework"], r["backend"]) for r in rows} == {
        (f, b) for f in ("torch", "numpy", "warp") for b in ("cpu", "warp")}
    for row in rows:
        assert row["input_view_us"] > 0 and row["floor_us"] > 0
        assert row["input_view_median_us"] >= row["input_view_us"]
    images = conversions.measure_images(repeat=2)
    text = conversions.format_report(rows, images)
    assert "view/goal" in text and f"<= {conversions.GOAL_INPUT_VIEW_US:.0f} us" in text
    assert len(text.splitlines()) == 2 + len(rows) + len(images)

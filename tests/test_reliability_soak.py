"""Soak: at least 100,000 messages through the warp path (export in this process, import in a
child whose subscriptions join and leave), with open fds, /dev/shm mappings, /dev/shm files and
RSS sampled on both sides.

Bounds: fds and mappings are O(1) on both sides: the publisher holds one arena (its memfd and
mapping, its hand-off socket) whatever the number in flight, the subscriber one mapping of that
arena (kept between turns) and one fd; neither names anything in /dev/shm. Both RSS stay flat
after warm-up, and the pool reuses its blocks (a block pinned per departed subscription, or a
leak of one block per thousand messages, would break it).

``SOAK_MESSAGES`` sets the size of the default run (100,000); ``-m slow`` runs 1,000,000.
"""

from __future__ import annotations

import os
import time
import uuid

import pytest

from buffer_pubsub import Node
from tests._pubsub_helpers import TENSOR, make_frame
from tests._reliability_helpers import Child, release_pool_memory, resources

pytestmark = pytest.mark.multiprocess

MESSAGES = int(os.environ.get("SOAK_MESSAGES", "100000"))
LONG_MESSAGES = 1_000_000
WINDOW = 600  # messages in flight at most (publisher waits for the child's GOT lines)
SAMPLE_EVERY = 5_000
WARM_UP = 0.25  # fraction of the run before the baseline sample
# Publisher fds and mappings above the first sample: O(1), whatever is in flight. Zenoh and the
# hand-off's short-lived connections move the fd count by a few; a block fd per message in
# flight (the old design: +600) or a leak of one per thousand messages (+100) would break it.
FD_CEILING = 16
RSS_MARGIN_KIB = 48 * 1024  # allocator noise after warm-up
SUBSCRIBER_FD_MARGIN = 8


def _size(index: int) -> int:
    return 256 + (index * 997) % (4096 - 256)  # 256 B .. 4 KiB


def soak(messages: int) -> dict:
    """Publish ``messages`` frames that the child receives through the warp path (it joins
    and leaves), keeping at most WINDOW in flight; returns both sides' figures."""
    topic = f"/reliability/soak_{uuid.uuid4().hex[:8]}"
    domain = 4900 + os.getpid() % 50
    child = Child("soak", domain=domain, topic=topic, turn=2.0, gap=0.3, depth=WINDOW + 100)
    samples, published = [], 0
    before = resources()
    started = time.monotonic()
    try:
        with Node("soak_pub", domain_id=domain) as node:
            pub = node.create_publisher(TENSOR, topic, depth=WINDOW)
            child.wait_ready()
            sent_matched = 0  # published while a subscription was matched
            while child.progress() < messages:
                if pub.get_subscription_count() == 0:
                    sent_matched = child.progress()  # what was in flight is dropped with it
                    time.sleep(0.005)
                    continue
                if sent_matched - child.progress() >= WINDOW:
                    time.sleep(0.0005)
                    continue
                pub.publish(make_frame(0, published, _size(published), "warp"))
                published += 1
                sent_matched += 1
                if published % SAMPLE_EVERY == 0:
                    samples.append(resources())
                if time.monotonic() - started > 600:
                    raise TimeoutError(f"soak stalled at {child.progress()} messages")
            result = child.stop()
    finally:
        child.close()
    elapsed = time.monotonic() - started
    pool = release_pool_memory()
    return {"published": published, "elapsed": elapsed, "before": before,
            "pub_samples": samples, "child": result, "pool": pool}


def assert_flat(samples: list[dict], side: str, key: str, margin: int) -> None:
    """``key`` grows by at most ``margin`` after the warm-up sample."""
    assert len(samples) >= 4, f"{side}: too few samples to judge ({len(samples)})"
    settled = samples[int(len(samples) * WARM_UP):]
    peak = max(s[key] for s in settled)
    assert peak - settled[0][key] <= margin, (
        f"{side}: {key} grew from {settled[0][key]} to {peak} after warm-up: "
        f"{[s[key] for s in samples]}")


def assert_ceiling(samples: list[dict], before: dict, side: str) -> None:
    for key in ("fds", "maps"):  # the first sample has the Node, its Zenoh session and arena
        peak = max(s[key] for s in samples)
        assert peak - samples[0][key] <= FD_CEILING, (
            f"{side}: {key} rose from {samples[0][key]} to {peak} (ceiling +{FD_CEILING}): "
            f"{[s[key] for s in samples]}")
    assert max(s["maps"] for s in samples) - before["maps"] <= 2, "more than one arena mapped"
    assert max(s["shm_files"] for s in samples) == 0, f"{side}: files in /dev/shm"


def check_soak(messages: int) -> dict:
    figures = soak(messages)
    child = figures["child"]
    assert child["received"] >= messages
    assert child["backends"] == {"warp": child["received"]}, child["backends"]
    assert child["bad"] == 0 and child["errors"] == 0
    assert child["turns"] >= 3, "the subscriptions did not join and leave"
    assert_ceiling(figures["pub_samples"], figures["before"], "publisher")
    assert_flat(figures["pub_samples"], "publisher", "rss_kib", RSS_MARGIN_KIB)
    assert_flat(child["samples"], "subscriber", "rss_kib", RSS_MARGIN_KIB)
    assert_flat(child["samples"], "subscriber", "fds", SUBSCRIBER_FD_MARGIN)
    pool = figures["pool"]["cpu"]
    assert pool["reused"] >= 0.95 * figures["published"], pool  # steady state allocates nothing
    # The subscriber maps the publisher's arena once and keeps it (header + data): O(1).
    assert max(s["maps"] for s in child["samples"]) <= 2, child["samples"]
    assert max(s["shm_files"] for s in child["samples"]) == 0, child["samples"]
    assert all(s["leased"] == 0 for s in figures["pool"].values()), figures["pool"]
    summary = {k: v for k, v in figures.items() if k not in ("pub_samples", "child")}
    summary["pub_peak"] = {k: max(s[k] for s in figures["pub_samples"])
                           for k in figures["before"]}
    summary.update(received=child["received"], turns=child["turns"],
                   rate=round(child["received"] / figures["elapsed"]),
                   pub_last=figures["pub_samples"][-1], sub_last=child["samples"][-1])
    print(f"\nsoak: {summary}")
    return figures


def test_soak_warp_path_resources_stay_flat():
    check_soak(MESSAGES)


@pytest.mark.slow
def test_long_soak(request):
    if "slow" not in (request.config.option.markexpr or ""):
        pytest.skip("long soak: opt in with `-m slow`")
    check_soak(LONG_MESSAGES)

"""Holds follow messages across processes (issue 11 point 5 in the transport): a descriptor is
imported when it arrives, so a frame a slow keep-last subscriber evicts is released at once and
its block goes back to the publisher's pool, not when a later frame happens to be imported.
"""

from __future__ import annotations

import itertools
import os
import time
import uuid

import pytest

from buffer_pubsub import Node, fast_lane
from tests._pubsub_helpers import TENSOR, Child, make_frame
from tests._reliability_helpers import release_pool_memory
from warp_buffer import ipc

pytestmark = pytest.mark.multiprocess

BURST = 40
_domains = itertools.count(5000 + os.getpid() % 50 * 40)


def _created() -> int:
    return ipc.pool_stats()["cpu"]["created"]


@pytest.fixture(autouse=True)
def _pool_memory_back():
    yield
    release_pool_memory()


def test_frames_a_blocked_depth_1_subscriber_evicts_are_released_at_once(monkeypatch):
    """The subscriber's callback blocks on frame 0 while 40 more arrive: each arrival imports
    its frame and releases the one it evicts, so the publisher reuses a handful of blocks
    instead of pinning one per frame until the callback returns. (The Zenoh route: lane
    frames wait in the ring until the executor thread is free, see the README.)"""
    monkeypatch.setenv(fast_lane.ENV_SWITCH, "0")
    domain, topic = next(_domains), f"/holds/t_{uuid.uuid4().hex[:10]}"
    slow = Child("slow", module="tests._slow_child", domain=domain, topic=topic, depth=1)
    try:
        with Node("holds_pub", domain_id=domain) as node:
            pub = node.create_publisher(TENSOR, topic, depth=100)
            slow.wait_ready()
            assert pub.wait_for_subscriptions(1, timeout=10)
            pub.publish(make_frame(0, 0, 2048, "warp"))
            slow._expect("BLOCKED", 10)
            before = _created()
            for index in range(1, BURST + 1):
                pub.publish(make_frame(0, index, 2048, "warp"))
                time.sleep(0.01)  # arrivals are imported (and evictions released) meanwhile
            grown = _created() - before
            slow.proc.stdin.write("go\n")
            slow.proc.stdin.flush()
            time.sleep(0.3)
            result = slow.stop()
    finally:
        slow.close()
    assert grown <= BURST // 4, \
        f"{grown} new blocks for {BURST} frames: evicted frames stayed pinned"
    assert result["errors"] == 0 and result["seen"][0] == 0
    assert result["seen"][-1] == BURST  # the newest frame is the one kept
    assert result["dropped"] >= BURST - 3

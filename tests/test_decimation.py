"""A subscription's ``max_rate``: at most that many messages a second from each publisher.
Our publishers honour it before serializing for the subscription (nothing is sent to be thrown
away); messages from publishers that know nothing of it (rmw_zenoh) are dropped on arrival,
before they are decoded, and counted in ``decimated``."""

from __future__ import annotations

import time

import pytest

from buffer_pubsub import InvalidEndpointError, Node
from tests._pubsub_helpers import TENSOR, Child, make_frame
from tests.test_ros2_interop import Procs

pytestmark = pytest.mark.multiprocess

IMAGE = "sensor_msgs/msg/Image"


@pytest.mark.parametrize("accept, other, thinned_here", [
    ("cpu", "warp", False),  # alone on its stream: the publisher sends it 10 Hz
    ("warp", "warp", False),
    # beside another CPU-only subscription, it also listens on the shared _buf_cpu stream,
    # which carries every message: it thins that stream on arrival
    ("cpu", "cpu", True),
])
def test_our_publisher_sends_a_limited_subscription_only_what_it_takes(
        domain, topic, accept, other, thinned_here):
    """100 Hz published for 2 s; a subscription in another process asks for 10 Hz: it gets
    about 20 messages, none lost; when it has its stream to itself the publisher sent no more
    (nothing thinned on its side). A subscription without a limit beside it gets all 200."""
    limited = Child("sub", domain=domain, topic=topic, accept=accept, max_rate=10.0,
                    publishers=0)
    full = Child("sub", domain=domain, topic=topic, accept=other, publishers=0)
    try:
        limited.wait_ready()
        full.wait_ready()
        with Node("rate_pub", domain_id=domain) as node:
            pub = node.create_publisher(TENSOR, topic, depth=10)
            assert pub.wait_for_subscriptions(2, timeout=15)
            assert any("at most 10 messages a second" in r.reason for r in pub.routes())
            start = time.monotonic()
            for index in range(200):
                pub.publish(make_frame(0, index, 256, "warp"))
                time.sleep(max(0.0, start + (index + 1) * 0.01 - time.monotonic()))
            time.sleep(0.3)
            got_limited, got_full = limited.stop(), full.stop()
    finally:
        limited.close()
        full.close()
    assert len(got_full["records"]) == 200
    assert 15 <= len(got_limited["records"]) <= 25, len(got_limited["records"])
    counters = got_limited["counters"]
    assert (counters["decimated"] > 100) == thinned_here, counters
    assert counters["lost"] == 0 and counters["dropped"] == 0


def test_messages_of_an_rmw_zenoh_publisher_are_thinned_on_arrival(domain, topic):
    procs = Procs()
    got: list[str] = []
    try:
        with Node("rate_rx", domain_id=domain) as node:
            sub = node.create_subscription(IMAGE, topic, lambda m: got.append(m.header.frame_id),
                                           max_rate=5)
            pub = procs.model("pub", domain, topic, IMAGE, "--wait-subs", "1", "--count", "100",
                              "--rate", "50", "--size", "64", "--no-stdin")
            pub.communicate(timeout=60)
            time.sleep(0.3)
            counters = sub.counters
    finally:
        procs.close()
    assert 8 <= len(got) <= 12, got  # 2 s at 5 Hz
    assert counters.decimated == 100 - len(got) and counters.lost == 0


@pytest.mark.parametrize("bad", [0, -1, float("nan"), float("inf"), "fast", True])
def test_max_rate_must_be_a_positive_finite_rate(domain, topic, bad):
    with Node("rate_bad", domain_id=domain) as node:
        with pytest.raises(InvalidEndpointError, match="max_rate"):
            node.create_subscription(TENSOR, topic, lambda m: None, max_rate=bad)

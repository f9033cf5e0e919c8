"""The fast lane wired into the transport, with real processes: a SIGKILLed lane subscriber or
lane publisher leaves no lane ring mapped in the survivor (it lets the dead peer's ring go),
publishing goes on, and a new peer gets the lane.
"""

from __future__ import annotations

import itertools
import os
import time
import uuid

import pytest

from tests._pubsub_helpers import TENSOR, Child, check_frame, make_frame, use_fake_backend
from tests.conftest import lane_files

pytestmark = [pytest.mark.multiprocess]

use_fake_backend()

from buffer_pubsub import Node, fast_lane  # noqa: E402
from rosidl_buffer import registry  # noqa: E402

_domains = itertools.count(6000 + os.getpid() % 50 * 40)


@pytest.fixture
def setting(monkeypatch):
    monkeypatch.setenv(fast_lane.ENV_SWITCH, "1")
    loaded, _errors = registry.load_backends()
    return next(_domains), f"/lane_wired/t_{uuid.uuid4().hex[:10]}", loaded


def _settles(predicate, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def test_sigkilled_lane_subscriber_is_cleaned_and_publishing_goes_on(setting):
    domain, topic, backends = setting
    children = []
    try:
        with Node("lane_kill_pub", domain_id=domain, backends=backends) as node:
            pub = node.create_publisher(TENSOR, topic)
            baseline = lane_files()
            for round_ in range(2):  # the second subscriber gets the lane again
                sub = Child("sub", domain=domain, topic=topic, accept="fake", expect=5)
                children.append(sub)
                sub.wait_ready()
                assert pub.wait_for_subscriptions(1, timeout=10)
                peer = next(iter(pub._peers.values()))
                assert _settles(lambda: peer.lane is not None), "no lane to the subscriber"
                for index in range(5):
                    pub.publish(make_frame(0, index, 256, "fake"))
                    time.sleep(0.005)
                assert lane_files() > baseline
                sub.proc.kill()
                sub.proc.wait(timeout=10)
                assert _settles(lambda: pub.get_subscription_count() == 0)
                pub.publish(make_frame(0, 99, 256, "fake"))  # nobody left: must not fail
                assert _settles(lambda: lane_files() <= baseline), \
                    f"left by the killed subscriber: {sorted(lane_files() - baseline)}"
    finally:
        for child in children:
            child.close()


def test_sigkilled_lane_publisher_is_cleaned_and_the_next_one_uses_the_lane(setting):
    domain, topic, backends = setting
    got = []
    children = []
    try:
        with Node("lane_kill_sub", domain_id=domain, backends=backends) as node:
            sub = node.create_subscription(TENSOR, topic, lambda m, i: got.append((m, i)),
                                           depth=100, acceptable_buffer_backends="fake",
                                           with_info=True)
            baseline = lane_files()
            for pub_id in (1, 2):
                pub = Child("pub", domain=domain, topic=topic, backend="fake", pub_id=pub_id,
                            count=10, interval=0.01)
                children.append(pub)
                pub.wait_ready()
                assert _settles(lambda: sum(check_frame(m)["pub"] == pub_id
                                            for m, _ in got) >= 5)
                pub.proc.kill()
                pub.proc.wait(timeout=10)
                assert _settles(lambda: sub.get_publisher_count() == 0)
                assert _settles(lambda: lane_files() <= baseline), \
                    f"left by the killed publisher: {sorted(lane_files() - baseline)}"
            assert sub.counters.errors == 0
    finally:
        for child in children:
            child.close()
    routes = {pub_id: {i.route for m, i in got if check_frame(m)["pub"] == pub_id}
              for pub_id in (1, 2)}
    assert routes == {1: {"lane"}, 2: {"lane"}}
    assert all(check_frame(m)["ok"] for m, _ in got)


def test_a_slow_subscriber_on_the_lane_counts_its_backlog_as_dropped_not_lost(setting):
    """The lane's keep-last queue overwrites what a slow callback did not take: the
    subscriber's own backlog, counted in ``dropped`` as on Zenoh, never as transport loss."""
    domain, topic, backends = setting
    routes = set()

    def slow(msg, info) -> None:
        routes.add(info.route)
        time.sleep(0.01)

    with Node("lane_slow", domain_id=domain, backends=backends) as node:
        sub = node.create_subscription(TENSOR, topic, slow, depth=5, with_info=True,
                                       acceptable_buffer_backends="warp")
        pub = Child("pub", domain=domain, topic=topic, backend="warp", count=300,
                    interval=0.001, size=1024)
        try:
            pub.wait_ready()
            assert _settles(lambda: sub.received + sub.counters.dropped >= 300, 30)
            pub.stop()
        finally:
            pub.close()
    assert "lane" in routes
    assert sub.counters.lost == 0 and sub.counters.dropped > 50
    assert sub.received + sub.counters.dropped == 300


def test_a_reader_that_starts_late_counts_what_the_lane_overwrote_before_its_first_read(
        setting):
    """Frames the lane's keep-last queue overwrote before the subscription's first read
    (nobody spun yet) are counted in ``dropped``: everything published is accounted for."""
    from buffer_pubsub.executors import SingleThreadedExecutor

    domain, topic, backends = setting
    count = 40
    executor = SingleThreadedExecutor()
    with Node("lane_late", domain_id=domain, backends=backends) as node:
        executor.add_node(node)  # which nobody spins until the publisher is done
        routes = []
        sub = node.create_subscription(TENSOR, topic, lambda m, i: routes.append(i.route),
                                       depth=4, with_info=True, acceptable_buffer_backends="fake")
        pub = Child("pub", domain=domain, topic=topic, backend="fake", count=count,
                    interval=0.002, size=256)
        try:
            pub.wait_ready()
            time.sleep(1.0)  # every frame is written meanwhile
            deadline = time.monotonic() + 10
            while sub.received + sub.counters.dropped < count and time.monotonic() < deadline:
                executor.spin_once(0.1)
            pub.stop()
        finally:
            pub.close()
            executor.shutdown()
    assert set(routes) == {"lane"}
    assert sub.counters.lost == 0 and sub.received <= 4 + 1, sub.counters
    assert sub.received + sub.counters.dropped == count, sub.counters


def test_topic_info_says_why_a_deep_subscription_takes_zenoh_and_not_the_lane(setting):
    """A same-host subscription whose queue is deeper than the lane's ring takes its own Zenoh
    stream; ``routes()`` (``topic info -v``) said only "own stream", and a user could not tell
    why the lane was skipped."""
    domain, topic, backends = setting
    depth = fast_lane.MAX_DEPTH + 1
    with Node("deep_sub_pub", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)
        sub = Child("sub", domain=domain, topic=topic, accept="fake", depth=depth)
        try:
            sub.wait_ready()
            assert pub.wait_for_subscriptions(1, timeout=10)
            (route,) = pub.routes()
        finally:
            sub.close()
    assert route.route == "descriptor", route
    assert route.via.startswith("own stream (_buf/<gid>)")
    assert f"({depth}) is deeper than the same-host lane's {fast_lane.MAX_DEPTH}" in route.via

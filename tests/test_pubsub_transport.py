"""The transport under faults and beside other ROS 2 implementations (issue 12), with real
processes: a frozen (SIGSTOPped) subscriber, a raw Zenoh peer publishing with foreign gids on our
keys, Ctrl-C while a peer is frozen, a 1 GiB CPU payload, endpoint churn.

Every child is reaped in ``finally`` (a stopped one is killed and continued).
"""

from __future__ import annotations

import copy
import gc
import json
import os
import signal
import subprocess
import threading
import time
import zlib

import numpy as np
import pytest
import zenoh

from tests._pubsub_helpers import TENSOR, Child, check_frame, make_frame, use_fake_backend

pytestmark = pytest.mark.multiprocess

use_fake_backend()

from buffer_pubsub.config import (  # noqa: E402
    CONFIG_URI_ENV, DEFAULT_CONFIG, DROP_FRAGMENTS_WAIT_US)
from buffer_pubsub import (  # noqa: E402
    DEFAULT_CONFIG,
    ExecutorModeError,
    InvalidEndpointError,
    InvalidNameError,
    InvalidTimeoutError,
    Node,
    PayloadTooLargeError,
    wire,
)
from rosidl_buffer import registry  # noqa: E402
from rosidl_buffer.errors import SerializationError  # noqa: E402
from rosidl_buffer.messages import get_message_type  # noqa: E402

HELPERS = "tests._transport_helpers"




@pytest.fixture(scope="module")
def backends():
    loaded, _errors = registry.load_backends()
    assert "fake" in loaded
    return loaded


def _wait(predicate, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.01)
    return predicate()


# --------------------------------------------------------------------------- 1. foreign peers
def test_samples_from_foreign_gids_are_messages_and_refusals_are_counted(domain, topic,
                                                                          backends):
    got = []
    with Node("foreign_sub", domain_id=domain, backends=backends) as node:
        sub = node.create_subscription(TENSOR, topic, lambda m, i: got.append((m, i)), depth=50,
                                       with_info=True)
        peer = Child("foreign", module=HELPERS, domain=domain, topic=topic, mode="base", count=5)
        try:
            peer.wait_ready()
            assert _wait(lambda: len(got) >= 5 and sub.counters.rejected >= 2, 10)
            time.sleep(0.1)
            peer.stop()
        finally:
            peer.close()
    assert sorted(check_frame(m)["index"] for m, _ in got) == list(range(5))
    assert {i.route for _, i in got} == {"base"}
    assert len({i.publisher_gid for _, i in got}) == 5  # five random gids, none with a token
    assert sub.counters.refused == {"attachment": 2} and sub.counters.rejected == 2


def test_spoofed_sequence_jump_does_not_count_as_loss(domain, topic, backends):
    with Node("seq_sub", domain_id=domain, backends=backends) as node:
        sub = node.create_subscription(TENSOR, topic, lambda m: None, depth=50)
        peer = Child("foreign", module=HELPERS, domain=domain, topic=topic, mode="seq")
        try:
            peer.wait_ready()
            assert _wait(lambda: sub.received >= 6, 10)
            peer.stop()
        finally:
            peer.close()
    # 1, 2, 2**62 (jump), 2**62+1, 3 (jump back), 5 (one lost)
    assert sub.counters.lost == 1 and sub.counters.sequence_jumps == 2


def test_a_restarted_foreign_publisher_is_followed_not_refused(domain, topic, backends):
    """A publisher of another implementation that numbers again from 1 under the same gid (a
    restarted rmw_zenoh node with a pinned Zenoh id) is resynchronized: rmw_zenoh drops nothing
    for it, and neither does a keep-last subscription of ours."""
    got = []
    with Node("restart_sub", domain_id=domain, backends=backends) as node:
        sub = node.create_subscription(TENSOR, topic, got.append, depth=50)
        peer = Child("foreign", module=HELPERS, domain=domain, topic=topic, mode="restart")
        try:
            peer.wait_ready()
            assert _wait(lambda: len(got) >= 30, 10)
            peer.stop()
        finally:
            peer.close()
    assert [check_frame(m)["index"] for m in got] == list(range(20)) + list(range(100, 110))
    assert sub.counters.refused == {} and sub.counters.lost == 0
    assert sub.counters.sequence_jumps == 1


def test_samples_of_undiscovered_publishers_are_delivered_at_once(domain, topic, backends):
    """As rmw_zenoh, samples on a subscription's own stream from a publisher whose token has
    not arrived (or never comes) are messages, decoded at once with the gid alone: nothing
    waits for discovery, and another subscription of the node keeps its rate."""
    got, ticks = [], []
    other_topic = topic + "_other"
    with Node("park_sub", domain_id=domain, backends=backends) as node:
        sub = node.create_subscription(TENSOR, topic, lambda m, i: got.append((m, i)),
                                       acceptable_buffer_backends="fake", with_info=True)
        node.create_subscription(TENSOR, other_topic, lambda m: ticks.append(time.monotonic()),
                                 depth=100)
        ticker = node.create_publisher(TENSOR, other_topic)
        frame = make_frame(0, 0, 64, "cpu")
        peer = Child("foreign", module=HELPERS, domain=domain, topic=topic, mode="buffer")
        try:
            peer.wait_ready()
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:
                ticker.publish(frame)
                time.sleep(0.01)
            assert _wait(lambda: len(got) == 5, 5)
            peer.stop()
        finally:
            peer.close()
    assert sorted(check_frame(m)["index"] for m, _ in got) == [0, 1, 10, 11, 12]
    assert {i.route for _, i in got} == {"buffer"}
    assert sub.counters.refused == {} and sub.counters.errors == 0
    # Before, each such sample held the node's only callback thread for 1 s.
    assert max(np.diff(ticks)) < 0.6, "a sample waiting for discovery stalled the executor"


# --------------------------------------------------------------------------- 2 + 3. frozen peer
def test_frozen_subscriber_neither_stalls_publish_nor_starves_the_healthy_one(
        domain, topic, backends):
    frozen = Child("sub", domain=domain, topic=topic, accept="cpu")
    healthy = Child("sub", domain=domain, topic=topic, accept="cpu", expect=120)
    count, durations = 120, []
    try:
        node = Node("frozen_pub", domain_id=domain, backends=backends)
        try:
            pub = node.create_publisher(TENSOR, topic, depth=10)
            frozen.wait_ready()
            healthy.wait_ready()
            assert pub.wait_for_subscriptions(2, timeout=10)
            os.kill(frozen.proc.pid, signal.SIGSTOP)
            for index in range(count):
                msg = make_frame(0, index, 512 * 1024, "cpu")
                start = time.perf_counter()
                pub.publish(msg)
                durations.append(time.perf_counter() - start)
                time.sleep(0.01)
            result = healthy.stop()
        finally:
            start = time.monotonic()
            node.close()
            close_s = time.monotonic() - start
    finally:
        frozen.close()
        healthy.close()
    # BLOCK would hold publish() ~5 s once the frozen peer's queue is full (60 MB sent).
    assert max(durations) < 1.0, f"publish() blocked {max(durations):.2f} s"
    assert len(result["records"]) >= 0.9 * count
    assert close_s < 4.0


def test_keep_all_blocks_and_keep_last_drops(domain, topic, backends):
    with Node("qos", domain_id=domain, backends=backends) as node:
        last = node.create_publisher(TENSOR, topic)
        every = node.create_publisher(TENSOR, topic, depth=5, history="keep_all")
        sub = node.create_subscription(TENSOR, topic, lambda m: None, depth=3,
                                       history="keep_all")
        assert last._congestion == zenoh.CongestionControl.DROP
        assert every._congestion == zenoh.CongestionControl.BLOCK
        assert every._token.qos.to_keyexpr() == "::2,5:,:,:,," and every._token.qos.keep_all
        assert sub._queue.maxlen is None


def test_ctrl_c_during_a_frozen_peer_raises_keyboard_interrupt_promptly(domain, topic):
    frozen = Child("sub", domain=domain, topic=topic, accept="cpu", publishers=0)
    flood = None
    try:
        frozen.wait_ready()
        flood = Child("flood", module=HELPERS, stderr=subprocess.PIPE, domain=domain,
                      topic=topic)
        flood.wait_ready()
        os.kill(frozen.proc.pid, signal.SIGSTOP)
        time.sleep(1.5)  # the frozen peer's queue fills
        os.kill(flood.proc.pid, signal.SIGINT)
        start = time.monotonic()
        rc = flood.proc.wait(timeout=15)
        exit_s = time.monotonic() - start
        stderr = flood.proc.stderr.read()
    finally:
        frozen.close()
        if flood is not None:
            flood.close()
    assert rc != 0 and "KeyboardInterrupt" in stderr, stderr[-2000:]
    assert "ZError" not in stderr and "TransportError" not in stderr, stderr[-2000:]
    assert exit_s < 6.0, f"exit took {exit_s:.1f} s"


def test_exit_never_masks_the_exception_in_flight(domain, backends, monkeypatch):
    node = Node("masking", domain_id=domain, backends=backends)

    def broken_close():
        raise zenoh.ZError("transport is gone")

    monkeypatch.setattr(node, "session", type("S", (), {"close": staticmethod(broken_close)})())
    with pytest.raises(KeyboardInterrupt):
        with node:
            raise KeyboardInterrupt
    assert node.closed


# --------------------------------------------------------------------------- 4. executor
def test_slow_subscriber_holds_one_pending_task_at_most(domain, topic, backends):
    peak = [0]
    stop = threading.Event()

    def slow(msg) -> None:
        time.sleep(0.01)

    with Node("slow_sub", domain_id=domain, backends=backends) as node:
        sub = node.create_subscription(TENSOR, topic, slow, depth=5)
        pub = Child("pub", domain=domain, topic=topic, backend="cpu", count=300, interval=0.001,
                    size=1024)

        def watch() -> None:
            while not stop.is_set():
                peak[0] = max(peak[0], len(node.scheduler._ready))
                time.sleep(0.0005)

        watcher = threading.Thread(target=watch)
        watcher.start()
        try:
            pub.wait_ready()
            assert _wait(lambda: sub.received + sub.counters.dropped + sub.lost >= 300, 20)
            pub.stop()
        finally:
            stop.set()
            watcher.join()
            pub.close()
    assert peak[0] <= 1
    assert sub.counters.dropped > 100
    assert sub.received + sub.counters.dropped + sub.lost == 300


def test_manual_executor_runs_callbacks_on_the_spinning_thread(domain, topic, backends):
    threads = []
    with Node("spinner", domain_id=domain, backends=backends, executor="manual") as node:
        node.create_subscription(TENSOR, topic, lambda m: threads.append(threading.get_ident()))
        pub = node.create_publisher(TENSOR, topic)
        pub.publish(make_frame(0, 0, 64, "cpu"))
        pub.publish(make_frame(0, 1, 64, "cpu"))
        time.sleep(0.05)
        assert threads == []  # nothing runs until the user spins
        assert node.spin_once(timeout=1.0) == 1 and node.spin_once(timeout=1.0) == 1
        assert node.spin_once(timeout=0.01) == 0
        node.spin(timeout=0.05)
    assert threads == [threading.get_ident()] * 2
    with Node("threaded", domain_id=domain, backends=backends) as node:
        with pytest.raises(ExecutorModeError):
            node.spin_once(0)


@pytest.mark.parametrize("lane", [True, False], ids=["lane", "no-lane"])
def test_spin_timeouts_read_as_rclpy_and_never_abort(domain, topic, backends, lane):
    """None, negative, inf or huge: wait until a callback is ready (inf once aborted the
    process in iceoryx2's Duration); NaN and strings: a typed error; the same with or
    without the lane."""
    got = []
    with Node("spin_t", domain_id=domain, backends=backends, executor="manual",
              fast_lane=lane) as node:
        node.create_subscription(TENSOR, topic, got.append,
                                 acceptable_buffer_backends="warp" if lane else "cpu")
        pub = node.create_publisher(TENSOR, topic)
        for index, timeout in enumerate((float("inf"), 1e300, 10**400, -1.0, None)):
            timer = threading.Timer(0.2, pub.publish, (make_frame(0, index, 64, "cpu"),))
            timer.start()
            start = time.monotonic()
            try:
                assert node.spin_once(timeout) == 1, timeout
            finally:
                timer.cancel()
            assert 0.1 < time.monotonic() - start < 10
        for bad in (float("nan"), "soon"):
            with pytest.raises(InvalidTimeoutError):
                node.spin_once(bad)
            with pytest.raises(InvalidTimeoutError):
                node.spin(bad)
        assert node.spin_once(0) == 0
    assert len(got) == 5


def test_waits_for_matches_read_their_arguments_as_spin_does(domain, topic, backends):
    """wait_for_subscriptions / wait_for_publishers: a NaN or string timeout and a count that
    is not a whole number >= 0 are typed errors (NaN once spun forever on a core); None,
    negative and infinite timeouts wait without limit, as spin_once's do."""
    with Node("wait_args", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)
        sub = node.create_subscription(TENSOR, topic + "_other", lambda m: None)
        for wait in (pub.wait_for_subscriptions, sub.wait_for_publishers):
            for bad in (float("nan"), "1", b"1"):
                with pytest.raises(InvalidTimeoutError):
                    wait(1, timeout=bad)
            for bad in ("a", -1, 1.5, True, None):
                with pytest.raises(InvalidEndpointError, match="count"):
                    wait(bad, timeout=0.05)
            start = time.monotonic()
            assert wait(1, timeout=0.05) is False
            assert time.monotonic() - start < 5
            for unlimited in (float("inf"), 1e300, -1):
                assert wait(0, timeout=unlimited) is True
        node.create_subscription(TENSOR, topic, lambda m: None)
        assert pub.wait_for_subscriptions(1, timeout=-1) is True  # no limit: until it matches


def test_a_node_is_spun_by_one_thread_at_a_time(domain, topic, backends):
    with Node("spin_one", domain_id=domain, backends=backends, executor="manual") as node:
        node.create_subscription(TENSOR, topic, lambda m: None)
        pub = node.create_publisher(TENSOR, topic)
        spinning = threading.Thread(target=node.spin_once, args=(None,))
        spinning.start()
        try:
            deadline = time.monotonic() + 5
            while not node._spin_lock.locked() and time.monotonic() < deadline:
                time.sleep(0.01)
            with pytest.raises(ExecutorModeError, match="already spinning"):
                node.spin_once(0)  # its callbacks would overlap the other thread's
        finally:
            pub.publish(make_frame(0, 0, 64, "cpu"))
            spinning.join(timeout=10)
        assert not spinning.is_alive()
        assert node.spin_once(0) == 0  # free again


# --------------------------------------------------------------------------- 5. payload limit
def test_payload_over_the_limit_is_a_typed_error(domain, topic, backends):
    config = json.loads(json.dumps(DEFAULT_CONFIG))
    config["transport"].setdefault("link", {}).setdefault("rx", {})["max_message_size"] = 65536
    sub = Child("sub", domain=domain, topic=topic, accept="cpu", expect=1)
    try:
        with Node("limited", zenoh.Config.from_json5(json.dumps(config)), domain_id=domain,
                  backends=backends) as node:
            assert node.max_message_size < 65536
            pub = node.create_publisher(TENSOR, topic)
            sub.wait_ready()
            assert pub.wait_for_subscriptions(1, timeout=10)
            with pytest.raises(PayloadTooLargeError):
                pub.publish(make_frame(0, 0, 100 * 1024, "cpu"))
            with pytest.raises(PayloadTooLargeError):  # just over: caught after serializing
                pub.publish(make_frame(0, 2, node.max_message_size - 8, "cpu"))
            pub.publish(make_frame(0, 1, 1024, "cpu"))
            time.sleep(0.3)
            result = sub.stop()
    finally:
        sub.close()
    assert [r["index"] for r in result["records"]] == [1]


def test_big_cpu_payloads_of_a_keep_last_publisher_arrive(domain, topic, backends):
    """Keep-last publishers drop under congestion (DROP), but a message that merely needs many
    fragments must not be dropped on a healthy link: with Zenoh's 50 ms default for queueing
    them, every message of 64 MiB and more vanished on loopback here."""
    sizes = (32 << 20, 96 << 20)
    sub = Child("sub", domain=domain, topic=topic, accept="cpu", expect=len(sizes), timeout=60)
    try:
        with Node("big_last", domain_id=domain, backends=backends) as node:
            pub = node.create_publisher(TENSOR, topic, depth=2)  # keep-last: DROP
            assert pub._congestion == zenoh.CongestionControl.DROP
            sub.wait_ready()
            assert pub.wait_for_subscriptions(1, timeout=10)
            for index, n in enumerate(sizes):
                pub.publish(make_frame(0, index, n, "cpu"))
                time.sleep(0.5)  # one in flight: nothing to drop but the fragments' deadline
            result = sub.stop(timeout=60)
    finally:
        sub.close()
    assert [r["index"] for r in result["records"]] == [0, 1], result["counters"]
    assert all(r["ok"] for r in result["records"])


def test_a_peer_frozen_during_big_messages_holds_publish_once_at_most(domain, topic, backends):
    """The fragments' deadline (DROP_FRAGMENTS_WAIT_US) is spent once, by the message in flight
    when the peer froze; afterwards each message gives up at Zenoh's first full queue (1 ms)."""
    frozen = Child("sub", domain=domain, topic=topic, accept="cpu")
    durations = []
    try:
        with Node("big_frozen", domain_id=domain, backends=backends) as node:
            pub = node.create_publisher(TENSOR, topic, depth=2)
            frozen.wait_ready()
            assert pub.wait_for_subscriptions(1, timeout=10)
            os.kill(frozen.proc.pid, signal.SIGSTOP)
            msg = make_frame(0, 0, 8 << 20, "cpu")
            for _ in range(12):
                start = time.perf_counter()
                pub.publish(msg)
                durations.append(time.perf_counter() - start)
    finally:
        frozen.close()
    cap = DROP_FRAGMENTS_WAIT_US / 1e6
    assert max(durations) < cap + 0.5, durations
    slow = [d for d in durations if d > 0.1]
    assert len(slow) <= 2, durations  # the queue fills within a message or two, then 1 ms each


def _one_gib_message(n: int, pattern: bool = True):
    # zeros are calloc'ed: pages untouched until read, so the error test costs no memory
    data = np.resize(np.arange(251, dtype=np.uint8), n) if pattern else np.zeros(n, np.uint8)
    tensor = get_message_type(TENSOR)
    return tensor(dtype_code=1, dtype_bits=8, dtype_lanes=1, shape=np.array([n]), data=data)


def test_one_gib_cpu_payload_is_a_typed_error_at_publish(domain, topic, backends):
    """Zenoh carries at most 1 GiB per message: a 1 GiB CPU payload (plus CDR framing) raises
    PayloadTooLargeError at publish() instead of vanishing with every counter at 0."""
    sub = Child("sub", domain=domain, topic=topic, accept="cpu", expect=1)
    try:
        with Node("gib_pub", domain_id=domain, backends=backends) as node:
            pub = node.create_publisher(TENSOR, topic, depth=1)
            sub.wait_ready()
            assert pub.wait_for_subscriptions(1, timeout=10)
            msg = _one_gib_message(1 << 30, pattern=False)
            with pytest.raises(PayloadTooLargeError, match="1 GiB"):
                pub.publish(msg)
            del msg
            pub.publish(make_frame(0, 3, 1024, "cpu"))  # the publisher goes on
            time.sleep(0.3)
            result = sub.stop()
    finally:
        sub.close()
    assert [r["index"] for r in result["records"]] == [3]


@pytest.mark.slow
def test_largest_cpu_payload_arrives(domain, topic, backends):
    """Just under the limit (~1 GiB) arrives intact (about 5 GiB of memory, ~15 s)."""
    big = Child("big", module=HELPERS, domain=domain, topic=topic, count=1, timeout=90)
    try:
        with Node("big_pub", domain_id=domain, backends=backends) as node:
            n = node.max_message_size - 256
            pub = node.create_publisher(TENSOR, topic, depth=1, history="keep_all")
            big.wait_ready()
            assert pub.wait_for_subscriptions(1, timeout=10)
            msg = _one_gib_message(n)
            crc = zlib.crc32(msg.data.to_numpy())
            pub.publish(msg)
            del msg
            result = big.stop(timeout=90)  # the child waits for the frame first
    finally:
        big.close()
    assert result["records"] == [{"size": n, "crc": crc}], result["counters"]


# --------------------------------------------------------------------------- 6. validation, names
def test_field_values_are_validated_whoever_listens(domain, topic, backends):
    image_type = "sensor_msgs/msg/Image"
    got = []
    with Node("validate", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(image_type, topic)
        with pytest.raises(SerializationError, match="height"):
            pub.publish(get_message_type(image_type)(height="480"))  # nobody listens
        node.create_subscription(image_type, topic, got.append)
        with pytest.raises(SerializationError, match="height"):
            pub.publish(get_message_type(image_type)(height="480"))  # intra-process only
        with pytest.raises(SerializationError, match="out of range"):
            pub.publish(get_message_type(image_type)(height=-1))
        with pytest.raises(SerializationError, match="stamp"):
            msg = get_message_type(image_type)()
            msg.header.stamp.sec = 1.5
            pub.publish(msg)
        pub.publish(get_message_type(image_type)(height=480, encoding="rgb8"))
        assert _wait(lambda: len(got) == 1, 5)
    assert got[0].height == 480


@pytest.mark.parametrize("bad", ["bad topic name!", "a//b", "//a", "1abc", "a/", "~x", "{foo}/a",
                                 ""])
def test_bad_topic_names_are_rejected(domain, backends, bad):
    with Node("names", domain_id=domain, backends=backends) as node:
        with pytest.raises(InvalidNameError):
            node.create_publisher(TENSOR, bad)


def test_names_expand_like_rcl(domain, backends):
    for bad in ("1node", "bad/name", "bad-name", ""):
        with pytest.raises(InvalidNameError):
            Node(bad, domain_id=domain, backends=backends)
    for namespace in ("a//b", "//a"):  # (a leading '//' was stripped and accepted)
        with pytest.raises(InvalidNameError):
            Node("ok", namespace=namespace, domain_id=domain, backends=backends)
    with Node("me", namespace="/ns", domain_id=domain, backends=backends) as node:
        assert node.create_publisher(TENSOR, "~/priv").topic_name == "/ns/me/priv"
        assert node.create_publisher(TENSOR, "rel/t").topic_name == "/ns/rel/t"
        assert node.create_publisher(TENSOR, "/abs").topic_name == "/abs"
        assert node.create_publisher(TENSOR, "{node}/x").topic_name == "/ns/me/x"


# --------------------------------------------------------------------------- 7. races and churn
def _remote_subscription(pub, domain: int, entity_id: int, node_name: str) -> wire.EndpointToken:
    """A buffer-aware subscription token of another host matching ``pub`` (the fake backend)."""
    return wire.EndpointToken(
        domain_id=domain, zid="0" * 32, node_id=0, entity_id=entity_id,
        kind=wire.SUBSCRIPTION_KIND, namespace="", node_name=node_name, topic=pub.topic_name,
        type_name=TENSOR, type_hash=pub._token.type_hash, qos=wire.QoSProfile.of(10),
        locality=wire.Locality("h", 1, 0), backends={"fake": "fake-v1", "cpu": ""})


def _negotiate(pub, token: wire.EndpointToken, fake, meanwhile) -> set[bytes]:
    """Match ``pub`` with ``token``, running ``meanwhile()`` inside the backend's negotiation;
    the gids the backend was told are gone in the meantime."""
    original = type(fake).on_discovering_endpoint

    def negotiating(self, info, existing, supported):
        meanwhile()
        return original(self, info, existing, supported)

    type(fake).on_discovering_endpoint = negotiating
    gone = len(fake.gone)
    try:
        pub.on_subscription(token, True)
    finally:
        type(fake).on_discovering_endpoint = original
    return {e.gid for e in fake.gone[gone:]}


def test_peer_that_vanishes_during_negotiation_leaves_no_ghost(domain, topic, backends):
    fake = backends["fake"]
    with Node("ghost", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)
        token = _remote_subscription(pub, domain, entity_id=7, node_name="ghost_sub")
        with node.graph.lock:
            node.graph.put(token.key(), token)
        def delete_overtakes() -> None:
            # The DELETE overtakes the PUT's negotiation, as the discovery thread would do it.
            with node.graph.lock:
                node.graph.delete(token.key())
            pub.on_subscription(token, False)

        gone = _negotiate(pub, token, fake, delete_overtakes)
        assert token.gid not in pub._peers
        assert token.gid in gone


def test_a_node_closing_during_negotiation_does_not_report_a_live_peer_gone(domain, topic,
                                                                            backends):
    """The not-kept path took "not in the graph" from a check that is also False once the node
    closes: backends (shared by the process) forgot a subscription that another node's
    publisher still served, and recycled the blocks of its queued frames."""
    fake = backends["fake"]
    node = Node("closing_mid_negotiation", domain_id=domain, backends=backends)
    try:
        pub = node.create_publisher(TENSOR, topic)
        token = _remote_subscription(pub, domain, entity_id=9, node_name="live_sub")
        with node.graph.lock:
            node.graph.put(token.key(), token)
        def close_begins() -> None:  # the peer stays in the graph
            node.graph.closed = True

        gone = _negotiate(pub, token, fake, close_begins)
        assert token.gid not in pub._peers
        assert token.gid not in gone
    finally:
        node.graph.closed = False
        node.close()


def test_backend_forgets_endpoints_that_churn(domain, topic, backends):
    fake = backends["fake"]
    discovered, gone = len(fake.discovered), len(fake.gone)
    churn = Child("churn", module=HELPERS, domain=domain, topic=topic, count=8)
    try:
        with Node("churn_pub", domain_id=domain, backends=backends) as node:
            pub = node.create_publisher(TENSOR, topic)
            churn.wait_ready()
            result = churn.stop(timeout=60)
            assert _wait(lambda: pub.get_subscription_count() == 0, 5)
            assert _wait(lambda: not pub._peers, 5)
            seen = {e.gid for e in fake.discovered[discovered:] if e.topic_name == topic}
            forgotten = {e.gid for e in fake.gone[gone:]}
    finally:
        churn.close()
    assert result["matched"] == 8 and len(seen) == 8
    assert seen <= forgotten, "the backend was not told that churned peers are gone"
    # The publisher itself is reported gone when its node closes.
    assert pub.gid in {e.gid for e in fake.gone[gone:]}


def test_depth_is_bounded_and_deep_subscriptions_stay_off_the_lane(domain, topic, backends):
    from buffer_pubsub import fast_lane
    from buffer_pubsub.qos import MAX_DEPTH

    with Node("depths", domain_id=domain, backends=backends) as node:
        for depth in (0, -1, MAX_DEPTH + 1, 2**64):
            with pytest.raises(InvalidEndpointError, match="depth"):
                node.create_subscription(TENSOR, topic, lambda m: None, depth=depth)
        shallow = node.create_subscription(TENSOR, topic, lambda m: None,
                                           depth=fast_lane.MAX_DEPTH,
                                           acceptable_buffer_backends="warp")
        deep = node.create_subscription(TENSOR, topic, lambda m: None,
                                        depth=fast_lane.MAX_DEPTH + 1,
                                        acceptable_buffer_backends="warp")
        assert deep._lane_reader is None  # a ring preallocates every slot
        assert deep._queue.maxlen == fast_lane.MAX_DEPTH + 1
        if node.lane is not None:
            assert shallow._lane_reader is not None


def test_concurrent_publishers_threads_count_nothing_lost(domain, topic, backends):
    """Two threads publishing on one publisher: numbered and sent in the same order, so the
    subscription counts no gap (it counted the overtaken messages as lost)."""
    import sys

    per_thread = 1500
    with Node("two_threads", domain_id=domain, backends=backends) as node:
        sub = node.create_subscription(TENSOR, topic, lambda m: None, depth=10,
                                       acceptable_buffer_backends="cpu")
        pub = node.create_publisher(TENSOR, topic)
        msg = make_frame(0, 0, 64, "cpu")
        interval = sys.getswitchinterval()
        sys.setswitchinterval(1e-6)  # threads switch inside publish(), as under load
        try:
            threads = [threading.Thread(target=lambda: [pub.publish(msg)
                                                        for _ in range(per_thread)])
                       for _ in range(2)]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()
        finally:
            sys.setswitchinterval(interval)
        assert _wait(lambda: sub.received + sub.counters.dropped >= 2 * per_thread, 20)
    assert sub.counters.lost == 0 and sub.counters.sequence_jumps == 0
    assert sub.received + sub.counters.dropped == 2 * per_thread


def test_acceptable_backends_take_a_list_and_refuse_other_types(domain, topic, backends):
    with Node("accept_list", domain_id=domain, backends=backends) as node:
        names = [name for name in node.backends][:1] or []
        sub = node.create_subscription(TENSOR, topic, lambda m: None,
                                       acceptable_buffer_backends=["cpu", *names])
        assert set(sub.accepted) == {"cpu", *names}
        for bad in (5, [1, 2], {"cpu": 1}):
            with pytest.raises(InvalidEndpointError, match="acceptable_buffer_backends"):
                node.create_subscription(TENSOR, topic, lambda m: None,
                                         acceptable_buffer_backends=bad)


def test_a_frozen_warp_subscriber_on_the_lane_pins_a_bounded_number_of_blocks(
        domain, topic, backends):
    """A SIGSTOPped keep-last subscriber on the lane can only ever import the frames its
    ring still holds (and a few in hand): the publisher's pool holds about that many
    blocks for it, not one per publish (1.5 GB after 1,500 MiB frames before)."""
    from tests._pubsub_helpers import warp_available
    from warp_buffer import pool_stats
    from warp_buffer_backend.backend import IN_HAND

    if not warp_available():
        pytest.skip("the warp backend is not available")
    depth, count = 4, 200
    frozen = Child("sub", domain=domain, topic=topic, accept="warp", depth=depth)
    try:
        with Node("pin_pub", domain_id=domain, backends=backends) as node:
            if node.lane is None:
                pytest.skip("no fast lane here: Zenoh carries it, whose buffers bound nothing")
            pub = node.create_publisher(TENSOR, topic)
            frozen.wait_ready()
            assert pub.wait_for_subscriptions(1, timeout=10)
            (peer,) = pub._remote.own
            assert peer.lane is not None and peer.route_info.delivery_queue_depth == depth
            before = pool_stats().get("cpu", {}).get("created", 0)
            os.kill(frozen.proc.pid, signal.SIGSTOP)
            for index in range(count):
                pub.publish(make_frame(0, index, 64 * 1024, "warp"))
            gc.collect()
            pinned = pool_stats()["cpu"]["created"] - before  # blocks it could not reuse
    finally:
        frozen.close()
    # bounded whatever the count (26 for 100 or 200 publishes here): the window, and a few
    # the pool's probing order leaves behind
    assert pinned <= depth + IN_HAND + 8, f"{pinned} blocks pinned for a lane of depth {depth}"


def test_a_lane_frame_recycled_before_its_import_counts_as_dropped(
        domain, topic, backends, tmp_path):
    """A keep-last reader descheduled between taking a frame off the lane and importing it,
    while the publisher goes more than its window ahead, finds the block recycled: a
    RecycledBufferError that the subscription counts in ``dropped`` (what its queue would have
    dropped), not in ``errors``; the frames after it arrive intact."""
    from tests._pubsub_helpers import warp_available
    from warp_buffer_backend.backend import IN_HAND

    if not warp_available():
        pytest.skip("the warp backend is not available")
    depth = 4
    ahead = depth + IN_HAND + 40
    release = tmp_path / "release"
    reader = Child("sub", domain=domain, topic=topic, accept="warp", depth=depth,
                   stall_first_import=release)
    try:
        with Node("recycle_pub", domain_id=domain, backends=backends) as node:
            if node.lane is None:
                pytest.skip("no fast lane here: Zenoh carries it, which bounds nothing")
            pub = node.create_publisher(TENSOR, topic)
            reader.wait_ready()
            assert pub.wait_for_subscriptions(1, timeout=10)
            (peer,) = pub._remote.own
            assert peer.lane is not None
            pub.publish(make_frame(0, 0, 64 * 1024, "warp"))
            reader._expect("TAKEN", 10)  # frame 0 is off the ring, its import waits
            for index in range(1, ahead + 1):
                pub.publish(make_frame(0, index, 64 * 1024, "warp"))
            gc.collect()
            release.touch()
            time.sleep(0.3)
            after = ahead + 1
            pub.publish(make_frame(0, after, 64 * 1024, "warp"))
            result = reader.stop(timeout=30)
    finally:
        reader.close()
    assert result["import"] == "RecycledBufferError", result.get("import")
    counters = result["counters"]
    assert counters["errors"] == 0 and counters["dropped"] >= 1, counters
    indexes = [r["index"] for r in result["records"]]
    assert 0 not in indexes and after in indexes, indexes
    assert all(r["ok"] and r["backend"] == "warp" for r in result["records"])


def test_a_subscriber_behind_on_zenoh_loses_nothing_to_recycling(domain, topic, backends):
    """Over Zenoh nothing bounds what is in flight (its queues, the sockets): a subscriber
    that was stopped and resumes imports every descriptor still on its way, none recycled."""
    from tests._pubsub_helpers import warp_available

    if not warp_available():
        pytest.skip("the warp backend is not available")
    count = 40
    late = Child("sub", domain=domain, topic=topic, accept="warp", depth=count, expect=count)
    try:
        with Node("zenoh_pub", domain_id=domain, backends=backends, fast_lane=False) as node:
            pub = node.create_publisher(TENSOR, topic)
            late.wait_ready()
            assert pub.wait_for_subscriptions(1, timeout=10)
            (peer,) = pub._remote.own
            assert peer.lane is None and peer.route_info.delivery_queue_depth == 0
            os.kill(late.proc.pid, signal.SIGSTOP)
            try:
                for index in range(count):
                    pub.publish(make_frame(0, index, 4096, "warp"))
                    time.sleep(0.002)
            finally:
                os.kill(late.proc.pid, signal.SIGCONT)
            result = late.stop(timeout=30)
    finally:
        late.close()
    assert result["counters"]["errors"] == 0, result["counters"]
    assert len(result["records"]) == count


@pytest.mark.parametrize("segment, history, depth", [
    ("::,10:,:,:,,", "keep_last", 10), ("::,:,:,:,,", "keep_last", 42),
    ("::1,7:,:,:,,", "keep_last", 7), ("::2,5:,:,:,,", "keep_all", 5),
    ("::,007:,:,:,,", "keep_last", 7),
])
def test_the_history_is_read_from_a_qos_segment(segment, history, depth):
    qos = wire.QoSProfile.from_keyexpr(segment)
    assert (qos.history_name, qos.depth) == (history, depth)


@pytest.mark.parametrize("segment", [
    "garbage", "::1,x:", "::1,7:,:,:", "::01,7:,:,:,,", "::1,-7:,:,:,,",
    "::1,\u00b2:,:,:,,",  # a digit to str.isdigit(), not to strtoull
])
def test_qos_segments_rmw_zenoh_rejects_are_refused(segment):
    with pytest.raises(wire.WireFormatError):
        wire.QoSProfile.from_keyexpr(segment)




@pytest.mark.usefixtures("sigint_raises")
def test_ctrl_c_during_a_bounded_teardown_step_lets_it_finish_then_propagates():
    """A second Ctrl-C while Node.close() waits on Zenoh must not leave the interpreter exiting
    with the step still inside Zenoh (the process aborted): the step finishes (within its
    bound), then KeyboardInterrupt goes on its way."""
    import signal as signals

    from buffer_pubsub._zenoh import run_bounded

    finished = []

    def slow_step():
        time.sleep(0.4)
        finished.append(True)

    main = threading.get_ident()
    timer = threading.Timer(0.1, signals.pthread_kill, (main, signals.SIGINT))
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            run_bounded(slow_step, 5.0, "a test step")
    finally:
        timer.cancel()
    assert finished == [True]  # it was waited for before the interrupt surfaced


@pytest.mark.parametrize("history", ["keep_last", "keep_all"])
def test_a_subscriber_whose_link_closed_while_frozen_resumes_and_counts_what_it_missed(
        domain, topic, backends, tmp_path, monkeypatch, history):
    """Frozen past Zenoh's lease, a subscriber loses its link: its token leaves the publisher
    and comes back when it resumes. Its stream's numbers go on from where they stood, so the
    fresh messages are delivered (restarted from 1, a keep-last reader refused each as late
    until the numbers caught up; a keep-all one counted nothing lost) and everything the
    publisher sent is either received or counted (lost, or dropped by the lane's queue)."""
    from tests._pubsub_helpers import pick_backend

    backend = pick_backend()
    config = copy.deepcopy(DEFAULT_CONFIG)
    config["transport"]["link"]["tx"].update(lease=1000, keep_alive=4)  # link closed in ~1 s
    path = tmp_path / "short_lease.json5"
    path.write_text(json.dumps(config))
    monkeypatch.setenv(CONFIG_URI_ENV, str(path))
    sub = Child("sub", domain=domain, topic=topic, accept=backend, depth=10, history=history)
    published = 0
    try:
        with Node("lease_pub", domain_id=domain, backends=backends) as node:
            pub = node.create_publisher(TENSOR, topic, depth=10, history=history)
            sub.wait_ready()
            assert pub.wait_for_subscriptions(1, timeout=10)

            def burst(seconds: float) -> None:
                nonlocal published
                end = time.monotonic() + seconds
                while time.monotonic() < end:
                    pub.publish(make_frame(0, published, 4096, backend))
                    published += 1
                    time.sleep(0.01)

            burst(0.3)
            os.kill(sub.proc.pid, signal.SIGSTOP)
            burst(3.0)  # the link closes: the subscription leaves the publisher's graph
            left = not pub._peers
            os.kill(sub.proc.pid, signal.SIGCONT)
            assert pub.wait_for_subscriptions(1, timeout=10)
            burst(1.0)
            first_after = published
            burst(0.5)
            result = sub.stop()
    finally:
        sub.close()
    counters = result["counters"]
    indices = {r["index"] for r in result["records"]}
    assert left, "the link did not close: nothing was tested"
    assert counters["refused"] == {} and counters["errors"] == 0, counters
    assert set(range(first_after, published)) <= indices, counters
    assert counters["received"] + counters["lost"] + counters["dropped"] == published, counters


def test_durability_is_volatile_or_transient_local_and_a_latched_subscription_takes_cpu(
        domain, topic, backends):
    with Node("durability", domain_id=domain, backends=backends) as node:
        for bad in ("latched", "", 1):  # (None: the default)
            with pytest.raises(InvalidEndpointError, match="durability"):
                node.create_publisher(TENSOR, topic, durability=bad)
            with pytest.raises(InvalidEndpointError, match="durability"):
                node.create_subscription(TENSOR, topic, lambda m: None, durability=bad)
        with pytest.raises(InvalidEndpointError, match="CPU bytes only"):
            node.create_subscription(TENSOR, topic, lambda m: None, durability="transient_local",
                                     acceptable_buffer_backends="any")
        pub = node.create_publisher(TENSOR, topic, durability="transient_local")
        sub = node.create_subscription(TENSOR, topic, lambda m: None,
                                       durability="transient_local")
        for token in (pub._token, sub._token):
            assert token.qos.transient_local and token.backends is None
            assert token.qos.to_keyexpr().split(":")[1] == "1"  # rmw's TRANSIENT_LOCAL

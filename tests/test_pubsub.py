"""buffer_pubsub over real Zenoh sessions: the six topologies of the backend guide, a relay
pipeline, discovery (SIGKILL included), error counting, and the base-key fallback.

Topology tests use the ``warp`` backend once it is installed and the test-only ``fake`` backend
(tests/fake_backend) until then; every child process is reaped in ``finally``.
"""

from __future__ import annotations

import dataclasses

import os
import signal
import time

import numpy as np
import pytest
import zenoh

from tests._pubsub_helpers import (
    TENSOR,
    Child,
    check_frame,
    make_frame,
    pick_backend,
    use_fake_backend,
)
from tests._reliability_helpers import wait_until

pytestmark = pytest.mark.multiprocess

use_fake_backend()

from buffer_pubsub import (  # noqa: E402
    InvalidEndpointError,
    Node,
    NodeClosedError,
    WrongMessageTypeError,
    fast_lane,
    wire,
)
from rosidl_buffer import BufferReleasedError, registry  # noqa: E402
from warp_buffer.errors import HandleReleasedError  # noqa: E402
from rosidl_buffer.messages import get_message_type, serialize_message  # noqa: E402

BACKEND = pick_backend()
COUNT = 20
SIZE = 2048  # the fake backend carries payloads inline: stay under its 4000-byte bound




@pytest.fixture(params=["lane_on", "lane_off"])
def same_host(request, monkeypatch) -> str:
    """Run a topology with the same-host lane on (children inherit the switch) and off; the
    route a same-host inter-process backend subscription should then see."""
    on = request.param == "lane_on"
    monkeypatch.setenv(fast_lane.ENV_SWITCH, "1" if on else "0")
    return "lane" if on and fast_lane.status().available else "buffer"


@pytest.fixture(scope="module")
def backends():
    loaded, _errors = registry.load_backends()
    assert BACKEND in loaded
    return loaded


def _children(*children: Child):
    for child in children:
        child.wait_ready()


def _close(*children: Child) -> None:
    for child in children:
        child.close()


def _check_all(records, *, backend: str, route: str, count: int, pub: int = 0) -> None:
    mine = [r for r in records if r["pub"] == pub]
    assert len(mine) == count, (f"expected {count} frames from publisher {pub}, got "
                                f"{sorted(r['index'] for r in mine)} by {[r['route'] for r in mine]}")
    assert sorted(r["index"] for r in mine) == list(range(count))
    assert all(r["ok"] for r in mine), "payload checksum mismatch"
    assert {r["backend"] for r in mine} == {backend}
    assert {r["route"] for r in mine} == {route}


def _publish(pub, count: int = COUNT, backend: str = BACKEND, pub_id: int = 0) -> None:
    for index in range(count):
        pub.publish(make_frame(pub_id, index, SIZE, backend))
        time.sleep(0.003)
    time.sleep(0.3)  # let the last samples land before the children are told to stop


# --------------------------------------------------------------------------- 1. intra-process
@pytest.mark.parametrize("backend", [BACKEND, "cpu"])
def test_an_in_process_subscriber_releasing_its_message_ends_its_own_share_alone(
        domain, topic, backends, backend):
    """``msg.data.release()`` in an in-process callback refuses later access through that
    message, as across processes (the message shared the publisher's Buffer object, and
    release was a no-op); the publisher's buffer and another subscription's message read on."""
    got: dict[str, list] = {"a": [], "b": []}
    with Node("intra_release", domain_id=domain, backends=backends) as node:
        for name, seen in got.items():
            node.create_subscription(TENSOR, topic, seen.append, depth=5,
                                     acceptable_buffer_backends=backend)
        pub = node.create_publisher(TENSOR, topic)
        msg = make_frame(0, 7, SIZE, backend)
        pub.publish(msg)
        assert wait_until(lambda: got["a"] and got["b"], 10)
    mine, other = got["a"][0], got["b"][0]
    before = mine.data.to_numpy()
    mine.data.release()
    mine.data.release()  # idempotent
    refused = HandleReleasedError if backend == "warp" else BufferReleasedError
    with pytest.raises(refused):
        mine.data.to_numpy()
    assert len(mine.data) == SIZE and mine.data.get_backend_type() == backend
    assert check_frame(other)["ok"] and check_frame(msg)["ok"]
    assert np.array_equal(before, msg.data.to_numpy())


def test_intra_process_shares_the_payload_and_gives_cpu_only_a_copy(domain, topic, backends):
    got_backend, got_cpu = [], []
    with Node("intra_pub", domain_id=domain, backends=backends) as pub_node, \
            Node("intra_sub", domain_id=domain, backends=backends) as sub_node:
        s1 = sub_node.create_subscription(TENSOR, topic, lambda m, i: got_backend.append((m, i)),
                                          depth=COUNT, acceptable_buffer_backends=BACKEND,
                                          with_info=True)
        s2 = pub_node.create_subscription(TENSOR, topic, lambda m, i: got_cpu.append((m, i)),
                                          depth=COUNT, acceptable_buffer_backends="cpu",
                                          with_info=True)
        pub = pub_node.create_publisher(TENSOR, topic)
        assert pub.wait_for_subscriptions(2, timeout=10)
        # what `topic info -v` shows says what the subscriptions get: a snapshot, not the object
        reasons = [route.reason for route in pub.routes()]
        assert len(reasons) == 2 and all("a snapshot of the message" in r for r in reasons)
        sent = [make_frame(0, i, SIZE, BACKEND) for i in range(COUNT)]
        for msg in sent:
            pub.publish(msg)
        deadline = time.monotonic() + 10
        while (len(got_backend) < COUNT or len(got_cpu) < COUNT) and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.2)  # a duplicate through Zenoh would arrive in this window
    assert len(got_backend) == COUNT and len(got_cpu) == COUNT
    for msg, (received, info) in zip(sent, got_backend):
        # no serialization, no payload copy: a snapshot of the message over the same storage
        assert received is not msg and received.data.get_impl() is msg.data.get_impl()
        assert info.route == "intra"
        assert received.data.get_backend_type() == BACKEND
    for msg, (received, info) in zip(sent, got_cpu):
        assert received is not msg and received.data.get_backend_type() == "cpu"
        assert check_frame(received)["crc"] == check_frame(msg)["crc"]
        assert check_frame(received)["ok"]
    assert s1.counters.received == COUNT and s2.counters.received == COUNT
    assert s1.lost == s2.lost == 0


# --------------------------------------------------------------------------- 2. inter-process
def test_inter_process_same_host_uses_the_backend(domain, topic, backends, same_host):
    sub = Child("sub", domain=domain, topic=topic, accept=BACKEND, expect=COUNT)
    try:
        with Node("inter_pub", domain_id=domain, backends=backends) as node:
            pub = node.create_publisher(TENSOR, topic)
            _children(sub)
            assert pub.wait_for_subscriptions(1, timeout=10)
            _publish(pub)
            result = sub.stop()
    finally:
        _close(sub)
    _check_all(result["records"], backend=BACKEND, route=same_host, count=COUNT)
    assert result["counters"]["lost"] == 0 and result["counters"]["errors"] == 0


# --------------------------------------------------------------------------- 3 + 5. mixed, fallback
def test_mixed_intra_inter_and_cpu_fallback(domain, topic, backends, same_host):
    """One publisher; an intra-process subscription, a backend subscription in another process,
    and a CPU-only subscription beside it that must get correct bytes as "cpu"."""
    accel = Child("sub", domain=domain, topic=topic, accept=BACKEND, expect=COUNT)
    cpu = Child("sub", domain=domain, topic=topic, accept="cpu", expect=COUNT)
    local = []
    try:
        with Node("mixed_pub", domain_id=domain, backends=backends) as node:
            pub = node.create_publisher(TENSOR, topic)
            node.create_subscription(TENSOR, topic, lambda m, i: local.append((m, i)),
                                     depth=COUNT, acceptable_buffer_backends="any",
                                     with_info=True)
            _children(accel, cpu)
            assert pub.wait_for_subscriptions(3, timeout=10)
            assert pub.get_subscription_count() == 3
            _publish(pub)
            accel_result, cpu_result = accel.stop(), cpu.stop()
    finally:
        _close(accel, cpu)
    _check_all(accel_result["records"], backend=BACKEND, route=same_host, count=COUNT)
    _check_all(cpu_result["records"], backend="cpu", route="cpu", count=COUNT)
    assert [check_frame(m)["index"] for m, _ in local] == list(range(COUNT))
    assert {i.route for _, i in local} == {"intra"}
    assert {m.data.get_backend_type() for m, _ in local} == {BACKEND}


# --------------------------------------------------------------------------- 4. fan-in
def test_multi_publisher_fan_in(domain, topic, backends, same_host):
    pubs = [Child("pub", domain=domain, topic=topic, backend=BACKEND, pub_id=k, count=COUNT)
            for k in (1, 2)]
    received = []
    try:
        with Node("fan_in_sub", domain_id=domain, backends=backends) as node:
            sub = node.create_subscription(TENSOR, topic, lambda m, i: received.append((m, i)),
                                           depth=2 * COUNT, acceptable_buffer_backends=BACKEND,
                                           with_info=True)
            assert sub.wait_for_publishers(2, timeout=10)
            _children(*pubs)
            deadline = time.monotonic() + 15
            while len(received) < 2 * COUNT and time.monotonic() < deadline:
                time.sleep(0.02)
            time.sleep(0.2)
            for p in pubs:
                assert p.stop()["matched"]
            records = [dict(check_frame(m), route=i.route) for m, i in received]
            assert sub.counters.lost == 0 and sub.counters.errors == 0
    finally:
        _close(*pubs)
    for pub_id in (1, 2):
        _check_all(records, backend=BACKEND, route=same_host, count=COUNT, pub=pub_id)
    assert len(records) == 2 * COUNT


# --------------------------------------------------------------------------- 6. no duplicates
def test_mixed_no_duplicate(domain, topic, backends, same_host):
    """Subscriptions accepting the backend and CPU, while CPU and backend frames alternate and a
    CPU-only subscription shares the topic: each gets every frame once (never more)."""
    both = Child("sub", domain=domain, topic=topic, accept=f"{BACKEND},cpu", expect=COUNT)
    anyb = Child("sub", domain=domain, topic=topic, accept="any", expect=COUNT)
    cpu = Child("sub", domain=domain, topic=topic, accept="cpu", expect=COUNT)
    try:
        with Node("dup_pub", domain_id=domain, backends=backends) as node:
            pub = node.create_publisher(TENSOR, topic)
            _children(both, anyb, cpu)
            assert pub.wait_for_subscriptions(3, timeout=10)
            for index in range(COUNT):
                pub.publish(make_frame(0, index, SIZE, BACKEND if index % 2 else "cpu"))
                time.sleep(0.003)
            time.sleep(0.3)
            results = [c.stop() for c in (both, anyb, cpu)]
    finally:
        _close(both, anyb, cpu)
    for result in results:
        indices = [r["index"] for r in result["records"]]
        assert COUNT - 1 <= len(indices) <= COUNT
        assert len(set(indices)) == len(indices), "a frame arrived twice"
        assert all(r["ok"] for r in result["records"])
    for result in results[:2]:
        assert {r["backend"] for r in result["records"] if r["index"] % 2} == {BACKEND}
        assert {r["route"] for r in result["records"] if r["index"] % 2} == {same_host}
        assert {r["backend"] for r in result["records"] if not r["index"] % 2} == {"cpu"}
    assert {r["backend"] for r in results[2]["records"]} == {"cpu"}


# --------------------------------------------------------------------------- relay pipeline
def test_relay_pipeline_runs_a_warp_kernel(domain, topic, backends, same_host):
    out_topic = topic + "_out"
    key = 0x5A
    relay = Child("relay", domain=domain, topic=topic, out_topic=out_topic, accept=BACKEND,
                  xor=key)
    sink = Child("sub", domain=domain, topic=out_topic, accept=BACKEND, xor=key, expect=COUNT)
    try:
        with Node("relay_src", domain_id=domain, backends=backends) as node:
            pub = node.create_publisher(TENSOR, topic)
            _children(relay, sink)
            assert pub.wait_for_subscriptions(1, timeout=10)
            _publish(pub)
            sink_result = sink.stop()
            relay_result = relay.stop()
    finally:
        _close(relay, sink)
    assert relay_result["backends"] == [BACKEND] * COUNT
    _check_all(sink_result["records"], backend=BACKEND, route=same_host, count=COUNT)


# --------------------------------------------------------------------------- discovery
def test_sigkilled_subscriber_vanishes_from_the_graph(domain, topic, backends):
    sub = Child("sub", domain=domain, topic=topic, accept="cpu")
    try:
        with Node("kill_pub", domain_id=domain, backends=backends) as node:
            pub = node.create_publisher(TENSOR, topic)
            _children(sub)
            assert pub.wait_for_subscriptions(1, timeout=10)
            os.kill(sub.proc.pid, signal.SIGKILL)
            sub.proc.wait(timeout=10)
            deadline = time.monotonic() + 5
            while pub.get_subscription_count() and time.monotonic() < deadline:
                time.sleep(0.02)
            assert pub.get_subscription_count() == 0
            pub.publish(make_frame(0, 0, SIZE, BACKEND))  # nobody left: must not fail
    finally:
        _close(sub)


def test_negotiation_hooks_are_called(domain, topic, backends):
    fake = backends["fake"]
    created, discovered = len(fake.created), len(fake.discovered)
    with Node("hooks", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)
        sub = node.create_subscription(TENSOR, topic, lambda m: None,
                                       acceptable_buffer_backends="fake")
        assert pub.wait_for_subscriptions(1, timeout=10)
        deadline = time.monotonic() + 5
        while len(fake.discovered) == discovered and time.monotonic() < deadline:
            time.sleep(0.01)
    assert {e.gid for e in fake.created[created:]} == {pub.gid, sub.gid}
    peer = fake.discovered[discovered]
    # as rmw_zenoh advertises an explicit list: its backends besides cpu, with their metadata
    assert peer.gid == sub.gid and dict(peer.supported_backends) == {"fake": "fake-v1"}
    assert peer.process_id == os.getpid()


# --------------------------------------------------------------------------- errors and wire
def test_stale_descriptor_is_counted_and_the_subscription_goes_on(domain, topic, backends, same_host):
    """Frame 1 arrives with a descriptor the backend rejects (a typed error): it is counted, and
    the frames around it are delivered."""
    pub = Child("pub", domain=domain, topic=topic, backend="fake", count=3, stale_index=1)
    got = []
    try:
        with Node("stale_sub", domain_id=domain, backends=backends) as node:
            sub = node.create_subscription(TENSOR, topic, got.append,
                                           acceptable_buffer_backends="fake")
            _children(pub)
            deadline = time.monotonic() + 10
            while len(got) + sub.errors < 3 and time.monotonic() < deadline:
                time.sleep(0.01)
            pub.stop()
            assert sub.errors == 1 and sub.received == 2 and sub.lost == 0
            assert type(sub.last_error).__name__ == "BackendError"
    finally:
        _close(pub)
    assert [check_frame(m)["index"] for m in got] == [0, 2]
    assert {m.data.get_backend_type() for m in got} == {"fake"}


def test_samples_without_attachment_are_rejected_and_base_key_serves_plain_peers(
        domain, topic, backends):
    """A peer that knows nothing of buffers (pre-0.10.5 rmw_zenoh: no backends) gets CPU bytes on
    the base key; a bare sample with no attachment is dropped."""
    tensor = get_message_type(TENSOR)
    got, plain = [], []
    with Node("plain_pub", domain_id=domain, backends=backends) as node, \
            zenoh.open(zenoh.Config.from_json5(
                '{mode:"peer",listen:{endpoints:["tcp/127.0.0.1:0"]},'
                'scouting:{multicast:{enabled:true,interface:"lo"}}}')) as raw:
        sub = node.create_subscription(TENSOR, topic, got.append,
                                       acceptable_buffer_backends="cpu")
        token = wire.EndpointToken(
            domain_id=domain, zid=str(raw.zid()), node_id=0, entity_id=1,
            kind=wire.SUBSCRIPTION_KIND, namespace="", node_name="plain", topic=topic,
            type_name=TENSOR, type_hash=sub._token.type_hash, qos=wire.QoSProfile.of(10))
        base = wire.data_key(domain, topic, TENSOR)
        raw_sub = raw.declare_subscriber(
            base, lambda s: plain.append((s.payload.to_bytes(), s.attachment)))
        raw_token = raw.liveliness().declare_token(token.key())
        pub = node.create_publisher(TENSOR, topic)
        assert pub.wait_for_subscriptions(2, timeout=10)
        # The bare put goes out once Zenoh routes its key to our subscription (a fixed sleep
        # lost it on a loaded host), and the frame after it has been judged.
        bare = raw.declare_publisher(wire.cpu_channel_key(base))
        deadline = time.monotonic() + 10
        while not bare.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        bare.put(bytes(serialize_message(tensor())))  # no attachment
        while not sub.counters.rejected and time.monotonic() < deadline:
            time.sleep(0.01)
        bare.undeclare()
        pub.publish(make_frame(0, 7, SIZE, BACKEND))
        deadline = time.monotonic() + 5
        while (not plain or not got) and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.2)
        raw_token.undeclare()
        raw_sub.undeclare()
        assert sub.counters.rejected == 1
    assert len(plain) == 1 and len(got) == 1
    payload, attachment = plain[0]
    parsed = wire.Attachment.decode(attachment.to_bytes())
    assert parsed.sequence_number == 1 and parsed.publisher_gid == pub.gid
    from rosidl_buffer.messages import deserialize_message

    assert check_frame(deserialize_message(payload, tensor))["index"] == 7


def test_wire_layout():
    """Tokens, gid and attachment against values written out by hand from rmw_zenoh 0.10.5's
    liveliness_utils.cpp (Entity constructor, escape_backend_field) and attachment_helpers.cpp."""
    token = wire.EndpointToken(
        domain_id=0, zid="abc", node_id=1, entity_id=2, kind=wire.SUBSCRIPTION_KIND,
        namespace="/ns", node_name="n", topic="/robot1/chatter", type_name="std_msgs/msg/String",
        type_hash="RIHS01_" + "0" * 64, qos=wire.QoSProfile.of(10),
        locality=wire.Locality("id@host/x", 12, 1000),
        backends={"warp": "dev=cpu;a/b:c%", "cpu": ""})
    canonical = ("@ros2_lv/0/abc/1/2/MS/%/%ns/n/%robot1%chatter/std_msgs::msg::dds_::String_/"
                 "RIHS01_" + "0" * 64 + "/::,10:,:,:,,/backends:cpu:;warp:dev=cpu%3Ba%2Fb%3Ac%25")
    assert token.canonical_key() == canonical
    # ours adds the locality segment last, which rmw_zenoh drops when it rebuilds the key
    assert token.key() == canonical + "/wbloc:id@host%2Fx:12:1000"
    parsed = wire.parse_token(token.key())
    assert parsed == token and parsed.backends == token.backends
    assert wire.parse_token(canonical).gid == token.gid
    assert wire.data_key(0, "/robot1/chatter", "std_msgs/msg/String").startswith(
        "0/robot1/chatter/std_msgs::msg::dds_::String_/RIHS01_")
    att = wire.Attachment(5, 123, token.gid)
    assert len(att.encode()) == 33 and att.encode()[16] == 0x10
    assert wire.Attachment.decode(att.encode()) == att
    with pytest.raises(wire.WireFormatError):
        wire.Attachment.decode(b"\x00" * 32)
    import xxhash

    # The gid is XXH3-128 of the canonical key, the backends segment included: low 64 bits then
    # high 64 bits, each little endian.
    digest = xxhash.xxh3_128_intdigest(canonical.encode())
    assert token.gid == digest.to_bytes(16, "little")
    assert token.gid[:8] == (digest & (2**64 - 1)).to_bytes(8, "little")
    # a '*' (which a Zenoh key cannot hold) is escaped in the declared key, not in the hash
    starred = dataclasses.replace(token, backends={"warp": "a*b"})
    assert "warp:a%2Ab" in starred.key() and starred.canonical_key().endswith("warp:a*b")
    assert wire.parse_token(starred.key()).gid == starred.gid


def test_misuse_raises_typed_errors(domain, topic, backends):
    node = Node("misuse", domain_id=domain, backends=backends)
    try:
        with pytest.raises(InvalidEndpointError):
            node.create_subscription(TENSOR, topic, lambda m: None,
                                     acceptable_buffer_backends="nonexistent")
        with pytest.raises(InvalidEndpointError):
            node.create_publisher(TENSOR, topic, depth=0)
        pub = node.create_publisher(TENSOR, topic)
        for wrong in (get_message_type("sensor_msgs/msg/Image")(), None, {}, b"bytes"):
            with pytest.raises(WrongMessageTypeError, match="publisher of") as caught:
                pub.publish(wrong)
            assert isinstance(caught.value, TypeError)  # and an InvalidEndpointError, as before
            assert isinstance(caught.value, InvalidEndpointError)
    finally:
        node.close()
    with pytest.raises(NodeClosedError):
        pub.publish(make_frame(0, 0, 16, "cpu"))
    with pytest.raises(NodeClosedError):
        node.create_publisher(TENSOR, topic)
    # a closed node knows no graph (it answered with its own closed endpoints) and spins nothing
    for query in (node.get_topic_names_and_types, node.get_node_names_and_namespaces,
                  lambda: node.count_subscribers(topic), lambda: node.count_publishers(topic),
                  lambda: node.get_endpoints_by_node("n"), lambda: node.spin_once(0)):
        with pytest.raises(NodeClosedError):
            query()
    with pytest.raises(InvalidEndpointError):
        Node("bad/name")


def test_keep_last_depth_drops_the_oldest(domain, topic, backends):
    import threading

    gate = threading.Event()
    got = []

    def slow(msg):
        gate.wait(5)
        got.append(check_frame(msg)["index"])

    with Node("depth", domain_id=domain, backends=backends) as node:
        sub = node.create_subscription(TENSOR, topic, slow, depth=3)
        pub = node.create_publisher(TENSOR, topic)
        for index in range(10):
            pub.publish(make_frame(0, index, 64, "cpu"))
        gate.set()
        deadline = time.monotonic() + 5
        while sub.received + sub.counters.dropped < 10 and time.monotonic() < deadline:
            time.sleep(0.01)
    assert got[-3:] == [7, 8, 9] and sub.counters.dropped == 10 - len(got)
    assert np.all(np.diff(got) > 0)


def _raw_session():
    return zenoh.open(zenoh.Config.from_json5(
        '{mode:"peer",listen:{endpoints:["tcp/127.0.0.1:0"]},'
        'scouting:{multicast:{enabled:true,interface:"lo"}}}'))


def test_a_twin_token_with_the_same_gid_never_replaces_or_removes_the_endpoint(
        domain, topic, backends):
    """A foreign token repeating a subscription's 13 stock segments (same gid, no extra
    segment) is kept aside: the real endpoint stays, and the twin's DELETE removes nothing."""
    with Node("twin_pub", domain_id=domain, backends=backends) as node, _raw_session() as raw:
        pub = node.create_publisher(TENSOR, topic)
        real = wire.EndpointToken(
            domain_id=domain, zid=str(raw.zid()), node_id=0, entity_id=1,
            kind=wire.SUBSCRIPTION_KIND, namespace="", node_name="real", topic=topic,
            type_name=TENSOR, type_hash=pub._token.type_hash, qos=wire.QoSProfile.of(10),
            backends={"cpu": ""})
        real_key = real.key()
        # a segment after the 14th is dropped from the rebuilt key: same gid, another key
        twin_key = real_key + "/wbloc:elsewhere:1:2"
        assert twin_key != real_key and wire.parse_token(twin_key).gid == real.gid
        real_token = raw.liveliness().declare_token(real_key)
        assert wait_until(lambda: real.gid in pub._peers)
        twin_token = raw.liveliness().declare_token(twin_key)
        time.sleep(0.5)
        assert node.graph.current(real.gid).locality is None  # still the real one
        twin_token.undeclare()
        time.sleep(0.5)
        assert real.gid in pub._peers and pub.get_subscription_count() == 1
        real_token.undeclare()
        assert wait_until(lambda: pub.get_subscription_count() == 0 and not pub._peers)


def test_tokens_with_impossible_type_names_are_ignored(domain, topic, backends, caplog):
    with Node("odd_types", domain_id=domain, backends=backends) as node, _raw_session() as raw:
        good = wire.EndpointToken(
            domain_id=domain, zid=str(raw.zid()), node_id=0, entity_id=1,
            kind=wire.SUBSCRIPTION_KIND, namespace="", node_name="odd", topic=topic,
            type_name=TENSOR, type_hash="RIHS01_00", qos=wire.QoSProfile.of(10)).key().split("/")
        tokens = []
        for dds in ("::::dds_::_", "a::b::dds_::_", "::msg::dds_::X_", "a b::msg::dds_::X_"):
            parts = list(good)
            parts[10] = dds
            tokens.append(raw.liveliness().declare_token("/".join(parts)))
        time.sleep(0.7)
        names = dict(node.get_topic_names_and_types())
        for token in tokens:
            token.undeclare()
    assert "callback error" not in caplog.text
    assert not [t for t in node.graph.endpoints() if t.node_name == "odd"]
    assert not any("/msg/X" == n or n.startswith("a/b") for types in names.values()
                   for n in types)


def test_a_raw_subscription_gets_the_serialized_bytes(domain, topic, backends):
    """rclpy's raw=True: the CDR bytes, nothing decoded (CPU-only: a descriptor means nothing
    serialized); in process, the message serialized as the wire would carry it."""
    from rosidl_buffer.messages import deserialize_message, serialize_message

    got = []
    with Node("raw", domain_id=domain, backends=backends) as node:
        with pytest.raises(InvalidEndpointError, match="raw"):
            node.create_subscription(TENSOR, topic, got.append, raw=True,
                                     acceptable_buffer_backends="any")
        node.create_subscription(TENSOR, topic, got.append, raw=True)
        pub = node.create_publisher(TENSOR, topic)
        frame = make_frame(0, 3, 64, "cpu")
        pub.publish(frame)
        assert wait_until(lambda: got)
    assert type(got[0]) is bytes and got[0] == bytes(serialize_message(frame))
    assert check_frame(deserialize_message(got[0], TENSOR))["index"] == 3


def test_our_subscription_without_backends_does_not_move_everyone_to_the_base_key(
        domain, topic, backends):
    """A subscription of ours that accepts "any" where no backend is installed advertises none,
    as rmw_zenoh's; it listens on its own stream, which our publishers know (it is ours): they
    serve it there, and the others keep their streams. A foreign subscription without backends
    (it listens on the base key only) moves everyone to the base key."""
    with Node("nobackends_pub", domain_id=domain, backends=backends) as node:
        pub = node.create_publisher(TENSOR, topic)

        def remote_subscription(entity_id: int, ours: bool) -> wire.EndpointToken:
            token = wire.EndpointToken(
                domain_id=domain, zid="0" * 32, node_id=0, entity_id=entity_id,
                kind=wire.SUBSCRIPTION_KIND, namespace="", node_name="remote", topic=topic,
                type_name=TENSOR, type_hash=pub._token.type_hash, qos=wire.QoSProfile.of(10),
                locality=wire.Locality("elsewhere", 1, 0) if ours else None)
            with node._lock:
                node.graph.put(token.key(), token)
            pub.on_subscription(token, True)
            return token

        ours = remote_subscription(1, ours=True)
        assert [p.token for p in pub._remote.own] == [ours] and not pub._remote.base
        (route,) = pub.routes()
        assert route.via == "own stream (_buf/<gid>)"
        remote_subscription(2, ours=False)
        assert pub._remote.base

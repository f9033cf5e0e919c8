"""Interoperability with ROS 2's rmw_zenoh 0.10.5 / 0.12.0, both ways, in separate processes.

The other side is :mod:`tests.upstream_model`: a model of rmw_zenoh written from its released
sources alone (its own tokens, gids, routing, numbering and framing over plain zenoh-python; it
imports nothing of ours). Each test starts model processes and checks what crossed: every
message exactly once, the bytes, the keys it came on, the numbers, and that both sides compute
the same gids.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from buffer_pubsub import Node
from rosidl_buffer import Buffer
from rosidl_buffer.messages import get_message_type, serialize_message
from tests._pubsub_helpers import ROOT, TENSOR, child_env, make_frame
from tests._reliability_helpers import wait_until
from tests.upstream_model import messages as model_messages

pytestmark = pytest.mark.multiprocess

IMAGE = "sensor_msgs/msg/Image"
SIZE = 4096
COUNT = 20


# --------------------------------------------------------------------------- processes
class Procs:
    """Child processes of one test: started with a pipe on stdin, reaped at the end."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def start(self, module: str, *args: str) -> subprocess.Popen:
        proc = subprocess.Popen([sys.executable, "-m", module, *args], cwd=ROOT,
                                env=child_env(), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        self.procs.append(proc)
        return proc

    def model(self, role: str, domain: int, topic: str, msg_type: str, *args: str
              ) -> subprocess.Popen:
        return self.start("tests.upstream_model", role, "--domain", str(domain), "--topic",
                          topic, "--type", msg_type, "--timeout", "60", *args)

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
            proc.communicate()


@pytest.fixture
def procs():
    children = Procs()
    yield children
    children.close()


def wait_ready(proc: subprocess.Popen, timeout: float = 30.0) -> None:
    line: list[str] = []
    reader = threading.Thread(target=lambda: line.append(proc.stdout.readline()), daemon=True)
    reader.start()
    reader.join(timeout)
    assert line and line[0] == "READY\n", (line, proc.poll())


def result(proc: subprocess.Popen, timeout: float = 60.0) -> dict:
    """Close its stdin (the stop signal), then its ``RESULT`` json."""
    out, err = proc.communicate(timeout=timeout)
    lines = [line for line in out.splitlines() if line.startswith("RESULT ")]
    assert lines, (out, err[-2000:])
    return json.loads(lines[-1][len("RESULT "):])


def sha(data) -> str:
    return hashlib.sha256(bytes(data)).hexdigest()


def image(index: int, backend: str = "cpu") -> object:
    """An Image of ours whose frame_id and bytes say which one it is."""
    data = np.frombuffer(model_messages.payload_pattern(index, SIZE), dtype=np.uint8)
    if backend == "warp":
        from tests._pubsub_helpers import make_buffer

        buffer = make_buffer(data, "warp")
    else:
        buffer = Buffer(data.copy())
    msg = get_message_type(IMAGE)(height=1, width=SIZE, encoding="mono8", step=SIZE,
                                  data=buffer)
    msg.header.frame_id = f"ours/{index}"
    return msg


# --------------------------------------------------------------------------- ROS 2 -> us
def test_an_upstream_publisher_reaches_our_cpu_and_warp_subscriptions(domain, topic, procs):
    """A buffer-aware rmw_zenoh publisher writes our CPU-only subscription on _buf_cpu and our
    warp-accepting one on its own _buf/<gid> (one sequence number per put, so 2 per publish):
    both get every image once with its bytes, and count nothing lost or refused. A pre-0.10.5
    subscription on the topic gets nothing from it (upstream's routing; see the README)."""
    got: dict[str, list] = {"cpu": [], "warp": []}
    legacy = procs.model("legacy-sub", domain, topic, IMAGE)
    wait_ready(legacy)
    with Node("interop_rx", domain_id=domain) as node:
        subs = {name: node.create_subscription(
            IMAGE, topic, lambda m, i, n=name: got[n].append(
                (m.header.frame_id, sha(m.data.to_numpy()), i.route, i.sequence_number)),
            depth=COUNT * 2, acceptable_buffer_backends=name, with_info=True)
            for name in got}
        pub = procs.model("pub", domain, topic, IMAGE, "--wait-subs", "3", "--count",
                          str(COUNT), "--rate", "50", "--size", str(SIZE), "--no-stdin")
        assert wait_until(lambda: node.count_publishers(topic) == 1)
        seen = {e.endpoint_gid.hex() for e in node.get_publishers_info_by_topic(topic)}
        sent = result(pub)
        assert sent["error"] is None
        assert wait_until(lambda: all(len(v) >= COUNT for v in got.values()))
        time.sleep(0.3)  # a duplicate would land here
        assert seen == {sent["gid"]}  # both sides compute the same gids
        discovered = {s["gid"] for s in sent["discovered_subscriptions"]}
        assert {subs["cpu"].gid.hex(), subs["warp"].gid.hex()} <= discovered
        counters = {name: sub.counters for name, sub in subs.items()}
    expected = [(f"model/{i}", sha(model_messages.payload_pattern(i, SIZE))) for i in range(COUNT)]
    assert [(f, h) for f, h, _, _ in got["cpu"]] == expected
    assert [(f, h) for f, h, _, _ in got["warp"]] == expected
    assert {r for _, _, r, _ in got["cpu"]} == {"cpu"}
    assert {r for _, _, r, _ in got["warp"]} == {"buffer"}
    for counter in counters.values():
        assert counter.lost == 0 and counter.refused == {} and counter.errors == 0
    # rmw_zenoh numbers every put (3 per publish here: _buf_cpu, ours, the legacy one's)
    for name in got:
        assert set(np.diff([s for _, _, _, s in got[name]])) == {3}, name
    assert result(legacy)["samples"] == []


# --------------------------------------------------------------------------- us -> ROS 2
@pytest.mark.parametrize("backend", ["cpu", "warp"])
def test_our_publisher_reaches_upstream_cpu_and_cuda_subscriptions_once(
        domain, topic, procs, backend):
    """An rmw_zenoh CPU-only subscription gets each image once on _buf_cpu, one accepting only
    `cuda` (which we do not have) once on its own _buf/<gid>, both as CPU bytes, numbered
    1, 2, 3... on their key (we number each stream), whatever memory our buffers live in."""
    cpu = procs.model("sub", domain, topic, IMAGE)
    cuda = procs.model("sub", domain, topic, IMAGE, "--backend", "cuda=dev=0",
                       "--acceptable-buffer-backends", "cuda")
    for proc in (cpu, cuda):
        wait_ready(proc)
    with Node("interop_tx", domain_id=domain) as node:
        pub = node.create_publisher(IMAGE, topic, depth=COUNT)
        assert pub.wait_for_subscriptions(2, timeout=15)
        routes = {r.subscription_gid.hex(): r for r in pub.routes()}
        for index in range(COUNT):
            pub.publish(image(index, backend))
            time.sleep(0.01)
        time.sleep(0.5)
        got = {"cpu": result(cpu), "cuda": result(cuda)}
    for name, key in (("cpu", "_buf_cpu"), ("cuda", f"_buf/{got['cuda']['gid']}")):
        samples = got[name]["samples"]
        assert [s["route"] for s in samples] == [key] * COUNT, name
        assert [s["seq"] for s in samples] == list(range(1, COUNT + 1))
        assert {s["gid"] for s in samples} == {pub.gid.hex()}
        assert [s["decoded"]["fields"]["header.frame_id"] for s in samples] == \
            [f"ours/{i}" for i in range(COUNT)]
        assert [s["decoded"]["buffers"]["data"] for s in samples] == [
            {"form": "cpu", "size": SIZE, "sha256": sha(model_messages.payload_pattern(i, SIZE))}
            for i in range(COUNT)]
        assert got[name]["lost"] == 0
        assert routes[got[name]["gid"]].route == "cpu"  # the gids agree, and so does the route


# --------------------------------------------------------------------------- mixed graph
def test_a_mixed_graph_gets_every_message_exactly_once(domain, topic, procs):
    """Our warp publisher, with an rmw_zenoh CPU-only subscription, a pre-0.10.5 one (no
    backends: it listens on the base key only), and two subscriptions of ours in another
    process (warp and CPU). The base key serves every ROS 2 subscription; ours that take warp
    descriptors keep their stream too and drop the base copy. Each gets each frame once."""
    model_cpu = procs.model("sub", domain, topic, TENSOR)
    model_legacy = procs.model("legacy-sub", domain, topic, TENSOR)
    ours = ("tests._pubsub_helpers", "sub", "--domain", str(domain), "--topic", topic,
            "--expect", str(COUNT), "--publishers", "0")
    ours_warp = procs.start(*ours, "--accept", "warp")
    ours_cpu = procs.start(*ours, "--accept", "cpu")
    for proc in (model_cpu, model_legacy, ours_warp, ours_cpu):
        wait_ready(proc)
    with Node("interop_mixed", domain_id=domain) as node:
        pub = node.create_publisher(TENSOR, topic, depth=COUNT)
        assert pub.wait_for_subscriptions(4, timeout=15)
        sent = [make_frame(0, index, SIZE, "warp") for index in range(COUNT)]
        for msg in sent:
            pub.publish(msg)
            time.sleep(0.01)
        expected = [sha(m.data.to_numpy()) for m in sent]
        time.sleep(0.5)
        got = {name: result(proc) for name, proc in (
            ("model_cpu", model_cpu), ("model_legacy", model_legacy), ("ours_warp", ours_warp),
            ("ours_cpu", ours_cpu))}
    for name in ("model_cpu", "model_legacy"):
        samples = got[name]["samples"]
        assert [s["decoded"]["buffers"]["data"]["sha256"] for s in samples] == expected, name
        assert {s["route"] for s in samples} == {"base"}, name
        assert got[name]["lost"] == 0
    for name in ("ours_warp", "ours_cpu"):
        records = got[name]["records"]
        assert sorted(r["index"] for r in records) == list(range(COUNT)), name
        assert all(r["ok"] for r in records)
        assert got[name]["counters"]["lost"] == 0
    warp_counters = got["ours_warp"]["counters"]
    # the warp subscription took descriptors where they arrived first, and dropped the copies
    assert warp_counters["refused"].get("duplicate", 0) == COUNT
    assert {r["backend"] for r in got["ours_warp"]["records"]} <= {"warp", "cpu"}


# --------------------------------------------------------------------------- churn
def test_subscriptions_that_come_and_go_never_get_a_message_twice(domain, topic, procs):
    """rmw_zenoh subscriptions (CPU-only and cuda) join and leave while we publish at 100 Hz:
    each gets a run of consecutive numbers on its one key, no image twice, none lost while it
    was matched; and ours, created and destroyed while an rmw_zenoh publisher runs, likewise."""
    stop = threading.Event()
    with Node("interop_churn", domain_id=domain) as node:
        pub = node.create_publisher(IMAGE, topic, depth=10)

        def publish() -> None:
            index = 0
            while not stop.is_set():
                pub.publish(image(index))
                index += 1
                time.sleep(0.01)

        publisher = threading.Thread(target=publish, daemon=True)
        publisher.start()
        results = []
        try:
            for turn in range(3):
                extra = (("--backend", "cuda=dev=0", "--acceptable-buffer-backends", "cuda")
                         if turn % 2 else ())
                proc = procs.model("sub", domain, topic, IMAGE, *extra)
                wait_ready(proc)
                time.sleep(0.6)
                results.append(result(proc))
        finally:
            stop.set()
            publisher.join(5)
    for got in results:
        samples = got["samples"]
        assert len(samples) > 10
        frames = [s["decoded"]["fields"]["header.frame_id"] for s in samples]
        assert len(set(frames)) == len(frames)
        assert len({s["route"] for s in samples}) == 1
        seqs = [s["seq"] for s in samples]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
        indices = [int(f.split("/")[1]) for f in frames]
        assert indices == list(range(indices[0], indices[0] + len(indices)))

    pub_proc = procs.model("pub", domain, topic, IMAGE, "--rate", "100", "--size", "256",
                           "--count", "6000")
    seen: list[tuple[str, str]] = []
    counters = []
    with Node("interop_churn_rx", domain_id=domain) as node:
        wait_ready(pub_proc)
        for turn in range(4):
            frames: list[str] = []
            sub = node.create_subscription(
                IMAGE, topic, lambda m, f=frames: f.append(m.header.frame_id), depth=100,
                acceptable_buffer_backends="warp" if turn % 2 else "cpu")
            assert wait_until(lambda f=frames: len(f) > 10)
            sub.destroy()
            seen.append(tuple(frames))
            counters.append(sub.counters)
    pub_proc.terminate()
    pub_proc.communicate(timeout=30)
    for frames, counter in zip(seen, counters):
        assert len(set(frames)) == len(frames)
        indices = [int(f.split("/")[1]) for f in frames]
        assert indices == list(range(indices[0], indices[0] + len(indices)))
        assert counter.lost == 0 and counter.refused == {}


# --------------------------------------------------------------------------- the graph
def test_the_graph_shows_rmw_zenoh_endpoints_as_rclpy_does(domain, topic, procs):
    """A node of ours lists rmw_zenoh nodes and endpoints with their QoS and advertised
    backends (a pre-0.10.5 subscription advertises none), under the gids they compute."""
    cuda = procs.model("sub", domain, topic, IMAGE, "--backend", "cuda=dev=0",
                       "--acceptable-buffer-backends", "cuda", "--node-name", "gpu_viewer",
                       "--namespace", "/robot", "--depth", "5")
    legacy = procs.model("legacy-sub", domain, topic, IMAGE, "--node-name", "old_viewer")
    for proc in (cuda, legacy):
        wait_ready(proc)
    with Node("observer", domain_id=domain) as node:
        assert wait_until(lambda: node.count_subscribers(topic) == 2)
        infos = {i.node_name: i for i in node.get_subscriptions_info_by_topic(topic)}
        nodes = node.get_node_names_and_namespaces()
        topics = dict(node.get_topic_names_and_types())
        got = {"cuda": result(cuda), "legacy": result(legacy)}
    assert ("gpu_viewer", "/robot") in nodes and ("old_viewer", "/") in nodes
    assert topics[topic] == [IMAGE]
    gpu, old = infos["gpu_viewer"], infos["old_viewer"]
    assert gpu.node_namespace == "/robot" and gpu.topic_type == IMAGE
    assert dict(gpu.backends) == {"cuda": "dev=0"} and old.backends is None
    assert gpu.qos_profile.depth == 5 and not gpu.qos_profile.keep_all
    assert not gpu.is_ours and not old.is_ours
    assert gpu.endpoint_gid.hex() == got["cuda"]["gid"]
    assert old.endpoint_gid.hex() == got["legacy"]["gid"]


# --------------------------------------------------------------------------- rmw_zenoh's topology
def _rmw_zenoh_session_config(path, router: str) -> str:
    """rmw_zenoh's DEFAULT_RMW_ZENOH_SESSION_CONFIG.json5 in what decides discovery: a peer
    that scouts nothing and connects to the router of its host; gossip from the router tells
    it of the other peers (Zenoh's shared memory off, as in every model process)."""
    path.write_text(json.dumps({
        "mode": "peer",
        "connect": {"endpoints": [router]},
        "listen": {"endpoints": ["tcp/localhost:0"]},
        "scouting": {"multicast": {"enabled": False},
                     "gossip": {"enabled": True, "multihop": False,
                                "target": {"router": ["router", "peer"], "peer": ["router"]},
                                "autoconnect": {"router": [], "peer": ["router", "peer"]}}},
        "transport": {"shared_memory": {"enabled": False}},
    }))
    return str(path)


def test_a_node_on_the_default_configuration_joins_rmw_zenohs_graph_through_its_router(
        domain, topic, procs, tmp_path, monkeypatch):
    """rmw_zenoh's nodes scout nothing: they find each other through the router of their host
    (``rmw_zenohd`` at tcp/localhost:7447). Our embedded default connects there too, so a node
    with nothing set receives an rmw_zenoh publisher's messages (here the router listens on a
    port of the test's, which ZENOH_CONFIG_OVERRIDE gives our node, as it gives rmw_zenoh's)."""
    from benchmarks.processes import free_tcp_port
    from buffer_pubsub.config import DEFAULT_CONFIG, LOCAL_ROUTER

    assert DEFAULT_CONFIG["connect"]["endpoints"] == [LOCAL_ROUTER] == ["tcp/localhost:7447"]
    router_at = f"tcp/localhost:{free_tcp_port()}"
    router = procs.start("warp_buffer_cli.main", "router", "--listen",
                         router_at.replace("localhost", "127.0.0.1"))
    assert router.stdout.readline().startswith("warp-buffer router ")
    monkeypatch.setenv("ZENOH_CONFIG_OVERRIDE", f'connect/endpoints=["{router_at}"]')
    got = []
    with Node("default_config_rx", domain_id=domain) as node:
        node.create_subscription(IMAGE, topic, lambda m: got.append(m.header.frame_id),
                                 depth=COUNT)
        pub = procs.model("pub", domain, topic, IMAGE, "--wait-subs", "1", "--count",
                          str(COUNT), "--rate", "50", "--size", "64", "--no-stdin",
                          "--zenoh-config", _rmw_zenoh_session_config(tmp_path / "s.json5",
                                                                      router_at))
        sent = result(pub)
        assert sent["error"] is None, sent
        assert wait_until(lambda: len(got) >= COUNT)
    assert got == [f"model/{i}" for i in range(COUNT)]


def test_a_type_without_buffers_is_put_for_a_zenoh_subscriber_with_no_token_yet(domain, topic):
    """rmw_zenoh puts a message of a type without buffer fields on its key whoever listens
    (rmw_publisher_data.cpp), and a ROS 2 subscription declares its Zenoh subscriber before its
    liveliness token: what is published in between reaches it. A Zenoh subscriber with no
    token at all stands for that window here; it gets every message, and none once it left."""
    import zenoh

    from buffer_pubsub.config import make_config

    got = []
    listener = zenoh.open(make_config())
    try:
        with Node("tokenless_pub", domain_id=domain) as node:
            pub = node.create_publisher("std_msgs/msg/String", topic)
            sub = listener.declare_subscriber(pub.base_key,
                                              lambda s: got.append(s.payload.to_bytes()))
            msg = get_message_type("std_msgs/msg/String")()
            assert wait_until(lambda: pub._base_matched, 10)
            for index in range(COUNT):
                msg.data = f"hello {index}"
                pub.publish(msg)
            assert wait_until(lambda: len(got) >= COUNT, 10)
            sub.undeclare()
            assert wait_until(lambda: not pub._base_matched, 10)
            pub.publish(msg)  # nobody: nothing is serialized, nothing put
    finally:
        listener.close()
    store = model_messages.make_typestore()
    decoded = [store.deserialize_cdr(payload, "std_msgs/msg/String").data for payload in got]
    assert decoded == [f"hello {i}" for i in range(COUNT)]


# --------------------------------------------------------------------------- transient local
def test_a_late_transient_local_subscription_gets_an_rmw_zenoh_publishers_history(
        domain, topic, procs):
    """rmw_zenoh's transient-local publisher (latched: /tf_static, a map) keeps its last
    ``depth`` samples in a Zenoh advanced publisher's cache; ours, created after it published,
    queries that history first, then takes what follows: CPU bytes on the base key."""
    pub = procs.model("pub", domain, topic, IMAGE, "--durability", "transient_local",
                      "--depth", "3", "--count", "5", "--rate", "100", "--size", "64", "--hold",
                      "--linger", "0.2")
    wait_ready(pub)
    time.sleep(0.5)  # all 5 are published, and only the last 3 kept
    got = []
    with Node("latched_rx", domain_id=domain) as node:
        sub = node.create_subscription(IMAGE, topic, lambda m, i: got.append(
            (m.header.frame_id, i.route)), depth=10, with_info=True,
            durability="transient_local")
        assert wait_until(lambda: len(got) >= 3, 10)
        time.sleep(0.3)  # nothing more may come
        counters = sub.counters
    sent = result(pub)
    assert sent["error"] is None
    assert got == [(f"model/{i}", "base") for i in (2, 3, 4)]
    assert counters.errors == 0 and counters.refused == {}


def test_an_rmw_zenoh_transient_local_subscription_gets_our_publishers_history(
        domain, topic, procs):
    got_here = []
    with Node("latched_tx", domain_id=domain) as node:
        pub = node.create_publisher(IMAGE, topic, depth=3, durability="transient_local")
        for index in range(5):
            pub.publish(image(index))
        assert pub._token.backends is None and pub._token.qos.transient_local
        sub = procs.model("sub", domain, topic, IMAGE, "--durability", "transient_local",
                          "--depth", "10", "--count", "3", "--no-stdin")
        wait_ready(sub)
        received = result(sub, timeout=30)
        # and an in-process late joiner gets the same history, once
        node.create_subscription(IMAGE, topic, lambda m: got_here.append(m.header.frame_id),
                                 durability="transient_local")
        assert wait_until(lambda: len(got_here) >= 3, 10)
        time.sleep(0.3)
    samples = received["samples"]
    assert [s["decoded"]["fields"]["header.frame_id"] for s in samples] == \
        [f"ours/{i}" for i in (2, 3, 4)], samples
    assert {s["route"] for s in samples} == {"base"}
    assert [s["sha256"] for s in samples] == [
        sha(serialize_message(image(i))) for i in (2, 3, 4)]
    assert got_here == [f"ours/{i}" for i in (2, 3, 4)]

"""Nodes of one process configured alike share one Zenoh session (rmw_zenoh: one per context).

A session per node cost about 40 file descriptors and half a second each once a process held 20
nodes (a default ``ulimit -n`` of 1024 ran out near 24): these tests hold what a user sees of
the sharing, on real sessions."""

from __future__ import annotations

import os
import subprocess
import time
import sys

import pytest
import zenoh

from buffer_pubsub import Node, TransportConfigError, _sessions
from buffer_pubsub.config import make_config
from rosidl_buffer.messages import get_message_type, serialize_message
from tests._pubsub_helpers import ROOT, TENSOR, Child, check_frame, child_env, make_frame
from tests._reliability_helpers import wait_until

STRING = get_message_type("std_msgs/msg/String")
COUNT = 5


def _fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def test_nodes_configured_alike_share_one_session_that_the_last_one_closes(domain):
    first = Node("share_first", domain_id=domain, fast_lane=False)
    before = _fds()
    others = [Node(f"share_{k}", domain_id=domain, fast_lane=False) for k in range(12)]
    try:
        grown = _fds() - before
        assert all(node.session is first.session for node in others)
        assert {node.zid for node in others} == {first.zid}
        assert len({node.node_id for node in (first, *others)}) == 13  # told apart by node id
        assert grown <= 3 * len(others), f"{grown} descriptors for {len(others)} nodes"
        session = first.session
        first.close()
        for node in others[:-1]:
            node.close()
        assert not session.is_closed()  # one node still uses it
    finally:
        for node in others:
            node.close()
    assert session.is_closed()


def test_a_closed_node_leaves_the_others_of_its_session_working_and_its_graph(domain, topic):
    """B and C share A's session: once A closes, its tokens leave B's graph, and B still
    exchanges messages with another process (and in process with C) through the session."""
    child = Child("sub", domain=domain, topic=topic, accept="cpu", expect=COUNT)
    got: list[int] = []
    try:
        with Node("share_b", domain_id=domain) as b, Node("share_c", domain_id=domain) as c:
            a = Node("share_a", domain_id=domain)
            a.create_publisher(STRING, topic + "_a")
            assert wait_until(lambda: ("share_a", "/") in b.get_node_names_and_namespaces())
            assert wait_until(lambda: b.get_publishers_info_by_topic(topic + "_a"))
            a.close()
            assert wait_until(lambda: ("share_a", "/") not in b.get_node_names_and_namespaces())
            assert wait_until(lambda: not b.get_publishers_info_by_topic(topic + "_a"))
            c.create_subscription(TENSOR, topic, lambda m: got.append(check_frame(m)["index"]),
                                  depth=COUNT)
            pub = b.create_publisher(TENSOR, topic)
            child.wait_ready()
            assert pub.wait_for_subscriptions(2, timeout=10)
            for index in range(COUNT):
                pub.publish(make_frame(0, index, 256, "cpu"))
            result = child.stop()
            assert wait_until(lambda: len(got) == COUNT)
    finally:
        child.close()
    assert sorted(r["index"] for r in result["records"]) == list(range(COUNT))
    assert got == list(range(COUNT))  # once each: the session's own delivery is not a second


def test_nodes_of_two_sessions_answer_the_routes_query_each(domain, topic):
    from warp_buffer_cli._graph import routes_by_publisher

    with Node("routes_a", domain_id=domain) as a, Node("routes_b", domain_id=domain) as b:
        gids = {a.create_publisher(STRING, topic).gid.hex(),
                b.create_publisher(STRING, topic).gid.hex()}
        assert a.session is b.session
        assert wait_until(lambda: gids <= set(routes_by_publisher(a, timeout=1.0)))


def test_nodes_configured_differently_get_sessions_of_their_own(domain):
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    with Node("own_a", domain_id=domain) as a, Node("own_b", config=config,
                                                    domain_id=domain) as b:
        assert a.session is not b.session and a.zid != b.zid


def test_a_session_that_fails_to_open_leaves_nothing_and_the_next_node_opens_one(domain):
    config = zenoh.Config()
    config.insert_json5("listen/endpoints", '["tcp/256.0.0.1:1"]')  # no such address
    with pytest.raises(TransportConfigError):
        Node("never", config=config, domain_id=domain)
    assert str(make_config(config)) not in _sessions._shared  # no entry left half-open
    with Node("after", domain_id=domain) as node:
        assert not node.session.is_closed()


_FORK_WHILE_A_NODE_IS_OPEN = r"""
import os, sys
from buffer_pubsub import ForkedAfterZenohError, Node
with Node("fork_parent", domain_id=int(sys.argv[1])) as parent:
    pid = os.fork()
    if pid == 0:
        try:
            Node("fork_child", domain_id=int(sys.argv[1]))  # not the parent's session
        except ForkedAfterZenohError:
            os._exit(0)
        os._exit(3)
    _, status = os.waitpid(pid, 0)
    assert not parent.session.is_closed()
sys.exit(os.waitstatus_to_exitcode(status))
"""


def test_a_fork_child_never_gets_its_parents_open_session(domain):
    process = subprocess.run([sys.executable, "-c", _FORK_WHILE_A_NODE_IS_OPEN, str(domain)],
                             cwd=ROOT, env=child_env(), capture_output=True, text=True,
                             timeout=60)
    assert process.returncode == 0, (process.returncode, process.stderr[-2000:])


def test_nodes_made_at_once_from_many_threads_share_one_session(domain):
    import threading

    nodes: list[Node] = []
    errors: list[BaseException] = []
    lock = threading.Lock()

    def make(k: int) -> None:
        try:
            node = Node(f"threaded_{k}", domain_id=domain, fast_lane=False)
            with lock:
                nodes.append(node)
        except BaseException as error:  # noqa: BLE001 - reported below
            errors.append(error)

    threads = [threading.Thread(target=make, args=(k,)) for k in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    try:
        assert not errors and len(nodes) == 8
        assert len({id(node.session) for node in nodes}) == 1
    finally:
        closers = [threading.Thread(target=node.close) for node in nodes]
        for thread in closers:
            thread.start()
        for thread in closers:
            thread.join(60)
    assert nodes[0].session.is_closed()


def test_a_node_that_fails_after_joining_the_session_leaves_no_token_behind(domain, monkeypatch):
    from buffer_pubsub import _process

    with Node("keeper", domain_id=domain, fast_lane=False) as keeper:
        def refuse(node):
            raise OSError("no room")

        monkeypatch.setattr(_process, "add_node", refuse)
        with pytest.raises(OSError):
            Node("broken", domain_id=domain, fast_lane=False)
        monkeypatch.undo()
        with Node("witness", domain_id=domain, fast_lane=False) as witness:
            assert wait_until(lambda: ("witness", "/") in keeper.get_node_names_and_namespaces())
            assert ("broken", "/") not in keeper.get_node_names_and_namespaces()
            assert witness.session is keeper.session
        assert not keeper.session.is_closed()


def test_a_subscription_that_fails_half_made_receives_nothing_on_the_shared_session(
        domain, topic, monkeypatch):
    """Its Zenoh subscribers were declared before the step that failed: they are undeclared,
    not left on a session that outlives the node."""
    from buffer_pubsub import _process, wire

    got: list[object] = []
    with Node("keeper", domain_id=domain, fast_lane=False) as keeper, \
            Node("half", domain_id=domain, fast_lane=False) as half:
        def refuse(key, subscription):
            raise OSError("no room")

        monkeypatch.setattr(_process, "add_subscription", refuse)
        with pytest.raises(OSError):
            half.create_subscription(STRING, topic, got.append)
        monkeypatch.undo()
        # a peer in another session publishes on the key, as any ROS 2 publisher would, until
        # a healthy subscription of this process on the same key gets its samples
        live: list[object] = []
        keeper.create_subscription(STRING, topic, live.append)
        peer = zenoh.open(make_config())
        try:
            key = wire.data_key(domain, topic, "std_msgs/msg/String")
            sequence = iter(range(1, 1_000_000))

            def put_one() -> bool:
                number = next(sequence)
                peer.put(key, bytes(serialize_message(STRING(data="x"))),
                         attachment=wire.pack_attachment(number, number, b"\x07" * 16))
                return bool(live)

            assert wait_until(put_one)
            for _ in range(5):
                put_one()
            assert wait_until(lambda: len(live) >= 5)
        finally:
            peer.close()
    assert got == []


def test_a_publisher_that_fails_half_made_undeclares_what_it_declared(domain, topic,
                                                                      monkeypatch):
    from buffer_pubsub import _process
    from buffer_pubsub.publisher import Publisher

    declared: list[object] = []
    original = Publisher._declare_channel

    def recording(self, key):
        entity = original(self, key)
        declared.append(entity)
        return entity

    def refuse(gid):
        raise OSError("no room")

    monkeypatch.setattr(Publisher, "_declare_channel", recording)
    monkeypatch.setattr(_process, "add_publisher", refuse)
    tensor = get_message_type("tensor_msgs/msg/ExperimentalTensor")
    with Node("keeper", domain_id=domain, fast_lane=False), \
            Node("half", domain_id=domain, fast_lane=False) as half:
        with pytest.raises(OSError):
            half.create_publisher(tensor, topic)
        assert len(declared) == 2  # the base key and the CPU stream
        for entity in declared:
            with pytest.raises(zenoh.ZError, match="Undeclared"):
                entity.undeclare()  # undeclared already


def test_nodes_waiting_for_an_open_that_fails_fail_with_it_not_one_after_another(
        domain, monkeypatch):
    """Against a router that does not answer, each waiting node used to try again in turn:
    N nodes took N connect timeouts."""
    import threading

    calls: list[int] = []
    started = threading.Event()

    def unreachable(config):
        calls.append(1)
        started.set()
        time.sleep(0.5)
        raise TransportConfigError("cannot connect to Zenoh router tcp/10.255.0.1:7447")

    monkeypatch.setattr(_sessions, "open_session", unreachable)
    errors: list[BaseException] = []

    def make(k: int) -> None:
        try:
            Node(f"waiting_{k}", domain_id=domain, fast_lane=False).close()
        except TransportConfigError as error:
            errors.append(error)

    first = threading.Thread(target=make, args=(0,))
    first.start()
    assert started.wait(10)
    others = [threading.Thread(target=make, args=(k,)) for k in range(1, 4)]
    begin = time.monotonic()
    for thread in others:
        thread.start()
    for thread in (first, *others):
        thread.join(30)
    assert len(errors) == 4 and len(calls) == 1
    assert time.monotonic() - begin < 1.5


def test_no_node_is_made_once_the_exit_closed_the_others(domain, monkeypatch):
    """A daemon thread making nodes while the interpreter exited aborted the process
    ("FATAL: exception not rethrown") in 8 runs of 10: a node opened after the exit closed the
    others outlived it, its Zenoh threads calling into a finalizing interpreter."""
    from buffer_pubsub import NodeClosedError, _process

    monkeypatch.setattr(_process, "_exiting", True)
    with pytest.raises(NodeClosedError, match="exiting"):
        Node("late", domain_id=domain, fast_lane=False)


_HELD_AT_EXIT = r"""
import sys
from buffer_pubsub import Node, _process, _sessions
node = Node("held", domain_id=int(sys.argv[1]), fast_lane=False)
_process.remove_node(node)  # as if made after the exit took its list of nodes
session = node.session
_process.close_open_nodes()  # what the interpreter's exit runs
print(session.is_closed(), _sessions._shared == {}, flush=True)
"""


def test_the_exit_closes_a_session_a_daemon_threads_node_still_holds(domain):
    """The exit closes the nodes it knows, waits for node calls in flight, then closes every
    session left: a node a daemon thread made meanwhile kept its session open, whose Zenoh
    threads then called into the finalizing interpreter (SIGABRT or SIGSEGV in about half the
    runs of such a program)."""
    process = subprocess.run([sys.executable, "-c", _HELD_AT_EXIT, str(domain)], cwd=ROOT,
                             env=child_env(), capture_output=True, text=True, timeout=60)
    assert process.returncode == 0, (process.returncode, process.stderr[-2000:])
    assert process.stdout.split() == ["True", "True"]

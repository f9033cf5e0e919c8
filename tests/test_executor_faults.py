"""The executor and the process model against what users meet: a callback that calls
sys.exit(), a sample that fails to decode, samples out of order, a worker forked after Zenoh
started. Each case was a fault found by trying the library."""

from __future__ import annotations

import contextlib
import struct
import sys
import threading
import time

import pytest
import zenoh

from buffer_pubsub import Node, make_config
from buffer_pubsub.qos import QoSProfile
from tests._reliability_helpers import wait_until

STRING = "std_msgs/msg/String"


@pytest.mark.parametrize("inline", [True, False], ids=["inline", "executor-thread"])
def test_a_callback_calling_sys_exit_does_not_end_delivery(domain, topic, inline):
    """SystemExit from a callback on the node's executor thread ended that thread silently:
    nothing was delivered again, and nothing was counted or logged."""
    calls: list[str] = []

    def callback(msg) -> None:
        calls.append(msg.data)
        if msg.data == "3":
            sys.exit("callback decided to stop")

    with Node("executor_sysexit", domain_id=domain, inline_callbacks=inline) as node:
        sub = node.create_subscription(STRING, topic, callback, depth=100)
        pub = node.create_publisher(STRING, topic)
        for i in range(20):
            pub.publish(pub.msg_type(data=str(i)))
            time.sleep(0.002)
        assert wait_until(lambda: len(calls) == 20), calls
        assert sub.counters.callback_errors == 1
        assert isinstance(sub.last_error, SystemExit)
        assert node._thread.is_alive()


def test_sys_exit_in_a_callback_reaches_the_spinning_thread(domain, topic):
    """executor="manual": the user's own thread runs the callback, so it gets the exception
    (as rclpy's spin does)."""
    with Node("executor_sysexit_manual", domain_id=domain, executor="manual") as node:
        node.create_subscription(STRING, topic, lambda m: sys.exit(3))
        pub = node.create_publisher(STRING, topic)
        pub.publish(pub.msg_type(data="x"))
        with pytest.raises(SystemExit):
            node.spin_once(5.0)


def test_spin_once_waits_on_past_a_sample_that_fails_to_decode(domain, topic):
    """A sample that failed to deserialize counted as a callback that ran: spin_once(3.0)
    returned 1 after 0.2 s with no callback run."""
    calls: list = []
    with Node("executor_spin_garbage", domain_id=domain, executor="manual") as node:
        sub = node.create_subscription(STRING, topic, calls.append)
        raw = zenoh.open(make_config(None, None))
        try:
            time.sleep(0.5)  # discovery between the sessions
            attachment = struct.pack("<qqB16s", 1, time.time_ns(), 0x10, b"\x07" * 16)
            timer = threading.Timer(0.2, lambda: raw.put(sub.base_key, b"\x00\x01\x00\x00\xff\xff",
                                                         attachment=attachment))
            timer.start()
            start = time.monotonic()
            ran = node.spin_once(1.5)
            waited = time.monotonic() - start
            timer.join()
        finally:
            raw.close()
        assert sub.counters.errors == 1  # the sample arrived, and was refused
        assert ran == 0 and not calls and waited >= 1.4


_FORK_AFTER_A_STUCK_TEARDOWN = r"""
import os, sys, threading, time
from buffer_pubsub._zenoh import run_bounded
never = threading.Event()
run_bounded(never.wait, 0.05, "a teardown stuck on a frozen peer")  # left running
start = time.monotonic()
pid = os.fork()
if pid == 0:
    sys.exit(0)  # a normal exit: the atexit handlers run
os.waitpid(pid, 0)
print("CHILD_EXIT", time.monotonic() - start, flush=True)
never.set()
"""


def test_a_forked_child_does_not_wait_for_its_parents_teardown_at_exit():
    """The exit wait (for teardown still inside Zenoh) was inherited at fork: a child's normal
    exit waited its full second for a helper thread that only the parent had."""
    import subprocess

    from tests._pubsub_helpers import ROOT, child_env

    process = subprocess.run([sys.executable, "-c", _FORK_AFTER_A_STUCK_TEARDOWN], cwd=ROOT,
                             env=child_env(), capture_output=True, text=True, timeout=60)
    assert process.returncode == 0, process.stderr[-2000:]
    waited = float(process.stdout.split("CHILD_EXIT")[1])
    assert waited < 0.5, f"the child waited {waited:.2f} s at exit"


def test_a_keep_last_subscription_refuses_a_message_older_than_one_delivered(domain, topic):
    """A switch of route (Zenoh to the fast lane) let later messages overtake earlier ones in
    flight, and the late ones were delivered after them: out of order. Keep-last readers now
    get each publisher's messages in order, the late one counted as refused "late"; keep-all
    ones still get every message."""
    from buffer_pubsub import wire
    from buffer_pubsub.subscription import REFUSED_LATE, ROUTE_BASE

    gid = bytes(range(16))
    with Node("executor_order", domain_id=domain, executor="manual") as node:
        got: dict[str, list[str]] = {"keep_last": [], "keep_all": []}
        subs = {history: node.create_subscription(
                    STRING, f"{topic}_{history}", lambda m, h=history: got[h].append(m.data),
                    depth=10, history=history) for history in got}
        for history, sub in subs.items():
            for sequence in (1, 3, 2, 4):  # 2 arrives after 3
                msg = sub.msg_type(data=str(sequence))
                from rosidl_buffer.messages import serialize_message

                attachment = wire.Attachment(sequence, sequence, gid)
                sub._enqueue((bytes(serialize_message(msg)), attachment, ROUTE_BASE, 0, False))
        while node.spin_once(0.2):
            pass
        assert got["keep_last"] == ["1", "3", "4"]
        assert subs["keep_last"].counters.refused == {REFUSED_LATE: 1}
        assert subs["keep_last"].counters.lost == 1 and subs["keep_last"].counters.rejected == 0
        assert got["keep_all"] == ["1", "3", "2", "4"]


_NODE_IN_A_FORKED_WORKER = r"""
import os, sys, time
from buffer_pubsub import ForkedAfterZenohError, Node
with Node("fork_parent", domain_id=int(sys.argv[1])):
    pass  # the parent has run Zenoh (closed or not, it cannot start again in a child)
pid = os.fork()
if pid == 0:
    start = time.monotonic()
    try:
        Node("fork_worker", domain_id=int(sys.argv[1]))
    except ForkedAfterZenohError as exc:
        print("REFUSED", round(time.monotonic() - start, 2), "spawn" in str(exc), flush=True)
        os._exit(0)
    os._exit(3)
_, status = os.waitpid(pid, 0)
sys.exit(os.waitstatus_to_exitcode(status))
"""


def test_a_node_in_a_worker_forked_after_zenoh_started_is_refused_at_once(domain):
    """multiprocessing's default start method on Linux: Zenoh's runtime threads are not forked,
    and the worker's Node() hung for good (the parent's pool.get with it)."""
    import subprocess

    from tests._pubsub_helpers import ROOT, child_env

    process = subprocess.run([sys.executable, "-c", _NODE_IN_A_FORKED_WORKER, str(domain)],
                             cwd=ROOT, env=child_env(), capture_output=True, text=True,
                             timeout=60)
    assert process.returncode == 0, (process.returncode, process.stderr[-2000:])
    _, took, names_the_remedy = process.stdout.split()
    assert float(took) < 1.0 and names_the_remedy == "True"


_CLOSE_IN_A_FORKED_CHILD = r"""
import os, sys, threading, time
from buffer_pubsub import Node
got = []
arrived = threading.Event()
def on_message(msg):
    got.append(msg.data)
    arrived.set()
with Node("fork_closer", domain_id=int(sys.argv[1])) as node:
    node.create_subscription("std_msgs/msg/String", sys.argv[2], on_message)
    pub = node.create_publisher("std_msgs/msg/String", sys.argv[2])
    pub.publish(pub.msg_type(data="before"))
    assert arrived.wait(10), "nothing arrived before the fork"
    pid = os.fork()  # (the node's executor thread waits in its waker meanwhile)
    if pid == 0:
        start = time.monotonic()
        node.close()  # the with block's close of the inherited node, on purpose here
        print("CHILD", round(time.monotonic() - start, 2), flush=True)
        os._exit(0)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0, status
    arrived.clear()
    pub.publish(pub.msg_type(data="after"))  # the parent's node is untouched by that close
    assert arrived.wait(10), "the parent's node stopped delivering after the child's close"
    print("PARENT", got, flush=True)
"""


def test_a_forked_child_closes_an_inherited_node_at_once_and_leaves_the_parents_alone(
        domain, topic):
    """A child leaving a ``with Node(...)`` it inherited: nothing of Zenoh's runs there (its
    runtime's threads did not fork), so the close must not call into it (it waited 2 s for the
    session, then 10 s at exit blaming a frozen peer), nor wait for the executor thread that
    slept in the node's waker at the fork (the parent's)."""
    import subprocess

    from tests._pubsub_helpers import ROOT, child_env

    process = subprocess.run([sys.executable, "-c", _CLOSE_IN_A_FORKED_CHILD, str(domain),
                              topic], cwd=ROOT, env=child_env(), capture_output=True,
                             text=True, timeout=90)
    assert process.returncode == 0, (process.returncode, process.stderr[-2000:])
    lines = dict(line.split(" ", 1) for line in process.stdout.splitlines())
    assert float(lines["CHILD"]) < 0.5, process.stdout
    assert lines["PARENT"] == "['before', 'after']", process.stdout
    assert "frozen peer" not in process.stderr and "did not finish" not in process.stderr, (
        process.stderr[-2000:])


@contextlib.contextmanager
def _string_subscription(name: str, domain: int, topic: str):
    """A manual node's String subscription: ``(node, sub, got, token, sample)``, ``sample(n)``
    an arrived sample ``m<n>`` of the publisher of ``token`` (not in the graph yet)."""
    from rosidl_buffer.messages import serialize_message

    from buffer_pubsub import wire
    from buffer_pubsub.subscription import ROUTE_BUFFER

    with Node(name, domain_id=domain, executor="manual") as node:
        got: list[str] = []
        sub = node.create_subscription(STRING, topic, lambda m: got.append(m.data), depth=10)
        token = node._endpoint_token(wire.PUBLISHER_KIND, topic, STRING, QoSProfile(), {})

        def sample(sequence: int) -> tuple:
            payload = bytes(serialize_message(sub.msg_type(data=f"m{sequence}")))
            return (payload, wire.Attachment(sequence, time.time_ns(), token.gid),
                    ROUTE_BUFFER, time.time_ns(), False)

        yield node, sub, got, token, sample


def test_messages_lost_while_a_publisher_was_away_are_counted_when_it_returns(domain, topic):
    """Zenoh closes the link to a process that stalls a keep-all put for 5 s: the publisher's
    token leaves and comes back with the link, the same gid, its numbers going on. What it
    sent meanwhile is lost to this subscription and counted, not taken for a new stream."""
    with _string_subscription("executor_returning", domain, topic) as (
            node, sub, got, token, sample):
        def publisher(present: bool) -> None:
            with node.graph.lock:
                if present:
                    node.graph.put(token.key(), token)
                else:
                    node.graph.delete(token.key())
            sub.on_publisher(token, present)

        publisher(True)
        sub._arrived(sample(1))
        sub._arrived(sample(2))
        publisher(False)  # the link closed ...
        publisher(True)  # ... and came back
        sub._arrived(sample(7))
        while node.spin_once(0.2):
            pass
        assert got == ["m1", "m2", "m7"] and sub.counters.lost == 4


def test_a_sample_of_an_undiscovered_publisher_is_not_overtaken_by_a_later_one(domain, topic):
    """A sample whose publisher's token has not arrived is delivered at once (as rmw_zenoh:
    nothing waits for discovery), so a later sample, which arrives once the token did, comes
    after it and neither is refused as late."""
    with _string_subscription("executor_parked", domain, topic) as (
            node, sub, got, token, sample):
        sub._arrived(sample(1))  # the publisher is not discovered yet
        with node.graph.lock:
            node.graph.put(token.key(), token)  # discovery records it (under the lock) ...
        sub._arrived(sample(2))  # ... a Zenoh thread delivers the next sample ...
        sub.on_publisher(token, True)  # ... then the discovery hook runs
        while node.spin_once(0.2):
            pass
        assert got == ["m1", "m2"] and sub.counters.refused == {}

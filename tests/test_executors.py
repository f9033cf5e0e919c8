"""Executors and callback groups (issue 24 point 4), shaped after rclpy's.

A node's callbacks ran one at a time with no way to change it: a 100 ms image check held up the
features callback of the same node. ``MultiThreadedExecutor`` runs callbacks in parallel as
their groups allow: a slow callback in one mutually exclusive group no longer delays another
group's; a group's own callbacks never overlap; a reentrant group's do. Nothing here measures
speed: overlap is proven by callbacks that wait for each other (an Event, a Barrier).
"""

from __future__ import annotations

import threading
import time

import pytest

from buffer_pubsub import ExecutorModeError, InvalidEndpointError, Node, NodeClosedError
from buffer_pubsub.callback_groups import (
    MutuallyExclusiveCallbackGroup,
    ReentrantCallbackGroup,
)
from buffer_pubsub.executors import MultiThreadedExecutor, SingleThreadedExecutor
from tests._reliability_helpers import wait_until

STRING = "std_msgs/msg/String"
#: How long a callback waits for a partner that must run beside it: generous, so a loaded
#: machine cannot fail the parallel cases; the serial cases pass their wait in full.
PARTNER_WAIT_S = 5.0
SERIAL_WAIT_S = 0.5


def _publish(node: Node, topic: str, *texts: str) -> None:
    pub = node.create_publisher(STRING, topic, depth=100)
    for text in texts:
        pub.publish(pub.msg_type(data=text))


class _Spinning:
    """``executor.spin()`` on a thread of the test, shut down and joined on exit."""

    def __init__(self, executor) -> None:
        self.executor = executor
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._spin, daemon=True)

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except BaseException as exc:  # reported by __exit__
            self.error = exc

    def __enter__(self):
        self.thread.start()
        return self.executor

    def __exit__(self, *exc) -> None:
        assert self.executor.shutdown(timeout_sec=10)
        self.thread.join(10)
        assert not self.thread.is_alive()
        assert self.error is None, self.error


def _fast_ran_during_slow(domain: int, topic: str, own_group: bool, wait_s: float) -> bool:
    """A slow image callback waits up to ``wait_s`` for the features callback, published while
    it runs: whether that ran meanwhile (the image callback in a group of its own, or not)."""
    fast_ran = threading.Event()
    slow_started = threading.Event()
    seen: dict[str, bool] = {}

    def slow(msg) -> None:
        slow_started.set()
        seen["slow"] = fast_ran.wait(wait_s)

    with Node("exec_groups", domain_id=domain) as node:
        node.create_subscription(STRING, f"{topic}/image", slow,
                                 callback_group=MutuallyExclusiveCallbackGroup() if own_group
                                 else None)
        node.create_subscription(STRING, f"{topic}/features", lambda m: fast_ran.set())
        executor = MultiThreadedExecutor(num_threads=4)
        executor.add_node(node)
        with _Spinning(executor):
            _publish(node, f"{topic}/image", "frame")
            assert slow_started.wait(10)
            _publish(node, f"{topic}/features", "f")
            assert wait_until(lambda: "slow" in seen and fast_ran.is_set(),
                              timeout=wait_s + 10)
    return seen["slow"]


def test_a_slow_callback_does_not_delay_another_groups_callback(domain, topic):
    assert _fast_ran_during_slow(domain, topic, own_group=True, wait_s=PARTNER_WAIT_S), \
        "the features callback waited for the slow image callback"


def test_callbacks_of_the_default_group_wait_for_each_other(domain, topic):
    """The default (one group per node): the other callback runs only after the slow one."""
    assert not _fast_ran_during_slow(domain, topic, own_group=False, wait_s=SERIAL_WAIT_S)


class _Overlap:
    """A callback that records how many of its calls ran at once, and what it got."""

    def __init__(self) -> None:
        self.running = self.peak = 0
        self.done: list[str] = []
        self._lock = threading.Lock()

    def __call__(self, msg) -> None:
        with self._lock:
            self.running += 1
            self.peak = max(self.peak, self.running)
        time.sleep(0.002)  # room for another thread to start beside it, if it could
        with self._lock:
            self.running -= 1
            self.done.append(msg.data)


def test_a_mutually_exclusive_group_never_overlaps(domain, topic):
    group = MutuallyExclusiveCallbackGroup()
    callback = _Overlap()
    with Node("exec_mutex", domain_id=domain) as node:
        for i in range(3):
            node.create_subscription(STRING, f"{topic}/s{i}", callback, depth=100,
                                     callback_group=group)
        executor = MultiThreadedExecutor(num_threads=4)
        executor.add_node(node)
        with _Spinning(executor):
            for i in range(3):
                _publish(node, f"{topic}/s{i}", *(f"{i}:{k}" for k in range(20)))
            assert wait_until(lambda: len(callback.done) == 60, timeout=30), len(callback.done)
    assert callback.peak == 1
    for i in range(3):  # each subscription's messages in order
        mine = [d for d in callback.done if d.startswith(f"{i}:")]
        assert mine == [f"{i}:{k}" for k in range(20)]


@pytest.mark.parametrize("same_subscription", [True, False], ids=["one-sub", "two-subs"])
def test_a_reentrant_group_runs_callbacks_together(domain, topic, same_subscription):
    """Two callbacks of a reentrant group meet at a barrier: only possible side by side."""
    barrier = threading.Barrier(2, timeout=PARTNER_WAIT_S)
    met: list[bool] = []

    def callback(msg) -> None:
        try:
            barrier.wait()
            met.append(True)
        except threading.BrokenBarrierError:
            met.append(False)

    group = ReentrantCallbackGroup()
    with Node("exec_reentrant", domain_id=domain) as node:
        topics = [topic] if same_subscription else [f"{topic}/a", f"{topic}/b"]
        for name in topics:
            node.create_subscription(STRING, name, callback, depth=10, callback_group=group)
        executor = MultiThreadedExecutor(num_threads=2)
        executor.add_node(node)
        with _Spinning(executor):
            if same_subscription:
                _publish(node, topic, "1", "2")
            else:
                _publish(node, topics[0], "1")
                _publish(node, topics[1], "2")
            assert wait_until(lambda: len(met) == 2, timeout=PARTNER_WAIT_S + 10)
    assert met == [True, True]


def test_a_callback_group_is_honoured_across_nodes(domain, topic):
    """One group shared by subscriptions of two nodes in one executor."""
    group = MutuallyExclusiveCallbackGroup()
    callback = _Overlap()
    with Node("exec_a", domain_id=domain) as a, Node("exec_b", domain_id=domain,
                                                        executor="manual") as b:
        a.create_subscription(STRING, f"{topic}/a", callback, depth=50, callback_group=group)
        b.create_subscription(STRING, f"{topic}/b", callback, depth=50, callback_group=group)
        executor = MultiThreadedExecutor(num_threads=3)
        assert executor.add_node(a) and executor.add_node(b)
        assert executor.get_nodes() == [a, b]
        with _Spinning(executor):
            _publish(a, f"{topic}/a", *(f"a{k}" for k in range(15)))
            _publish(b, f"{topic}/b", *(f"b{k}" for k in range(15)))
            assert wait_until(lambda: len(callback.done) == 30, timeout=30), len(callback.done)
    assert callback.peak == 1


def test_single_threaded_executor_runs_several_nodes_on_the_calling_thread(domain, topic):
    threads: list[tuple[str, int]] = []
    with Node("exec_s1", domain_id=domain) as a, Node("exec_s2", domain_id=domain,
                                                        executor="manual") as b:
        a.create_subscription(STRING, topic, lambda m: threads.append(("a", threading.get_ident())))
        b.create_subscription(STRING, topic, lambda m: threads.append(("b", threading.get_ident())))
        with SingleThreadedExecutor() as executor:
            executor.add_node(a)
            executor.add_node(b)
            _publish(a, topic, "x")
            deadline = time.monotonic() + 10
            while len(threads) < 2 and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.5)
    assert sorted(name for name, _ in threads) == ["a", "b"]
    assert {ident for _, ident in threads} == {threading.get_ident()}


def test_spin_once_zero_returns_at_once_when_nothing_is_ready(domain):
    with Node("exec_idle", domain_id=domain, executor="manual") as node:
        with SingleThreadedExecutor() as executor:
            executor.add_node(node)
            assert executor.spin_once(timeout_sec=0) is None


def test_callback_exceptions_are_counted_and_delivery_goes_on(domain, topic):
    import sys

    calls: list[str] = []

    def callback(msg) -> None:
        calls.append(msg.data)
        if msg.data == "2":
            raise ValueError("bad frame")
        if msg.data == "4":
            sys.exit("a worker thread must not end")

    with Node("exec_errors", domain_id=domain, executor="manual") as node:
        sub = node.create_subscription(STRING, topic, callback, depth=100)
        executor = MultiThreadedExecutor(num_threads=2)
        executor.add_node(node)
        with _Spinning(executor):
            _publish(node, topic, *(str(i) for i in range(8)))
            assert wait_until(lambda: len(calls) == 8, timeout=20), calls
        assert sub.counters.callback_errors == 2
        assert isinstance(sub.last_error, SystemExit)


def test_system_exit_in_a_callback_reaches_the_single_threaded_spinner(domain, topic):
    import sys

    with Node("exec_sysexit", domain_id=domain) as node:
        sub = node.create_subscription(STRING, topic, lambda m: sys.exit(3))
        with SingleThreadedExecutor() as executor:
            executor.add_node(node)
            _publish(node, topic, "x")
            with pytest.raises(SystemExit):
                executor.spin_once(timeout_sec=10)
        assert sub.counters.callback_errors == 0


def test_shutdown_from_a_callback_ends_spin(domain, topic):
    executor = MultiThreadedExecutor(num_threads=2)
    with Node("exec_stop", domain_id=domain) as node:
        node.create_subscription(STRING, topic, lambda m: executor.shutdown())
        executor.add_node(node)
        spinning = _Spinning(executor)
        spinning.thread.start()
        _publish(node, topic, "stop")
        spinning.thread.join(10)
        assert not spinning.thread.is_alive() and spinning.error is None
        assert executor.is_shutdown and executor.get_nodes() == []
        with pytest.raises(ExecutorModeError):
            executor.spin()
        with pytest.raises(ExecutorModeError):
            executor.add_node(node)


def test_a_node_gets_its_callbacks_back_after_shutdown(domain, topic):
    """A node's own thread delivers again once the executor let it go; a manual node spins."""
    got: list[tuple[str, int]] = []
    with Node("exec_back", domain_id=domain) as own, Node("exec_back_m", domain_id=domain,
                                                            executor="manual") as manual:
        own.create_subscription(STRING, topic, lambda m: got.append(("own", m.data)))
        manual.create_subscription(STRING, topic, lambda m: got.append(("manual", m.data)))
        executor = MultiThreadedExecutor(num_threads=2)
        executor.add_node(own)
        executor.add_node(manual)
        assert own.executor is executor and manual.executor is executor
        with pytest.raises(ExecutorModeError):
            manual.spin_once(0)  # the executor runs its callbacks
        with _Spinning(executor):
            _publish(own, topic, "in")
            assert wait_until(lambda: len(got) == 2)
        assert own.executor is None and manual.executor is None
        _publish(own, topic, "out")
        assert manual.spin_once(10) == 1
        assert wait_until(lambda: len(got) == 4)
    assert sorted(got) == [("manual", "in"), ("manual", "out"), ("own", "in"), ("own", "out")]


def test_messages_queued_before_add_node_run_on_the_executor(domain, topic):
    got: list[str] = []
    with Node("exec_queued", domain_id=domain, executor="manual") as node:
        node.create_subscription(STRING, topic, lambda m: got.append(m.data), depth=10)
        _publish(node, topic, "1", "2", "3")  # ready in the node, nobody spinning
        executor = MultiThreadedExecutor(num_threads=1)
        executor.add_node(node)
        with _Spinning(executor):
            assert wait_until(lambda: len(got) == 3)
    assert got == ["1", "2", "3"]


def test_add_node_refuses_what_would_run_callbacks_twice(domain):
    with Node("exec_twice", domain_id=domain, executor="manual") as node:
        first, second = SingleThreadedExecutor(), MultiThreadedExecutor(num_threads=1)
        assert first.add_node(node) is True
        assert first.add_node(node) is False
        with pytest.raises(ExecutorModeError, match="already in"):
            second.add_node(node)
        first.remove_node(node)
        assert second.add_node(node) is True
        second.shutdown()
        node.close()
        with pytest.raises(NodeClosedError):
            first.add_node(node)
        for not_a_node in ("node", None, first):
            with pytest.raises(InvalidEndpointError, match="takes a buffer_pubsub Node"):
                first.add_node(not_a_node)
        first.shutdown()


def test_closing_a_node_takes_it_out_of_its_executor(domain, topic):
    with MultiThreadedExecutor(num_threads=2) as executor:
        node = Node("exec_close", domain_id=domain)
        node.create_subscription(STRING, topic, lambda m: None)
        executor.add_node(node)
        node.close()
        assert executor.get_nodes() == [] and node.executor is None


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_num_threads_is_checked(bad):
    with pytest.raises(ExecutorModeError):
        MultiThreadedExecutor(num_threads=bad)


def test_callback_group_is_checked(domain, topic):
    from buffer_pubsub import InvalidEndpointError

    with Node("exec_badgroup", domain_id=domain) as node:
        with pytest.raises(InvalidEndpointError):
            node.create_subscription(STRING, topic, print, callback_group="reentrant")
        sub = node.create_subscription(STRING, topic, print)
        assert sub.callback_group is node.default_callback_group


@pytest.mark.multiprocess
@pytest.mark.parametrize("mode", ["manual", "thread"])
def test_lane_messages_from_another_process_run_on_the_executor(domain, topic, mode):
    """Same-host frames arrive on the fast lane inside the node's wait: a node in an executor
    still gets them (a manual node through the executor's receiving thread), and every
    callback runs on the executor's threads."""
    from buffer_pubsub import fast_lane
    from tests._pubsub_helpers import TENSOR, Child, check_frame, pick_backend

    if not fast_lane.status().available:
        pytest.skip(f"no fast lane here: {fast_lane.status().reason}")
    backend = pick_backend()
    got: list[tuple[str, bool, int]] = []
    with Node("exec_lane", domain_id=domain, executor=mode) as node:
        node.create_subscription(
            TENSOR, topic, lambda m, info: got.append(
                (info.route, check_frame(m)["ok"], threading.get_ident())),
            depth=50, acceptable_buffer_backends=backend, with_info=True)
        executor = MultiThreadedExecutor(num_threads=2)
        executor.add_node(node)
        with _Spinning(executor):
            child = Child("pub", domain=domain, topic=topic, backend=backend, count=20,
                          size=1024)
            try:
                child.wait_ready()
                assert wait_until(lambda: len(got) == 20, timeout=20), len(got)
                workers = {w.ident for w in executor._workers}
                child.stop()
            finally:
                child.close()
    assert {route for route, _, _ in got} == {"lane"}
    assert all(ok for _, ok, _ in got)
    assert {ident for _, _, ident in got} <= workers


def test_a_second_shutdown_still_waits_for_a_callback_the_spin_left_running(domain):
    """shutdown() is True only if no callback still runs: after a first shutdown (or Ctrl-C)
    ended spin() with a callback stuck, the second one (``with executor:`` makes it) said True
    at once."""
    running, release = threading.Event(), threading.Event()

    def stuck() -> None:
        running.set()
        release.wait(10)

    with Node("executor_stuck", domain_id=domain) as node:
        node.create_timer(0.05, stuck)
        executor = MultiThreadedExecutor(2)
        executor.add_node(node)
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()
        assert running.wait(5)
        assert executor.shutdown(timeout_sec=0.2) is False
        spinner.join(10)
        assert not spinner.is_alive()
        started = time.monotonic()
        assert executor.shutdown(timeout_sec=0.3) is False
        assert time.monotonic() - started >= 0.25
        release.set()
        assert executor.shutdown(timeout_sec=5) is True


@pytest.mark.parametrize("timeout", [float("nan"), "1", object()])
def test_shutdown_and_remove_node_refuse_what_is_no_timeout(domain, timeout):
    from buffer_pubsub import InvalidTimeoutError

    executor = SingleThreadedExecutor()
    with Node("executor_nan", domain_id=domain) as node:
        executor.add_node(node)
        with pytest.raises(InvalidTimeoutError):
            executor.remove_node(node, timeout)
        with pytest.raises(InvalidTimeoutError):
            executor.shutdown(timeout)
        assert executor.shutdown(-1) is True  # negative: no wait, as before

"""Timers (``node.create_timer``), as rclpy's: users building a camera -> inference -> viewer
pipeline from the docs got an AttributeError.

A timer runs where the node's subscription callbacks run (the node's thread, ``node.spin()``, a
``SingleThreadedExecutor`` or a ``MultiThreadedExecutor``), under its callback group. Timing
checks use wide bounds (a loaded 2-core machine); the scheduling rules themselves (no drift,
missed ticks skipped) are checked exactly on a fake clock.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import threading
import time
from collections.abc import Iterator
from types import SimpleNamespace

import pytest

import buffer_pubsub.timer as timer_module
from buffer_pubsub import InvalidEndpointError, Node, NodeClosedError, Timer
from buffer_pubsub._executor import InFlight
from buffer_pubsub.callback_groups import (
    MutuallyExclusiveCallbackGroup,
    ReentrantCallbackGroup,
)
from buffer_pubsub.executors import MultiThreadedExecutor, SingleThreadedExecutor
from tests._reliability_helpers import wait_until

STRING = "std_msgs/msg/String"
KINDS = ["thread", "spin", "single", "multi"]
MS = 1_000_000  # ns


@contextlib.contextmanager
def running(kind: str, node: Node) -> Iterator[None]:
    """Run ``node``'s callbacks the ``kind`` way until the block ends: its own thread,
    ``node.spin()`` on a thread of the test, or an executor spinning on one."""
    if kind == "thread":
        yield
        return
    if kind == "spin":
        stop = threading.Event()

        def spin() -> None:
            while not stop.is_set() and not node.closed:
                node.spin(0.25)  # (longer than a period: the deadline must end waits)
        end = stop.set
    else:
        executor = SingleThreadedExecutor() if kind == "single" else MultiThreadedExecutor(2)
        executor.add_node(node)
        spin = executor.spin

        def end() -> None:
            assert executor.shutdown(timeout_sec=10)
    errors: list[BaseException] = []

    def spinning() -> None:
        try:
            spin()
        except BaseException as exc:  # reported below
            if not (isinstance(exc, NodeClosedError) and node.closed):  # (closed by the test)
                errors.append(exc)
    thread = threading.Thread(target=spinning, daemon=True)
    thread.start()
    try:
        yield
    finally:
        end()
        thread.join(10)
    assert not thread.is_alive()
    assert not errors, errors


def _node(kind: str, domain: int, name: str) -> Node:
    return Node(name, domain_id=domain, executor="manual" if kind == "spin" else "thread")


# -- firing -------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
def test_a_timer_fires_at_its_period_where_callbacks_run(kind, domain):
    calls: list[str] = []
    with _node(kind, domain, "timer_rate") as node:
        timer = node.create_timer(0.02, lambda: calls.append(threading.current_thread().name))
        assert isinstance(timer, Timer) and node.timers == [timer]
        assert timer.timer_period_ns == 20 * MS
        with running(kind, node):
            time.sleep(0.5)
            count = len(calls)
    # 25 expected; a loop that only woke at its 0.2 s housekeeping tick would give 2 or 3
    assert 10 <= count <= 30, count
    threads = set(calls)
    if kind == "thread":
        assert threads == {"buffer_pubsub:timer_rate"}
    elif kind == "multi":
        assert all(name.startswith("buffer_pubsub:executor:") for name in threads), threads
    else:  # the thread that spins (node.spin() or the executor's spin())
        assert len(threads) == 1 and not threads.pop().startswith("buffer_pubsub:")


def test_spin_once_waits_only_until_the_timer_is_due(domain):
    with Node("timer_spin_once", domain_id=domain, executor="manual") as node:
        node.create_timer(0.05, lambda: None)
        start = time.monotonic()
        assert node.spin_once(5.0) == 1  # the timeout is the limit; the deadline ends the wait
        assert time.monotonic() - start < 2.5
    with Node("timer_exec_once", domain_id=domain) as node, SingleThreadedExecutor() as ex:
        calls: list[int] = []
        node.create_timer(0.05, lambda: calls.append(1))
        ex.add_node(node)
        start = time.monotonic()
        ex.spin_once(timeout_sec=5.0)
        assert calls == [1] and time.monotonic() - start < 2.5


def test_an_idle_timer_wakes_its_node_once_a_tick(domain):
    """Waits end at the deadline; nothing polls (the waker counts the times it slept)."""
    with Node("timer_idle", domain_id=domain) as node:
        calls: list[int] = []
        waker = node.scheduler.waker
        before = waker.wakeups
        node.create_timer(0.1, lambda: calls.append(1))
        time.sleep(0.55)
        wakeups = waker.wakeups - before
    assert 2 <= len(calls) <= 6, calls
    # ~5 ticks and ~3 housekeeping rounds; a 20 ms poll would be 27, a busy loop thousands
    assert wakeups <= 20, wakeups


# -- the scheduling rules, on a fake clock -----------------------------------------------------
class _Clock:
    def __init__(self) -> None:
        self.now = 1_000 * MS

    def __call__(self) -> int:
        return self.now


def _bare_timer(monkeypatch, period_ms: int) -> tuple[Timer, _Clock, list[int]]:
    """A timer of a stand-in node, run by hand (no loop sees it) on a fake clock."""
    clock = _Clock()
    monkeypatch.setattr(timer_module, "monotonic_ns", clock)
    calls: list[int] = []
    node = SimpleNamespace(name="fake", closed=False, scheduler=SimpleNamespace(
        in_flight=InFlight()))
    timer = Timer(node, timer_module.TimerSet(lambda: None), lambda: calls.append(clock.now),
                  period_ms * MS, MutuallyExclusiveCallbackGroup())
    return timer, clock, calls


def test_deadlines_advance_by_whole_periods_without_drift(monkeypatch):
    timer, clock, calls = _bare_timer(monkeypatch, 10)
    start = clock.now
    assert timer.time_until_next_call() == 10 * MS and not timer.is_ready()
    assert not timer.run_one()  # not due yet: nothing runs
    for late_ms in (3, 7, 0, 9):  # each call late, by less than a period
        clock.now = timer.deadline_ns + late_ms * MS
        assert timer.is_ready() and timer.run_one()
        assert timer.time_since_last_call() == 0
        assert (timer.deadline_ns - start) % (10 * MS) == 0  # the phase of creation, kept
        assert timer.time_until_next_call() == (10 - late_ms) * MS
    assert len(calls) == 4 and timer.counters.calls == 4 and timer.counters.skipped == 0


def test_a_timer_late_by_several_periods_skips_the_ticks_it_missed(monkeypatch):
    timer, clock, calls = _bare_timer(monkeypatch, 10)
    first = timer.deadline_ns
    clock.now = first + 35 * MS  # the deadlines at +10, +20 and +30 ms passed too
    assert timer.run_one()
    assert timer.counters.skipped == 3 and timer.deadline_ns == first + 40 * MS
    assert not timer.run_one()  # no burst: the next call waits for its deadline
    assert len(calls) == 1


def test_reset_restarts_the_period_from_now(monkeypatch):
    timer, clock, calls = _bare_timer(monkeypatch, 10)
    clock.now += 7 * MS
    timer.reset()
    assert timer.time_until_next_call() == 10 * MS
    clock.now += 5 * MS  # the old deadline passed; the new one not
    assert not timer.is_ready() and not timer.run_one() and calls == []


# -- cancel, reset, destroy ----------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["thread", "multi"])
def test_cancel_stops_a_timer_and_reset_starts_it_again(kind, domain):
    calls: list[int] = []
    with _node(kind, domain, "timer_cancel") as node, running(kind, node):
        timer = node.create_timer(0.01, lambda: calls.append(1))
        assert wait_until(lambda: len(calls) >= 3, timeout=10)
        timer.cancel()
        assert timer.is_canceled() and timer.time_until_next_call() is None
        assert not timer.is_ready()
        time.sleep(0.05)  # a callback made ready before cancel() may still end meanwhile
        after_cancel = len(calls)
        time.sleep(0.15)
        assert len(calls) == after_cancel
        timer.reset()
        assert not timer.is_canceled() and timer.time_until_next_call() is not None
        assert wait_until(lambda: len(calls) >= after_cancel + 3, timeout=10)


def test_autostart_false_creates_a_cancelled_timer(domain):
    calls: list[int] = []
    with Node("timer_autostart", domain_id=domain) as node:
        timer = node.create_timer(0.01, lambda: calls.append(1), autostart=False)
        assert timer.is_canceled()
        time.sleep(0.15)
        assert calls == []
        timer.reset()
        assert wait_until(lambda: len(calls) >= 2, timeout=10)


def test_a_destroyed_timer_never_runs_again(domain):
    calls: list[int] = []
    with Node("timer_destroy", domain_id=domain) as node, \
            Node("timer_other", domain_id=domain) as other:
        timer = node.create_timer(0.01, lambda: calls.append(1))
        kept = node.create_timer(10.0, lambda: None)
        assert wait_until(lambda: len(calls) >= 2, timeout=10)
        assert other.destroy_timer(timer) is False  # not its timer: left alone
        assert node.destroy_timer(timer) is True
        assert node.destroy_timer(timer) is False
        assert node.timers == [kept] and timer.is_canceled()
        time.sleep(0.05)
        count = len(calls)
        time.sleep(0.1)
        assert len(calls) == count
        with pytest.raises(NodeClosedError):
            timer.reset()
        kept.destroy()  # Timer.destroy is node.destroy_timer
        assert node.timers == []


# -- callback groups -------------------------------------------------------------------------------
@pytest.mark.parametrize("group", ["default", "shared", "reentrant"])
def test_a_mutually_exclusive_group_never_runs_a_timer_beside_its_subscription(
        group, domain, topic):
    """A subscription callback waits for the timer to run beside it: only a reentrant group
    lets it (the exclusive cases pass the whole wait)."""
    timer_ran = threading.Event()
    in_subscription = threading.Event()
    seen: dict[str, bool] = {}

    def on_message(msg) -> None:
        in_subscription.set()
        seen["overlap"] = timer_ran.wait(5.0 if group == "reentrant" else 0.4)
        in_subscription.clear()

    def on_timer() -> None:
        if in_subscription.is_set():
            timer_ran.set()
        seen["timer"] = True

    shared = {"default": None, "shared": MutuallyExclusiveCallbackGroup(),
              "reentrant": ReentrantCallbackGroup()}[group]
    with Node("timer_groups", domain_id=domain) as node:
        node.create_subscription(STRING, topic, on_message, callback_group=shared)
        node.create_timer(0.01, on_timer, callback_group=shared)
        pub = node.create_publisher(STRING, topic)
        with running("multi", node):  # two threads: room for both callbacks at once
            pub.publish(pub.msg_type(data="x"))
            assert wait_until(lambda: "overlap" in seen, timeout=10)
            assert wait_until(lambda: seen.get("timer", False), timeout=5)
    assert seen["overlap"] is (group == "reentrant")


# -- errors in callbacks ------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["thread", "multi"])
def test_a_failing_callback_is_counted_and_the_timer_goes_on(kind, domain, caplog):
    calls: list[int] = []

    def callback() -> None:
        calls.append(1)
        if len(calls) == 2:
            raise ValueError("bad tick")
        if len(calls) == 3:
            sys.exit("a library thread must not end")

    with caplog.at_level(logging.ERROR, logger="buffer_pubsub.timer"), \
            _node(kind, domain, "timer_errors") as node, running(kind, node):
        timer = node.create_timer(0.01, callback)
        assert wait_until(lambda: len(calls) >= 6, timeout=10), calls
    assert timer.counters.callback_errors == 2
    assert isinstance(timer.last_error, SystemExit)
    assert sum("callback raised ValueError" in r.getMessage() for r in caplog.records) == 1


def test_a_timer_that_keeps_raising_logs_one_traceback(domain, caplog):
    """A 100 Hz timer raising every tick logged its traceback every tick; the first error keeps
    it, the next ones are a line each with the count."""
    def callback() -> None:
        raise ValueError("bad tick")

    with caplog.at_level(logging.ERROR, logger="buffer_pubsub.timer"), \
            _node("thread", domain, "timer_noisy") as node, running("thread", node):
        timer = node.create_timer(0.01, callback)
        assert wait_until(lambda: timer.counters.callback_errors >= 5, timeout=10)
    records = [r for r in caplog.records if "callback raised ValueError" in r.getMessage()]
    assert len(records) >= 5
    assert [r.exc_info is not None for r in records[:3]] == [True, False, False]
    assert "so far" in records[1].getMessage()


def test_system_exit_in_a_timer_reaches_the_users_spinning_thread(domain):
    with Node("timer_exit_spin", domain_id=domain, executor="manual") as node:
        timer = node.create_timer(0.01, lambda: sys.exit(3))
        with pytest.raises(SystemExit):
            node.spin_once(5.0)
        assert timer.counters.callback_errors == 0
    with Node("timer_exit_exec", domain_id=domain) as node, SingleThreadedExecutor() as ex:
        node.create_timer(0.01, lambda: sys.exit(3))
        ex.add_node(node)
        with pytest.raises(SystemExit):
            ex.spin_once(timeout_sec=5.0)


def test_ctrl_c_in_a_timer_ends_node_spin_as_rclpy(domain):
    def interrupt() -> None:
        raise KeyboardInterrupt

    with Node("timer_ctrl_c", domain_id=domain, executor="manual") as node:
        timer = node.create_timer(0.01, interrupt)
        with pytest.raises(KeyboardInterrupt):
            node.spin(5.0)
        assert timer.counters.calls == 1 and timer.counters.callback_errors == 0
        timer.callback = lambda: None  # the timer stays usable after the interrupt
        assert node.spin_once(5.0) == 1 and timer.counters.calls == 2


# -- close ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
def test_close_stops_the_nodes_timers(kind, domain):
    calls: list[float] = []
    ended = threading.Event()

    def callback() -> None:
        calls.append(time.monotonic())
        if len(calls) == 3:  # close() comes while this one runs: it waits for it
            time.sleep(0.2)
            ended.set()

    node = _node(kind, domain, "timer_close")
    with running(kind, node):
        timer = node.create_timer(0.01, callback)
        assert wait_until(lambda: len(calls) >= 3, timeout=10)
        node.close()
        closed_at = time.monotonic()
        assert ended.is_set()
        time.sleep(0.1)
    assert all(call < closed_at for call in calls), "a timer ran after close() returned"
    assert timer.is_canceled() and node.timers == []
    with pytest.raises(NodeClosedError):
        node.create_timer(0.01, lambda: None)


# -- bad input ----------------------------------------------------------------------------------
@pytest.mark.parametrize("period", [0, -0.5, math.nan, math.inf, -math.inf, 1e-12, "0.1", None,
                                    True, [0.1]])
def test_a_bad_period_is_refused(period, domain):
    with Node("timer_bad_period", domain_id=domain) as node:
        with pytest.raises(InvalidEndpointError, match="timer_period_sec"):
            node.create_timer(period, lambda: None)
        assert node.timers == []


def test_bad_callbacks_groups_and_periods_are_refused(domain):
    with Node("timer_bad_args", domain_id=domain) as node:
        with pytest.raises(InvalidEndpointError, match="callable"):
            node.create_timer(0.1, "not a function")
        with pytest.raises(InvalidEndpointError, match="callback_group"):
            node.create_timer(0.1, lambda: None, callback_group="exclusive")
        timer = node.create_timer(1, lambda: None)  # an int period is a number of seconds
        assert timer.timer_period_ns == 1_000_000_000
        for bad in (0, -1, 0.5, True):
            with pytest.raises(InvalidEndpointError, match="timer_period_ns"):
                timer.timer_period_ns = bad
        timer.timer_period_ns = 5 * MS
        assert timer.timer_period_ns == 5 * MS
        assert node.timers == [timer]

"""Executors, as rclpy's: objects that run the callbacks of the nodes added to them.

A :class:`~buffer_pubsub.Node` runs its own callbacks, one at a time, by default (on its own
thread, or in ``node.spin()`` with ``executor="manual"``). Add it to an executor and that
executor runs them instead::

    from buffer_pubsub import Node
    from buffer_pubsub.callback_groups import MutuallyExclusiveCallbackGroup
    from buffer_pubsub.executors import MultiThreadedExecutor

    with Node("viewer") as node, MultiThreadedExecutor(num_threads=2) as executor:
        slow = MutuallyExclusiveCallbackGroup()
        node.create_subscription(Image, "/camera/image", check_image, callback_group=slow)
        node.create_subscription(Tensor, "/features", show, depth=4)  # the default group
        executor.add_node(node)
        executor.spin()  # until executor.shutdown() or Ctrl-C (KeyboardInterrupt)

- :class:`SingleThreadedExecutor`: every callback on the thread that calls :meth:`~Executor.spin`
  or :meth:`~Executor.spin_once` (several nodes on one thread).
- :class:`MultiThreadedExecutor`: ``num_threads`` threads run callbacks in parallel, as far as
  their callback groups allow (:mod:`buffer_pubsub.callback_groups`). The thread that calls
  :meth:`~Executor.spin` only waits, so Ctrl-C reaches it at once; the running callbacks finish
  (within :data:`STOP_BUDGET_S`) before ``spin`` raises KeyboardInterrupt.

A node belongs to one executor at a time, and a node added to one cannot ``spin()`` itself.
While it is in an executor, the node's own thread (or, for ``executor="manual"``, a thread the
executor starts) only receives: every callback runs on the executor. Removing the node (or
:meth:`~Executor.shutdown`, or closing the node) hands its callbacks back to it. Exceptions in
callbacks are counted in ``counters.callback_errors`` and logged, as on the node's own thread.
"""

from __future__ import annotations

import collections
import logging
import os
import threading
import time
from typing import TYPE_CHECKING, Any

from ._executor import NodeExecutor, Runnable, user_spin, wait_seconds
from .errors import ExecutorModeError, InvalidEndpointError, NodeClosedError

if TYPE_CHECKING:
    from .node import Node

__all__ = ["Executor", "MultiThreadedExecutor", "SingleThreadedExecutor", "STOP_BUDGET_S"]

_log = logging.getLogger(__name__)

#: How long stopping a spin (Ctrl-C, :meth:`Executor.shutdown` without a timeout) or removing a
#: node waits for the running callbacks before it goes on anyway.
STOP_BUDGET_S = 3.0
#: Longest single wait of an idle executor thread (it re-checks shutdown after it).
_TICK_S = 0.2


class Executor:
    """Runs the callbacks of the nodes added to it (base of the two executors)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._work = threading.Condition(self._lock)
        self._ready: collections.deque[Runnable] = collections.deque()
        self._nodes: list[Node] = []
        # Items of a node being removed, taken meanwhile: remove_node hands them back.
        self._set_aside: list[Runnable] = []
        # executor="manual" nodes get a thread that waits on their waker (lane messages, parked
        # samples' expiry) while their callbacks run here
        self._receivers: dict[int, tuple[threading.Thread, threading.Event]] = {}
        self._shutdown = False
        self._shutdown_event = threading.Event()  # what MultiThreadedExecutor.spin waits on
        self._spin_lock = threading.Lock()  # one spin()/spin_once() caller at a time
        self._spinner: int | None = None  # the thread in spin()/spin_once()
        self._spin_done = threading.Event()
        self._spin_done.set()

    # -- nodes --------------------------------------------------------------------------------
    def add_node(self, node: Node) -> bool:
        """Run ``node``'s callbacks here from now on; False if it is here already.

        Raises :class:`ExecutorModeError` if the node is in another executor, spins itself
        (``node.spin()`` in another thread), or this executor was shut down;
        :class:`NodeClosedError` if the node is closed; :class:`InvalidEndpointError` for
        anything but a :class:`~buffer_pubsub.Node`."""
        from .node import Node

        if not isinstance(node, Node):
            raise InvalidEndpointError(f"add_node takes a buffer_pubsub Node, not "
                                       f"{type(node).__name__} {node!r:.60}")
        with self._lock:
            if self._shutdown:
                raise ExecutorModeError("this executor was shut down; create another")
            if node in self._nodes:
                return False
        node.enter_executor(self)  # raises where the node cannot be added
        node_executor: NodeExecutor = node.scheduler
        with self._lock:
            self._nodes.append(node)
        node_executor.delegate(self)
        if node.executor_mode == "manual":  # nobody waits on its waker: a thread of ours does
            until = threading.Event()
            receiver = threading.Thread(target=node_executor.receive, args=(until,),
                                        name=f"buffer_pubsub:{node.name}:receive", daemon=True)
            self._receivers[id(node)] = (receiver, until)
            receiver.start()
        if node.closed:  # closed meanwhile: its close() found it in no executor yet
            self.remove_node(node)
            raise NodeClosedError(f"node {node.name!r} is closed")
        return True

    def remove_node(self, node: Node, timeout_sec: float | None = None) -> None:
        """Hand ``node``'s callbacks back to the node (its own thread, or ``node.spin()``),
        once the callbacks of it that run here ended (waiting up to ``timeout_sec`` seconds for
        them; None: :data:`STOP_BUDGET_S`)."""
        self._remove(node, time.monotonic() + stop_budget(timeout_sec))

    def _remove(self, node: Node, deadline: float) -> None:
        with self._lock:
            if node not in self._nodes:
                return
            self._nodes.remove(node)  # from here, _execute sets its items aside
        node_executor: NodeExecutor = node.scheduler
        receiver = self._receivers.pop(id(node), None)
        if receiver is not None:  # first: the waker has one waiting thread at a time
            thread, until = receiver
            until.set()
            node_executor.waker.notify()
            thread.join(max(0.0, deadline - time.monotonic()))
        # The node's own loop must not start a callback beside one still running here.
        node_executor.in_flight.wait_idle(max(0.0, deadline - time.monotonic()))
        with self._lock:
            node_executor.reclaim()
            mine = [item for item in self._ready if item.node is node]
            for item in mine:
                self._ready.remove(item)
            mine += [item for item in self._set_aside if item.node is node]
            self._set_aside = [item for item in self._set_aside if item.node is not node]
        for item in mine:
            node_executor.schedule(item)
        node.leave_executor(self)

    def get_nodes(self) -> list[Node]:
        """The nodes whose callbacks this executor runs."""
        with self._lock:
            return list(self._nodes)

    # -- running callbacks ------------------------------------------------------------------------
    def schedule(self, item: Runnable) -> None:
        """Called by a node's executor (any thread): ``item`` is ready."""
        with self._lock:
            if item.node.scheduler.target is self:
                self._ready.append(item)
                self._work.notify()
                return
        item.node.scheduler.schedule(item)  # its node left meanwhile: back to the node

    def _take(self, timeout: float | None, stop: threading.Event | None = None
              ) -> Runnable | None:
        """The next ready item, waiting up to ``timeout`` (None: until one comes, or the
        executor or ``stop`` stops); None if none came."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._lock:
            while not self._ready:
                if self._shutdown or (stop is not None and stop.is_set()):
                    return None
                left = _TICK_S if deadline is None else min(_TICK_S, deadline - time.monotonic())
                if left <= 0:
                    return None
                self._work.wait(left)
            return self._ready.popleft()

    def _execute(self, item: Runnable) -> bool:
        """Run ``item``'s next callback if its group allows it now (else the group keeps it
        and hands it back when it may run); whether a callback ran."""
        if item.node not in self._nodes:  # being removed: remove_node hands it back
            with self._lock:
                if item.node.scheduler.target is self:
                    self._set_aside.append(item)
                    return False
            item.node.scheduler.schedule(item)
            return False
        group = item.callback_group
        if not group.enter(item):
            return False
        try:
            return bool(item.run_one())
        except Exception:
            _log.exception("executor task failed")  # callbacks' own errors are counted there
            return False
        finally:
            released = group.leave()
            if released is not None:
                released.node.scheduler.schedule(released)

    def spin_once(self, timeout_sec: float | None = None) -> None:
        """Run one ready callback on this thread, waiting up to ``timeout_sec`` seconds for one
        (None or negative: no limit; 0: no wait), as rclpy's. A callback's ``Exception`` is
        counted and logged; SystemExit and KeyboardInterrupt reach the caller."""
        wait = wait_seconds(timeout_sec)
        with self._spinning(), user_spin():
            item = self._take(wait)
            if item is not None:
                self._execute(item)

    def spin(self) -> None:
        """Run callbacks until :meth:`shutdown` (Ctrl-C raises KeyboardInterrupt here)."""
        raise NotImplementedError

    def shutdown(self, timeout_sec: float | None = None) -> bool:
        """Stop: a ``spin()`` returns once its running callbacks ended (waiting up to
        ``timeout_sec`` seconds for them; None: :data:`STOP_BUDGET_S`), and every node gets its
        callbacks back. True if no callback still runs here. Idempotent; a shut-down executor
        does not spin again."""
        with self._lock:
            self._shutdown = True
            self._work.notify_all()
        self._shutdown_event.set()
        deadline = time.monotonic() + stop_budget(timeout_sec)
        done = self._wait_stopped(deadline)
        for node in self.get_nodes():
            self._remove(node, deadline)
        return done

    def _wait_stopped(self, deadline: float) -> bool:
        """Wait until no spin runs (a callback of the spin that shuts it down: at once)."""
        if self._spinner == threading.get_ident():
            return True
        return self._spin_done.wait(max(0.0, deadline - time.monotonic()))

    @property
    def is_shutdown(self) -> bool:
        """Whether :meth:`shutdown` was called."""
        return self._shutdown

    def _spinning(self) -> _SpinGuard:
        return _SpinGuard(self)

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.shutdown()

    def __repr__(self) -> str:
        return f"{type(self).__name__}(nodes={[n.name for n in self.get_nodes()]})"


def stop_budget(timeout_sec: float | None) -> float:
    """How long :meth:`Executor.shutdown` / :meth:`Executor.remove_node` wait for running
    callbacks: None is :data:`STOP_BUDGET_S`, a negative number 0, an infinite one no limit;
    NaN and non-numbers are refused (InvalidTimeoutError), as every timeout is."""
    if timeout_sec is None:
        return STOP_BUDGET_S
    seconds = wait_seconds(timeout_sec)
    if seconds is not None:
        return seconds
    try:
        negative = float(timeout_sec) < 0
    except OverflowError:  # an int past any float
        negative = int(timeout_sec) < 0
    return 0.0 if negative else threading.TIMEOUT_MAX / 2


class _SpinGuard:
    """One thread spins an executor at a time; a shut-down executor does not spin."""

    def __init__(self, executor: Executor) -> None:
        self.scheduler = executor

    def __enter__(self) -> None:
        executor = self.scheduler
        if executor._shutdown:
            raise ExecutorModeError("this executor was shut down; create another")
        if not executor._spin_lock.acquire(blocking=False):
            raise ExecutorModeError("this executor is already spinning (in another thread, or "
                                    "this callback's own spin)")
        executor._spinner = threading.get_ident()
        executor._spin_done.clear()

    def __exit__(self, *exc: Any) -> None:
        executor = self.scheduler
        executor._spinner = None
        executor._spin_done.set()
        executor._spin_lock.release()


class SingleThreadedExecutor(Executor):
    """Runs every callback of its nodes on the thread that calls :meth:`spin` /
    :meth:`spin_once`, one at a time."""

    def spin(self) -> None:
        """Run callbacks on this thread until :meth:`shutdown` (from a callback or another
        thread). Ctrl-C raises KeyboardInterrupt here, as in rclpy."""
        with self._spinning(), user_spin():
            while not self._shutdown:
                item = self._take(_TICK_S)
                if item is not None:
                    self._execute(item)


class MultiThreadedExecutor(Executor):
    """Runs callbacks on ``num_threads`` threads in parallel, as their callback groups allow
    (``num_threads`` defaults to the number of CPUs, as rclpy). :meth:`spin_once` runs one
    callback on the calling thread; :meth:`spin` uses the executor's threads."""

    def __init__(self, num_threads: int | None = None) -> None:
        super().__init__()
        if num_threads is None:
            num_threads = os.cpu_count() or 2
        if isinstance(num_threads, bool) or not isinstance(num_threads, int) or num_threads < 1:
            raise ExecutorModeError(f"num_threads must be an int >= 1, got {num_threads!r}")
        self.num_threads = num_threads
        self._workers: list[threading.Thread] = []

    def spin(self) -> None:
        """Run callbacks on the executor's threads until :meth:`shutdown`; this thread waits.
        Ctrl-C raises KeyboardInterrupt here once the running callbacks ended (at most
        :data:`STOP_BUDGET_S`)."""
        with self._spinning():
            stop = threading.Event()
            self._workers = [
                threading.Thread(target=self._worker, args=(stop,), daemon=True,
                                 name=f"buffer_pubsub:executor:{i}")
                for i in range(self.num_threads)]
            try:
                for worker in self._workers:
                    worker.start()
                # Ctrl-C lands in this wait, never in a callback. (Not on the workers' condition:
                # a notify meant for a worker would wake this thread instead.)
                while not self._shutdown_event.wait(_TICK_S):
                    pass
            finally:
                stop.set()
                with self._lock:
                    self._work.notify_all()
                self._join_workers(time.monotonic() + STOP_BUDGET_S)

    def _worker(self, stop: threading.Event) -> None:
        while not stop.is_set() and not self._shutdown:
            item = self._take(None, stop)
            if item is not None:
                self._execute(item)

    def _join_workers(self, deadline: float) -> bool:
        """Wait for the workers (not the calling one) to end; whether they all did."""
        me = threading.current_thread()
        # (a worker may shut down before spin() started the others: those end at once)
        others = [worker for worker in self._workers if worker is not me and worker.ident]
        for worker in others:
            worker.join(max(0.0, deadline - time.monotonic()))
        return not any(worker.is_alive() for worker in others)

    def _wait_stopped(self, deadline: float) -> bool:
        if threading.current_thread() in self._workers:  # shutdown() from a callback
            return self._join_workers(deadline)
        # A spin that returned (a first shutdown, Ctrl-C) may have left a callback running
        # past its own wait: a later shutdown waits for it too
        return super()._wait_stopped(deadline) and self._join_workers(deadline)

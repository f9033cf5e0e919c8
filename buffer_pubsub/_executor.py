"""The executor of a node: a set of ready subscriptions and timers, and one waker.

A subscription with messages waiting is in the ready deque exactly once (it re-enters itself
after each message while more wait, so subscriptions take turns); the keep-last queue of each
subscription is the only buffer, and nothing grows with the arrival rate. A due timer
(:mod:`buffer_pubsub.timer`) is made ready the same way, by the loop, whose waits end at the
nearest timer deadline (:class:`Deadlines`): timers need no thread and no polling. The loop
runs on the node's thread (:meth:`NodeExecutor.run`) or inside the user's :meth:`spin_once`; a
waker that delivers messages on the waiting thread (the fast lane's) may run a callback inside
its wait when nothing else is ready (:meth:`has_ready`, :meth:`ran_inline`).

A node added to a user's executor (:mod:`buffer_pubsub.executors`) *delegates*: what becomes
ready goes to that executor's threads instead (:meth:`NodeExecutor.delegate`), and the node's
loop only waits (lane messages arrive inside its wait) and keeps house (:meth:`receive`).
:class:`InFlight` records which threads run a node's callbacks, so that closing the node can
wait for them.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any, Protocol

from ._waker import Waker
from .errors import InvalidTimeoutError, NodeClosedError

if TYPE_CHECKING:
    from .callback_groups import CallbackGroup
    from .node import Node

__all__ = ["Deadlines", "InFlight", "NodeExecutor", "Runnable", "Target", "spinning_here",
           "user_spin", "wait_seconds"]

_log = logging.getLogger(__name__)

class Runnable(Protocol):
    node: Node
    callback_group: CallbackGroup

    def run_one(self) -> bool:
        """Deliver the next waiting message (re-schedules itself while more wait), or fire a
        due timer; whether a callback ran."""


class Deadlines(Protocol):
    """A node's timers as its loop sees them (:class:`buffer_pubsub.timer.TimerSet`)."""

    def next_deadline_ns(self) -> int | None:
        """The nearest ``time.monotonic_ns()`` at which a timer becomes due (None: none)."""

    def take_due(self, now_ns: int) -> Sequence[Runnable]:
        """The timers due at ``now_ns`` that are not ready yet, marked ready."""


class Target(Protocol):
    """A user's executor as a node sees it (:class:`buffer_pubsub.executors.Executor`)."""

    def schedule(self, item: Runnable) -> None:
        """Queue ``item``, ready to run on the executor's threads."""


# -- the user's own thread --------------------------------------------------------------------
_spinning = threading.local()


@contextlib.contextmanager
def user_spin() -> Iterator[None]:
    """Callbacks run in this block run on the user's own thread (``spin()``), which gets their
    SystemExit or KeyboardInterrupt, as rclpy's spin does."""
    depth = getattr(_spinning, "depth", 0)
    _spinning.depth = depth + 1
    try:
        yield
    finally:
        _spinning.depth = depth


def spinning_here() -> bool:
    """Whether the current thread is the user's, inside a spin (see :func:`user_spin`)."""
    return getattr(_spinning, "depth", 0) > 0


def wait_seconds(timeout: float | None) -> float | None:
    """A spin timeout as rclpy reads it: None, negative or infinite waits without limit, 0
    does not wait; NaN and non-numbers are refused (InvalidTimeoutError)."""
    if timeout is None:
        return None
    if isinstance(timeout, (str, bytes, bytearray)):  # float() would read "1": not a number
        raise InvalidTimeoutError(
            f"timeout must be a number of seconds or None, not {timeout!r}")
    try:
        seconds = float(timeout)
    except OverflowError:  # an int beyond any float (10**400): no limit, as inf
        return None
    except (TypeError, ValueError):
        raise InvalidTimeoutError(
            f"timeout must be a number of seconds or None, not {timeout!r}") from None
    if math.isnan(seconds):
        raise InvalidTimeoutError("timeout must be a number of seconds or None, not NaN")
    return None if seconds < 0 or seconds >= threading.TIMEOUT_MAX else seconds


class InFlight:
    """The threads running a callback of one node now, each with its nesting depth. Each
    thread writes only its own key, so no lock is needed (dict operations are atomic)."""

    #: How often :meth:`wait_idle` looks again (closing a node is rare; a callback is not).
    POLL_S = 0.005

    __slots__ = ("_threads",)

    def __init__(self) -> None:
        self._threads: dict[int, int] = {}

    def enter(self) -> int:
        """A callback starts on this thread; returns the thread's ident for :meth:`leave`."""
        ident = threading.get_ident()
        threads = self._threads
        threads[ident] = threads.get(ident, 0) + 1
        return ident

    def leave(self, ident: int) -> None:
        threads = self._threads
        depth = threads[ident] - 1
        if depth:
            threads[ident] = depth
        else:
            del threads[ident]

    def here(self) -> bool:
        """Whether the calling thread runs a callback of the node now."""
        return threading.get_ident() in self._threads

    def wait_idle(self, timeout: float) -> bool:
        """Wait until no other thread runs a callback (the calling thread's own callback, a
        callback closing its node, does not count); False if ``timeout`` passed first."""
        me = threading.get_ident()
        deadline = time.monotonic() + timeout
        while any(ident != me for ident in list(self._threads)):
            if time.monotonic() >= deadline:
                return False
            time.sleep(self.POLL_S)
        return True


class NodeExecutor:
    """Ready subscriptions and timers, run one callback at a time, woken by ``waker`` or by the
    nearest deadline of ``timers``."""

    #: Longest sleep between housekeeping rounds.
    TICK_S = 0.2
    #: How often a wait for the callback gate checks whether the executor was stopped.
    GATE_POLL_S = 0.05

    def __init__(self, waker: Waker, housekeeping: Callable[[], None],
                 gate: threading.Lock | None = None, timers: Deadlines | None = None) -> None:
        self.waker = waker
        self._timers = timers
        self.in_flight = InFlight()
        # Held while a callback runs, when callbacks may also run on arrival threads (see
        # Subscription._enqueue): one callback of the node at a time.
        self.gate = gate
        self._ready: collections.deque[Runnable] = collections.deque()
        self._housekeeping = housekeeping
        self._next_housekeeping = time.monotonic() + self.TICK_S
        self._stopped = False
        self._inline = 0  # callbacks run inside the waker's wait (see ran_inline)
        self._target: Target | None = None  # the user's executor this node delegates to

    @property
    def target(self) -> Target | None:
        """The user's executor that runs this node's callbacks (None: the node runs them)."""
        return self._target

    def schedule(self, item: Runnable) -> None:
        """Make ``item`` ready (the caller guarantees it is not ready already) and wake the
        loop."""
        waker = self.make_ready(item)
        if waker is not None:
            waker.notify()

    def make_ready(self, item: Runnable) -> Waker | None:
        """Make ``item`` ready without waking anyone; returns the waker its caller notifies
        (None: handed to the user's executor, which woke itself). A publish wakes the
        executors of its in-process subscriptions once it has sent everything, so a woken
        executor does not wait for the GIL that the rest of the publish holds."""
        target = self._target
        if target is not None:
            target.schedule(item)
            return None
        self._ready.append(item)
        return self.waker

    def has_ready(self) -> bool:
        """Whether anything waits to run. A message that arrives on the waiting thread (a lane
        message, inside the waker's wait) may run its callback at once only when nothing does,
        so turns and order stay as if it had been queued. Always True while the node delegates:
        then every callback runs on the user's executor, never on an arrival thread."""
        return bool(self._ready) or self._target is not None

    def ran_inline(self) -> None:
        """A callback ran inside the waker's wait, on the waiting thread (counted by
        :meth:`spin_once`)."""
        self._inline += 1

    def stop(self) -> None:
        self._stopped = True
        self.waker.notify()

    # -- delegation to a user's executor --------------------------------------------------------
    def delegate(self, target: Target) -> None:
        """Hand what becomes ready to ``target`` from now on, and what is ready now. Returns
        once no callback of the node runs on the node's thread or an arrival thread (the gate),
        so the user's executor alone decides what runs together from here."""
        self._target = target
        gate = self.gate
        if gate is not None and not self.in_flight.here():  # (not a callback adding its node)
            with gate:  # a callback that started before the hand-over ends first
                pass
        self._forward_ready()

    def reclaim(self) -> None:
        """Run callbacks on the node's own loop again (``target`` hands back what it queued)."""
        self._target = None
        self.waker.notify()

    def _forward_ready(self) -> None:
        target = self._target
        ready = self._ready
        while target is not None and ready:
            try:
                item = ready.popleft()
            except IndexError:
                break
            target.schedule(item)

    def receive(self, until: threading.Event) -> None:
        """The loop of a delegating node that has no thread of its own (``executor="manual"``):
        wait (lane messages arrive inside the wait and are queued for the user's executor) and
        keep house, until ``until`` is set (then :meth:`waker.notify`)."""
        while not self._stopped and not until.is_set():
            self._spin_pass(self.TICK_S)

    # -- the node's own loop ------------------------------------------------------------------
    def spin_once(self, timeout: float | None) -> int:
        """Run what is ready now; if nothing is, wait up to ``timeout`` (None: no limit) until
        something ran: a wake-up that brought no callback (an attach, housekeeping) waits on."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            ran = self._spin_pass(timeout)
            if ran or self._stopped:
                return ran
            if deadline is not None:
                timeout = deadline - time.monotonic()
                if timeout <= 0:
                    return 0

    def _spin_pass(self, timeout: float | None) -> int:
        """One wait (if nothing is ready) and what is ready after it."""
        inline = self._inline
        if not self._ready and not self._stopped:
            self.waker.wait(self._until_next_timer(timeout))
        if self._timers is not None and not self._stopped:
            for timer in self._timers.take_due(time.monotonic_ns()):
                self.make_ready(timer)  # (this loop runs it, or the user's executor, woken)
        ran = self._inline - inline
        ready = self._ready
        for _ in range(len(ready)):  # only what is ready now: re-scheduled items wait a turn
            if self._stopped:
                break
            try:
                item = ready.popleft()
            except IndexError:
                break
            gate = self.gate
            if gate is not None and not gate.acquire(blocking=False):
                while not gate.acquire(timeout=self.GATE_POLL_S):  # a callback runs elsewhere
                    if self._stopped:
                        ready.appendleft(item)
                        return ran
            try:
                target = self._target
                if target is not None:  # handed over while this item was taken
                    target.schedule(item)
                    continue
                ran += bool(item.run_one())  # a message that failed to decode ran nothing
            except Exception:
                _log.exception("executor task failed")
            finally:
                if gate is not None:
                    gate.release()
        now = time.monotonic()
        if now >= self._next_housekeeping:
            self._next_housekeeping = now + self.TICK_S
            try:
                self._housekeeping()
            except Exception:
                _log.exception("executor housekeeping failed")
        return ran

    def _until_next_timer(self, timeout: float | None) -> float | None:
        """``timeout``, cut short at the nearest timer deadline: the wait ends when a timer is
        due, and lasts as long as nothing else wakes it (no fixed-rate polling)."""
        deadline = None if self._timers is None else self._timers.next_deadline_ns()
        if deadline is None:
            return timeout
        left = max(0.0, (deadline - time.monotonic_ns()) / 1e9)
        return left if timeout is None or left < timeout else timeout

    def run(self) -> None:
        """The executor thread's loop, until :meth:`stop`."""
        while not self._stopped:
            self._spin_pass(self.TICK_S)


def log_callback_error(log: logging.Logger, owner: Any, exc: BaseException) -> None:
    """Log what a user callback of ``owner`` (a subscription, a timer; its
    ``counters.callback_errors`` counted it already) raised: the first with its traceback, the
    next ones in a line each (a timer raising at 100 Hz would fill the log with the same
    traceback; ``owner.last_error`` keeps the latest). One that ran past its node's close and
    published on the closed node is the end of the program (Ctrl-C): debug level only."""
    if isinstance(exc, NodeClosedError) and owner.node.closed:
        log.debug("%r: callback ran past its node's close: %s", owner, exc)
        return
    count = owner.counters.callback_errors
    if count <= 1:
        log.error("%r: callback raised %s", owner, type(exc).__name__,
                  exc_info=(type(exc), exc, exc.__traceback__))
    else:
        log.error("%r: callback raised %s: %s (%d so far; the first one's traceback was logged)",
                  owner, type(exc).__name__, exc, count)

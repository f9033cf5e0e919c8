"""Timers, as rclpy's: a callback every ``timer_period_sec`` seconds on the node's executor.

``node.create_timer(period, callback)`` makes a :class:`Timer`. A due timer becomes ready the way
a subscription with a message does (``NodeExecutor.make_ready``), so it runs where the node's
subscription callbacks run (the node's thread, ``node.spin()``, or the executor the node was
added to), under its callback group. The node's loop finds due timers: its waits end at the
nearest deadline (:meth:`TimerSet.next_deadline_ns`), not at a fixed poll rate.

The clock is steady (``time.monotonic_ns``). Deadlines advance by whole periods from the
previous deadline, never from when the callback ran, so the rate does not drift; a timer late by
more than a period skips the ticks it missed instead of running them in a burst (as rcl's
``rcl_timer_call``). A timer's callback never overlaps itself.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from time import monotonic_ns  # the steady clock (tests may replace this name)
from typing import TYPE_CHECKING, Any

from ._executor import log_callback_error, spinning_here
from .errors import InvalidEndpointError, NodeClosedError

if TYPE_CHECKING:
    from .callback_groups import CallbackGroup
    from .node import Node

__all__ = ["Timer", "TimerCounters", "TimerSet", "period_ns"]

_log = logging.getLogger(__name__)


def period_ns(timer_period_sec: float) -> int:
    """A timer period in seconds as whole nanoseconds; InvalidEndpointError unless it is a
    positive, finite number of at least 1 ns."""
    if isinstance(timer_period_sec, (bool, str, bytes, bytearray)):  # float("1") would pass
        raise InvalidEndpointError(
            f"timer_period_sec must be a number of seconds, got {timer_period_sec!r}")
    try:
        seconds = float(timer_period_sec)
    except (TypeError, ValueError, OverflowError):
        raise InvalidEndpointError(
            f"timer_period_sec must be a number of seconds, got {timer_period_sec!r}") from None
    if not 0 < seconds < math.inf:  # (NaN fails both comparisons)
        raise InvalidEndpointError(
            f"timer_period_sec must be positive and finite, got {timer_period_sec!r}")
    nanoseconds = round(seconds * 1e9)
    if nanoseconds < 1:
        raise InvalidEndpointError(f"timer_period_sec {seconds!r} is below 1 ns")
    return nanoseconds


@dataclass
class TimerCounters:
    calls: int = 0  # callbacks started
    callback_errors: int = 0  # exceptions raised by the callback
    skipped: int = 0  # ticks left out because the timer ran more than a period late


class TimerSet:
    """The timers of one node, and when the next is due. One lock guards the scheduling state
    of all of them (a timer's deadline, cancelled and ready flags): timers are few, and their
    state changes once a tick."""

    def __init__(self, wake: Callable[[], None]) -> None:
        self.lock = threading.Lock()
        self._wake = wake  # the node loop's waker: a deadline changed, recompute the wait
        self._timers: list[Timer] = []
        self._closed = False

    def add(self, timer: Timer) -> None:
        """Start watching ``timer``; NodeClosedError once the node closed."""
        with self.lock:
            if self._closed:
                raise NodeClosedError(f"node {timer.node.name!r} is closed")
            self._timers.append(timer)
        self.wake()

    def remove(self, timer: Timer) -> bool:
        """Stop watching ``timer``; whether it was watched."""
        with self.lock:
            if timer not in self._timers:
                return False
            self._timers.remove(timer)
            return True

    def close(self) -> list[Timer]:
        """No timer of the node is made ready from now on, nor can one be added; returns the
        timers it watched."""
        with self.lock:
            self._closed = True
            timers, self._timers = self._timers, []
            return timers

    def timers(self) -> list[Timer]:
        """The timers watched now (a copy)."""
        with self.lock:
            return list(self._timers)

    def wake(self) -> None:
        """Make the node's loop recompute its wait (a deadline moved, a timer is free again)."""
        if not self._closed:  # a closed node's waker is closed too
            self._wake()

    def next_deadline_ns(self) -> int | None:
        """The nearest deadline of a running timer not made ready yet (a ready one waits for
        its turn and needs no wake-up); None: none is running."""
        if not self._timers:  # every pass of the node's loop asks: no lock for a node without
            return None
        with self.lock:
            deadlines = [timer.deadline_ns for timer in self._timers if timer.waits_for_deadline]
        return min(deadlines) if deadlines else None

    def take_due(self, now_ns: int) -> list[Timer]:
        """The running timers due at ``now_ns`` that are not ready yet, marked ready: the
        caller makes them ready on the executor (each is there at most once)."""
        if not self._timers:  # (as next_deadline_ns)
            return []
        with self.lock:
            due = [timer for timer in self._timers
                   if timer.waits_for_deadline and timer.deadline_ns <= now_ns]
            for timer in due:
                timer.scheduled = True
        return due


class Timer:
    """Created by :meth:`Node.create_timer`: calls ``callback()`` every ``timer_period_ns``
    nanoseconds on the node's executor, in ``callback_group``, until cancelled or destroyed.

    Attributes: ``node``, ``callback`` (called with no arguments; may be replaced),
    ``callback_group``, ``counters`` (:class:`TimerCounters`) and ``last_error`` (the last
    exception a callback raised, which is also logged; the timer goes on)."""

    def __init__(self, node: Node, timers: TimerSet, callback: Callable[[], Any],
                 timer_period_ns: int, callback_group: CallbackGroup, *,
                 autostart: bool = True) -> None:
        self.node = node
        self.callback = callback
        self.callback_group = callback_group
        self.counters = TimerCounters()
        self.last_error: BaseException | None = None
        self._timers = timers
        self._lock = timers.lock  # (see TimerSet)
        self._period_ns = timer_period_ns
        now = monotonic_ns()
        self._last_call_ns = now  # rcl counts time since the last call from creation first
        #: The next deadline (monotonic ns); read by the TimerSet under the shared lock.
        self.deadline_ns = now + timer_period_ns
        self._canceled = not autostart  # rclpy: autostart=False makes a cancelled timer
        self._destroyed = False
        #: Ready on an executor, or running: not made ready again until run_one ends.
        self.scheduled = False

    def __repr__(self) -> str:
        return (f"Timer(period={self._period_ns / 1e9:g} s, node={self.node.name!r}, "
                f"canceled={self._canceled})")

    @property
    def waits_for_deadline(self) -> bool:
        """Whether the node's loop must make this timer ready at its deadline (call with the
        lock held)."""
        return not (self._canceled or self._destroyed or self.scheduled)

    # -- rclpy's API ------------------------------------------------------------------------
    @property
    def timer_period_ns(self) -> int:
        """The period in nanoseconds. Setting it takes effect from the next deadline on, as
        rcl's; InvalidEndpointError unless positive."""
        return self._period_ns

    @timer_period_ns.setter
    def timer_period_ns(self, value: int) -> None:
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise InvalidEndpointError(f"timer_period_ns must be an int >= 1, got {value!r}")
        with self._lock:
            self._period_ns = value

    def cancel(self) -> None:
        """Stop calling the callback (one running now finishes); :meth:`reset` starts again."""
        with self._lock:
            self._canceled = True

    def is_canceled(self) -> bool:
        """Whether the timer is cancelled (or destroyed)."""
        return self._canceled or self._destroyed

    def reset(self) -> None:
        """Restart the period from now (and un-cancel), as rclpy's. NodeClosedError on a
        destroyed timer, or one whose node closed."""
        with self._lock:
            if self._destroyed:
                raise NodeClosedError(f"{self!r} was destroyed")
            self._canceled = False
            self.deadline_ns = monotonic_ns() + self._period_ns
        self._timers.wake()

    def is_ready(self) -> bool:
        """Whether the timer is running and its deadline has passed."""
        with self._lock:
            return (not (self._canceled or self._destroyed)
                    and monotonic_ns() >= self.deadline_ns)

    def time_since_last_call(self) -> int:
        """Nanoseconds since the callback last started (since creation before the first)."""
        return monotonic_ns() - self._last_call_ns

    def time_until_next_call(self) -> int | None:
        """Nanoseconds until the next deadline (negative: overdue); None while cancelled."""
        with self._lock:
            if self._canceled or self._destroyed:
                return None
            return self.deadline_ns - monotonic_ns()

    def destroy(self) -> None:
        """Cancel the timer and take it off its node for good (as ``node.destroy_timer``)."""
        self.node.destroy_timer(self)

    def forget(self) -> None:
        """The node let go of this timer (destroy_timer, close): it never runs again."""
        with self._lock:
            self._destroyed = True
            self._canceled = True

    # -- the executor's side (the Runnable protocol) -------------------------------------------
    def run_one(self) -> bool:
        """Run the callback if the timer is still due; whether it ran. The next deadline is the
        previous one plus a period; ticks missed by more than a period are skipped."""
        with self._lock:
            now = monotonic_ns()
            if self._canceled or self._destroyed or now < self.deadline_ns:
                # cancelled, or reset, since it was made ready: nothing to run
                self.scheduled = False
                due = False
            else:
                due = True
                self._last_call_ns = now
                self._advance(now)
        if not due:
            self._timers.wake()  # its deadline (if any) is the loop's to watch again
            return False
        node = self.node
        in_flight = node.scheduler.in_flight  # what close() waits for
        thread = in_flight.enter()  # before the check: close() then either sees us or we it
        try:
            if node.closed or self._destroyed:
                return False
            self.counters.calls += 1
            try:
                self.callback()
            except Exception as exc:
                self._callback_failed(exc)
            except BaseException as exc:  # Ctrl-C, SystemExit: the user's own thread gets it
                if spinning_here():
                    raise
                self._callback_failed(exc)  # a library thread must not end (as subscriptions)
            return True
        finally:
            in_flight.leave(thread)
            with self._lock:
                self.scheduled = False
            self._timers.wake()

    def _advance(self, now: int) -> None:
        """Move the deadline one period on, or past ``now`` by whole periods when the timer
        ran over a period late (call with the lock held)."""
        period = self._period_ns
        deadline = self.deadline_ns + period
        if deadline < now:
            missed = 1 + (now - deadline - 1) // period
            deadline += missed * period
            self.counters.skipped += missed
        self.deadline_ns = deadline

    def _callback_failed(self, exc: BaseException) -> None:
        self.counters.callback_errors += 1  # (only this timer's run_one writes it: no overlap)
        self.last_error = exc
        log_callback_error(_log, self, exc)

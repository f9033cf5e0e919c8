"""The executor of a node: a set of ready subscriptions and one waker.

A subscription with messages waiting is in the ready deque exactly once (it re-enters itself
after each message while more wait, so subscriptions take turns); the keep-last queue of each
subscription is the only buffer, and nothing grows with the arrival rate. The loop runs on the
node's thread (:meth:`run`) or inside the user's :meth:`spin_once`; a waker that delivers
messages on the waiting thread (the fast lane's) may run a callback inside its wait when nothing
else is ready (:meth:`has_ready`, :meth:`ran_inline`).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from typing import Protocol

from ._waker import ThreadWaker, Waker

__all__ = ["Executor", "Runnable"]

_log = logging.getLogger(__name__)


class Runnable(Protocol):
    def _run_one(self) -> bool:
        """Deliver the next waiting message (re-schedules itself while more wait); whether a
        callback ran."""


class Executor:
    """Ready subscriptions, run one message at a time, woken by ``waker``."""

    #: Longest sleep between housekeeping rounds.
    TICK_S = 0.2
    #: How often a wait for the callback gate checks whether the executor was stopped.
    GATE_POLL_S = 0.05

    def __init__(self, waker: Waker | None, housekeeping: Callable[[], None],
                 gate: threading.Lock | None = None) -> None:
        self.waker: Waker = waker if waker is not None else ThreadWaker()
        # Held while a callback runs, when callbacks may also run on arrival threads (see
        # Subscription._enqueue): one callback of the node at a time.
        self._gate = gate
        self._ready: collections.deque[Runnable] = collections.deque()
        self._housekeeping = housekeeping
        self._next_housekeeping = time.monotonic() + self.TICK_S
        self._stopped = False
        self._inline = 0  # callbacks run inside the waker's wait (see ran_inline)

    def schedule(self, item: Runnable) -> None:
        """Make ``item`` ready (the caller guarantees it is not ready already)."""
        self._ready.append(item)
        self.waker.notify()

    def has_ready(self) -> bool:
        """Whether anything waits to run. A message that arrives on the waiting thread (a lane
        message, inside the waker's wait) may run its callback at once only when nothing does,
        so turns and order stay as if it had been queued."""
        return bool(self._ready)

    def ran_inline(self) -> None:
        """A callback ran inside the waker's wait, on the waiting thread (counted by
        :meth:`spin_once`)."""
        self._inline += 1

    def stop(self) -> None:
        self._stopped = True
        self.waker.notify()

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
            self.waker.wait(timeout)
        ran = self._inline - inline
        ready = self._ready
        for _ in range(len(ready)):  # only what is ready now: re-scheduled items wait a turn
            if self._stopped:
                break
            try:
                item = ready.popleft()
            except IndexError:
                break
            gate = self._gate
            if gate is not None and not gate.acquire(blocking=False):
                while not gate.acquire(timeout=self.GATE_POLL_S):  # a callback runs elsewhere
                    if self._stopped:
                        ready.appendleft(item)
                        return ran
            try:
                ran += bool(item._run_one())  # a message that failed to decode ran nothing
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

    def run(self) -> None:
        """The executor thread's loop, until :meth:`stop`."""
        while not self._stopped:
            self._spin_pass(self.TICK_S)

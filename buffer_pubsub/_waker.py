"""The one object a node's executor waits on (the fast lane's ``LaneWaker`` is one).

A waker has ``wait(timeout) -> None`` (return when notified or after ``timeout`` seconds, None =
no limit) and ``notify() -> None`` (wake the waiter; callable from any thread, cheap when nobody
waits). A notification given while nobody waits is kept until the next ``wait``. Another wake
source (the lane's ``LaneWaker``, say) can stand in for :class:`ThreadWaker` so its events run on the
same executor thread, or in the user's own ``spin()``, without an extra thread hop.
"""

from __future__ import annotations

import queue
from typing import Protocol

__all__ = ["ThreadWaker", "Waker"]


class Waker(Protocol):
    """What a node's executor needs of its wake-up source."""

    def wait(self, timeout: float | None) -> None:
        """Block until :meth:`notify` was called (since the last wait) or ``timeout`` passed."""

    def notify(self) -> None:
        """Wake the waiter (or the next one, if nobody waits)."""


class ThreadWaker:
    """The default waker: one token in a ``queue.SimpleQueue`` (a C-level blocking hand-off,
    cheaper than ``threading.Event``, whose methods run in Python)."""

    __slots__ = ("_queue", "_pending")

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue[None] = queue.SimpleQueue()
        self._pending = False

    def wait(self, timeout: float | None) -> None:
        try:
            self._queue.get(timeout=timeout)
        except queue.Empty:
            pass
        # Reset after waking: work notified before this line is already in the ready set the
        # executor drains next, so no notification is lost. Two racing notifiers may both put a
        # token; the extra one only makes the next wait return early.
        self._pending = False

    def notify(self) -> None:
        if not self._pending:
            self._pending = True
            self._queue.put(None)

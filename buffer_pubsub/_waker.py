"""What a node's executor waits on: the :class:`Waker` protocol.

A waker has ``wait(timeout) -> None`` (return when notified or after ``timeout`` seconds, None =
no limit) and ``notify() -> None`` (wake the waiter; callable from any thread, cheap when nobody
waits). A notification given while nobody waits is kept until the next ``wait``.

There is one implementation, :class:`buffer_pubsub.fast_lane.LaneWaker` (native: an eventfd and
``ppoll``); every node makes one, whether the lane runs or not, so one code path wakes every
executor. A waker that also delivers messages on the waiting thread (the lane's) runs their
callbacks on the executor thread, or in the user's own ``spin()``, without a thread hop. A user's
own ``Node(waker=...)`` may be anything that has these two methods.
"""

from __future__ import annotations

from typing import Protocol

__all__ = ["Waker"]


class Waker(Protocol):
    """What a node's executor needs of its wake-up source."""

    def wait(self, timeout: float | None) -> None:
        """Block until :meth:`notify` was called (since the last wait) or ``timeout`` passed."""

    def notify(self) -> None:
        """Wake the waiter (or the next one, if nobody waits)."""

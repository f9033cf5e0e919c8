"""Callback groups, as rclpy's: which callbacks a multi-threaded executor may run together.

Every subscription and timer belongs to one group: the one passed as
``node.create_subscription(..., callback_group=group)`` or ``node.create_timer(...,
callback_group=group)``, else the node's ``default_callback_group`` (mutually exclusive, so a
node's callbacks run one at a time unless you say otherwise).

- :class:`MutuallyExclusiveCallbackGroup`: at most one callback of the group runs at a time.
  Give a slow callback a group of its own and it no longer holds up the others.
- :class:`ReentrantCallbackGroup`: any number of the group's callbacks run at once, the same
  subscription's included (on several messages). The callback must then be thread-safe.

Groups matter only where callbacks may run in parallel: on a
:class:`~buffer_pubsub.executors.MultiThreadedExecutor`. A node's own thread, ``node.spin()``
and a :class:`~buffer_pubsub.executors.SingleThreadedExecutor` run one callback at a time.
"""

from __future__ import annotations

import collections
import threading
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ._executor import Runnable

__all__ = ["CallbackGroup", "MutuallyExclusiveCallbackGroup", "ReentrantCallbackGroup"]


class CallbackGroup:
    """Base class: decides whether a ready subscription or timer may start its callback now."""

    def enter(self, item: Runnable) -> bool:
        """Whether ``item`` may run now; if not, the group keeps it and hands it back from
        :meth:`_leave` once it may."""
        raise NotImplementedError

    def leave(self) -> Runnable | None:
        """A callback of the group ended; a kept item that may run now, if any."""
        raise NotImplementedError


class MutuallyExclusiveCallbackGroup(CallbackGroup):
    """At most one callback of this group runs at a time (the default group of a node)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._running = False
        # Subscriptions ready while another callback of the group ran, oldest first; each is
        # here at most once (a subscription is in one ready set at a time).
        self._waiting: collections.deque[Runnable] = collections.deque()

    def enter(self, item: Runnable) -> bool:
        with self._lock:
            if self._running:
                self._waiting.append(item)
                return False
            self._running = True
            return True

    def leave(self) -> Runnable | None:
        with self._lock:
            self._running = False
            return self._waiting.popleft() if self._waiting else None

    def __repr__(self) -> str:
        return f"MutuallyExclusiveCallbackGroup(running={self._running})"


class ReentrantCallbackGroup(CallbackGroup):
    """The group's callbacks may all run at once, including one subscription's on several
    messages: its callbacks must be thread-safe."""

    def enter(self, item: Runnable) -> bool:
        return True

    def leave(self) -> Runnable | None:
        return None

    def __repr__(self) -> str:
        return "ReentrantCallbackGroup()"

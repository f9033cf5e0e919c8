"""The recorder's cache: serialized messages waiting for the bag writer, bounded in bytes.

Subscription callbacks put (never wait: a callback that blocked would stall the node, and with it
every other topic); the writer thread takes. A message that does not fit is refused, and the
caller counts it as dropped: the disk could not keep up.
"""

from __future__ import annotations

import collections
import threading
from typing import Any


class WriteCache:
    """A FIFO of ``(item, nbytes)`` holding at most ``max_bytes`` (one item always fits, so a
    message larger than the cache is written when the cache is empty, never refused for good)."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.queued_bytes = 0
        self.peak_bytes = 0
        self._items: collections.deque[tuple[Any, int]] = collections.deque()
        self._cond = threading.Condition()
        self._closed = False

    def put(self, item: Any, nbytes: int) -> bool:
        """Queue ``item``; False (nothing queued) when it does not fit or the cache is closed."""
        with self._cond:
            if self._closed or (self._items and self.queued_bytes + nbytes > self.max_bytes):
                return False
            self._items.append((item, nbytes))
            self.queued_bytes += nbytes
            self.peak_bytes = max(self.peak_bytes, self.queued_bytes)
            self._cond.notify()
            return True

    def has_room(self, nbytes: int) -> bool:
        """Whether :meth:`put` of ``nbytes`` would be taken now (a caller skips the work of
        making an item that would be refused)."""
        with self._cond:
            return not self._closed and (not self._items
                                         or self.queued_bytes + nbytes <= self.max_bytes)

    def put_always(self, item: Any) -> None:
        """Queue ``item`` whatever the cache holds (a command for the writer, no payload)."""
        with self._cond:
            if self._closed:
                raise RuntimeError("the write cache is closed")
            self._items.append((item, 0))
            self._cond.notify()

    def get(self, timeout: float | None = None) -> Any | None:
        """The oldest item, waiting for one; None once the cache is closed and empty.
        Raises :class:`TimeoutError` when ``timeout`` seconds pass with nothing queued."""
        with self._cond:
            while not self._items:
                if self._closed:
                    return None
                if not self._cond.wait(timeout):
                    raise TimeoutError("nothing queued")
            item, nbytes = self._items.popleft()
            self.queued_bytes -= nbytes
            return item

    def close(self) -> None:
        """Refuse new items; :meth:`get` drains what is queued, then returns None."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

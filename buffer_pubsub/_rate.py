"""A subscription's ``max_rate``: admit at most one message per interval, on a steady grid."""

from __future__ import annotations

__all__ = ["RateLimit"]


class RateLimit:
    """Admits the first message at or after each due time. While messages keep coming, the due
    times stay on a grid of ``1 / rate_hz`` (a 30 Hz source limited to 10 Hz yields 10 Hz, not
    7.5); after a pause, or at the start, the grid restarts at the admitted message (no burst)."""

    __slots__ = ("interval", "next_due")

    def __init__(self, rate_hz: float) -> None:
        self.interval = 1.0 / rate_hz
        self.next_due = float("-inf")

    def admit(self, now: float) -> bool:
        """Whether a message at ``now`` (monotonic seconds) passes; not thread-safe."""
        if now < self.next_due:
            return False
        if now - self.next_due < self.interval:
            self.next_due += self.interval  # on schedule: keep the grid
        else:
            self.next_due = now + self.interval
        return True

"""When a subscription's callback may run on the Zenoh thread its sample arrived on.

Handing a sample to the node's executor thread costs a thread wake-up (15-60 us here); running
the callback where the sample arrived costs nothing. But the thread zenoh-python runs our
subscriber callback on drains a bounded channel: while a callback runs there, later samples of
that subscriber wait in Zenoh (outside the keep-last queue, so nothing is dropped or counted)
and, once that channel is full, Zenoh's network thread blocks and the whole session stalls,
discovery included. So a subscription runs callbacks inline only while they have proved short:

- it starts by handing every sample off (a first callback that compiles a kernel for seconds
  never runs on Zenoh's thread);
- after ``needed`` consecutive callbacks each shorter than :data:`BUDGET_S` it runs them inline
  (when nothing waits before them and no other callback of the node runs: see the subscription);
- one callback over budget, or samples arriving back to back behind inline callbacks (a backlog
  building in Zenoh), hands off again, and the streak needed doubles (up to :data:`MAX_NEEDED`).

The worst a trusted callback that suddenly blocks can do is hold that subscriber's Zenoh
deliveries (and, once Zenoh's channel for it is full, the session's) for its own duration, once.
``Node(..., inline_callbacks=False)`` never inlines; ``executor="manual"`` never does either.
"""

from __future__ import annotations

import time

__all__ = ["BUDGET_S", "FIRST_NEEDED", "InlinePolicy", "MAX_NEEDED"]

#: A callback shorter than this may run on Zenoh's thread.
BUDGET_S = 0.0005
#: Consecutive short callbacks before the first inline one; doubled at each demotion.
FIRST_NEEDED = 8
MAX_NEEDED = 4096
#: An inline arrival this soon after the previous inline callback ended waited behind it.
BACK_TO_BACK_NS = 20_000
#: Back-to-back inline arrivals in a row that mean a backlog in Zenoh.
MAX_BACK_TO_BACK = 4


class InlinePolicy:
    """One subscription's record of its callbacks' durations (updated one callback at a time,
    under the node's callback gate or on its one executor thread)."""

    __slots__ = ("_streak", "_needed", "_last_end_ns", "_back_to_back")

    def __init__(self) -> None:
        self._streak = 0
        self._needed = FIRST_NEEDED
        self._last_end_ns = 0
        self._back_to_back = 0

    @property
    def trusted(self) -> bool:
        """Whether the next sample may run its callback inline."""
        return self._streak >= self._needed

    def ran(self, seconds: float, inline: bool) -> None:
        """A callback took ``seconds`` (``inline``: on the arrival thread)."""
        if seconds > BUDGET_S:
            self._demote()
            return
        self._streak += 1
        if inline:
            self._last_end_ns = time.perf_counter_ns()

    def arrived_inline(self) -> bool:
        """An inline candidate arrived: False (and demoted) when it queued behind the previous
        inline callbacks in Zenoh's channel, so the keep-last queue takes over."""
        if time.perf_counter_ns() - self._last_end_ns < BACK_TO_BACK_NS:
            self._back_to_back += 1
            if self._back_to_back >= MAX_BACK_TO_BACK:
                self._demote()
                return False
        else:
            self._back_to_back = 0
        return True

    def _demote(self) -> None:
        if self._streak >= self._needed:
            self._needed = min(self._needed * 2, MAX_NEEDED)
        self._streak = 0
        self._back_to_back = 0

"""Ours: the fast lane with a busy-polling receiver (``LaneWaker(busy_poll_s=0.001)``).

The same messages as the ``lane`` path; after each message the receiver spins up to 1 ms
checking for the next before it blocks. Its CPU cost is in the receiver's report
(``cpu_per_wall_s``: 1.0 = a core held at 100%; the spin releases the GIL).
"""

from __future__ import annotations

from typing import Any

from benchmarks.paths import PathSettings
from benchmarks.paths.lane import LaneReceiver, make_sender

__all__ = ["LABEL", "KIND", "TOPOLOGY", "make_receiver", "make_sender"]

LABEL = "ours: fast lane, busy-poll receiver (1 ms spin)"
KIND = "ours"
TOPOLOGY = "pair"
BUSY_POLL_S = 0.001


def make_receiver(settings: PathSettings, shared: Any) -> LaneReceiver:
    """The subscribing side, spinning before it blocks."""
    return LaneReceiver(settings, busy_poll_s=BUSY_POLL_S)

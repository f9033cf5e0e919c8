"""An independent Python model of the rules ``buffer_pubsub._streams.Streams`` applies in C
(the tests judge the C tracker against it): gaps, late messages, duplicates.

Sequence numbers are judged per *channel* (the Zenoh key a sample came on, or the lane, which
carries what that subscription's own ``_buf/<gid>`` key carries) and publisher:

- our publishers number each channel on its own from 1, so on any channel a step of more than
  one is that many messages lost;
- rmw_zenoh's buffer-aware publishers number every *put* (one publish to N channels uses N
  numbers), so on one channel their numbers advance by the publisher's fan-out. That stride is
  learned from the steps themselves: a step seen twice running is the stride; a step that is a
  whole multiple of it is loss. A graph change that alters the fan-out costs no false loss
  (its step repeats before it is judged), at the price of judging a single odd step one
  message late.

A message reaches a subscription by one route per publisher, except while one of our publishers
serves both the base key (for a peer that advertises no backends) and this subscription's own
stream: the same message then arrives twice, with the same source timestamp (ours are strictly
increasing per publisher). :class:`Deduplicator` drops the second copy.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass

__all__ = ["IN_ORDER", "Deduplicator", "SequenceTracker", "Verdict"]

#: Largest step counted as loss; a larger jump (a restarted or spoofed counter) resynchronizes.
LOST_WINDOW = 1 << 16
#: Channel x publisher pairs remembered (the oldest forgotten first).
MAX_TRACKED = 1024
#: Source timestamps remembered per publisher for duplicate detection: how far one route of a
#: publisher may run ahead of another before a copy is no longer recognized.
RECENT_STAMPS = 256


@dataclass(frozen=True)
class Verdict:
    """What one arrival says: messages ``lost`` before it; ``late`` (older than one already
    seen on its channel: neither new nor a gap); ``jump`` (resynchronized)."""

    lost: int = 0
    late: bool = False
    jump: bool = False


#: The verdict of a message in order (the common case: one object, compared by identity).
IN_ORDER = Verdict()
_LATE = Verdict(late=True)
_JUMP = Verdict(jump=True)


class _Channel:
    __slots__ = ("last", "stride", "odd_step", "odd_lost")

    def __init__(self, sequence: int) -> None:
        self.last = sequence
        self.stride = 0  # 0: not learned yet
        self.odd_step = 0  # a step that differed from the stride, judged at the next arrival
        self.odd_lost = 0  # what it means if the stride holds


class SequenceTracker:
    """Per (channel, publisher) sequence state. Not thread-safe: callers hold their lock."""

    def __init__(self) -> None:
        self._channels: dict[tuple[str, bytes], _Channel] = {}

    def track(self, channel: str, gid: bytes, sequence: int, numbered_per_channel: bool,
              from_one: bool = False, restarts: bool = False) -> Verdict:
        """Judge ``sequence`` from publisher ``gid`` on ``channel``. ``numbered_per_channel``:
        the publisher numbers each channel from 1 (one of ours), so every step is exact.
        ``from_one``: the channel was started for this reader alone (its own stream), so a
        first number past 1 follows that many messages it missed (a lane's keep-last queue
        overwrote them before its first read, say); elsewhere a reader joins at any number.
        ``restarts``: a step back is the publisher's counter starting again (a jump)."""
        key = (channel, gid)
        state = self._channels.get(key)
        if state is None:
            if len(self._channels) >= MAX_TRACKED:
                del self._channels[next(iter(self._channels))]
            self._channels[key] = _Channel(sequence)
            if from_one and numbered_per_channel and 1 < sequence <= LOST_WINDOW:
                return Verdict(lost=sequence - 1)
            return IN_ORDER
        step = sequence - state.last
        if step <= 0:
            if -step < LOST_WINDOW and not restarts:
                return _LATE
            state.__init__(sequence)  # a restarted counter
            return _JUMP
        if step > LOST_WINDOW:
            state.__init__(sequence)
            return _JUMP
        state.last = sequence
        if numbered_per_channel:
            return Verdict(lost=step - 1) if step > 1 else IN_ORDER
        return self._judge_stride(state, step)

    def last(self, channel: str, gid: bytes) -> int | None:
        """The last number seen from ``gid`` on ``channel`` (None: nothing yet)."""
        state = self._channels.get((channel, gid))
        return None if state is None else state.last

    @staticmethod
    def _judge_stride(state: _Channel, step: int) -> Verdict:
        lost = 0
        if state.odd_step:  # the previous step differed from the stride: judged now
            if step == state.odd_step:  # it repeats: the publisher's fan-out changed
                state.stride, state.odd_step, state.odd_lost = step, 0, 0
                return IN_ORDER
            lost, state.odd_step, state.odd_lost = state.odd_lost, 0, 0
        if state.stride == 0:
            state.stride = step
        elif step != state.stride:
            state.odd_step = step
            state.odd_lost = step // state.stride - 1 if step % state.stride == 0 else 0
        return Verdict(lost=lost) if lost else IN_ORDER


class Deduplicator:
    """Recognizes a second copy of a message by its publisher and source timestamp. Not
    thread-safe: callers hold their lock."""

    def __init__(self) -> None:
        self._seen: dict[bytes, tuple[set[int], collections.deque[int]]] = {}

    def seen_before(self, gid: bytes, stamp: int) -> bool:
        """Whether a message of ``gid`` stamped ``stamp`` arrived already (it is then dropped);
        otherwise remembers it."""
        entry = self._seen.get(gid)
        if entry is None:
            if len(self._seen) >= MAX_TRACKED:
                del self._seen[next(iter(self._seen))]
            entry = self._seen[gid] = (set(), collections.deque())
        stamps, order = entry
        if stamp in stamps:
            return True
        stamps.add(stamp)
        order.append(stamp)
        if len(order) > RECENT_STAMPS:
            stamps.discard(order.popleft())
        return False

    def forget(self, gid: bytes) -> None:
        self._seen.pop(gid, None)

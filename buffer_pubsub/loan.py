"""Loaned messages: a publisher hands out messages whose buffers it reuses, as rclcpp's loaned
messages and iceoryx2's ``loan`` do.

    with publisher.loan(factory) as msg:
        fill msg in place
    # published on exit; an exception in the block publishes nothing and returns the loan

``factory`` makes a new message for the pool (called only when no pooled one is free). The
pool key is ``factory.loan_key`` when it has one (so specs built per frame with equal values
share a pool), else the factory itself. A pooled message is handed out again only when nobody
else references it or its buffers (intra-process subscribers get snapshots over its
``Buffer`` objects: a reader holding the message, a snapshot or a ``Buffer`` of it is a hold;
counted by reference, CPython; a message with no buffer is never pooled) and
every buffer's backend re-armed it (:meth:`rosidl_buffer.BufferImplBase.reclaim`: no reader in
this or another process holds its memory). Otherwise the pool grows, up to ``max_loans``
messages per key; past that a loan is a fresh, unpooled message (correct, just not reused).

This module knows backends only through ``reclaim``; what a loan's buffers and native views
are comes from the factory (``tensor_conversions`` provides tensor specs; a message whose
storage cannot be re-armed, an image allocated on warp storage say, is loaned unpooled).
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rosidl_buffer import Buffer, BufferImplBase
from rosidl_buffer.messages import Message, iter_buffers
from rosidl_buffer.messages._schema import FieldKind

from .errors import LoanError

if TYPE_CHECKING:
    from .publisher import Publisher

__all__ = ["Loan", "LoanPool", "DEFAULT_MAX_LOANS", "flat_buffer_fields"]

DEFAULT_MAX_LOANS = 16


def flat_buffer_fields(msg_type: type[Message]) -> tuple[str, ...] | None:
    """The buffer fields of a message type without nested messages (the common case: one
    getattr each), or None when nested messages need the full walk (``iter_buffers``)."""
    if any(spec.kind is FieldKind.MESSAGE for spec in msg_type._schema.fields):
        return None
    return tuple(sorted(msg_type._buffer_fields))


class _Slot:
    """One pooled message, its buffers and their reference counts when only we held them."""

    __slots__ = ("msg", "fields", "buffers", "baseline", "loaned")

    def __init__(self, msg: Message) -> None:
        self.msg: Message = msg
        self.fields = flat_buffer_fields(type(msg))
        self.buffers: tuple[Buffer, ...] = self._buffers_now()
        self.baseline = _buffer_refs(self.buffers)
        self.loaned = True

    def _buffers_now(self) -> tuple[Buffer, ...]:
        msg, fields = self.msg, self.fields
        if fields is None:
            return tuple(iter_buffers(msg))
        return tuple([getattr(msg, name) for name in fields])

    def reusable(self) -> bool:
        """Nobody but the pool references the message or its buffers, and every backend
        re-armed its memory (no reader holds it)."""
        if self.loaned or _refs(self.msg) > _SLOT_REFS:
            return False
        buffers = self.buffers
        if any(now > then for now, then in zip(_buffer_refs(buffers), self.baseline)):
            return False
        return all(buffer.get_impl().reclaim() for buffer in buffers)

    def intact(self) -> bool:
        """The message still holds the pooled buffers (a field may have been replaced)."""
        now = self._buffers_now()
        return len(now) == len(self.buffers) and all(a is b for a, b in zip(now, self.buffers))


def _buffer_refs(buffers: tuple[Buffer, ...]) -> tuple[int, ...]:
    """Reference counts of ``buffers``, measured the same way whenever called (so a count above
    the one taken when the slot was made is a reference someone else holds)."""
    return tuple([sys.getrefcount(buffer) for buffer in buffers])


def _refs(obj: Any) -> int:
    return sys.getrefcount(obj) - 1  # less getrefcount's own argument


_SLOT_REFS = 2  # _Slot.msg and the caller's argument of _refs (slot.msg evaluated once)


def _rearmable(msg: Message) -> bool:
    """Can every buffer of ``msg`` be re-armed for a later loan (its impl has a ``reclaim``)?
    A pool of messages whose storage never can would only pin them (a plain warp buffer). A
    message with no buffer is not pooled either: in-process readers hold snapshots of it (see
    buffer_pubsub._snapshot) that share its arrays, and only buffers count their readers."""
    buffers = list(iter_buffers(msg))
    return bool(buffers) and all(type(buffer.get_impl()).reclaim is not BufferImplBase.reclaim
                                 for buffer in buffers)


class LoanPool:
    """The pooled messages of one publisher, by factory key (see the module docstring)."""

    def __init__(self, max_loans: int = DEFAULT_MAX_LOANS) -> None:
        self.max_loans = max_loans
        self._lock = threading.Lock()
        self._slots: dict[Any, list[_Slot]] = {}
        self.created = 0  # pooled messages made by a factory
        self.reused = 0  # loans served by a pooled message
        self.unpooled = 0  # loans not kept: past max_loans, or storage that cannot be re-armed

    def take(self, factory: Callable[[], Message],
             max_loans: int | None = None) -> tuple[Message, _Slot | None]:
        """A pooled message of ``factory``'s key that nobody holds (handed to ``factory.reloan``
        if it has one, so a loan starts as the factory made it), else a new one, pooled while
        the key has fewer than ``max_loans`` (default: the pool's) and its buffers can be
        re-armed at all."""
        key = getattr(factory, "loan_key", factory)
        limit = self.max_loans if max_loans is None else max_loans
        reused = None
        with self._lock:
            slots = self._slots.setdefault(key, [])
            for index, slot in enumerate(slots):
                if slot.reusable():
                    slot.loaned = True
                    self.reused += 1
                    # Least recently loaned first next time: the one just published is the
                    # likeliest to be still held (probing it costs a reclaim that fails).
                    slots.append(slots.pop(index))
                    reused = slot
                    break
            full = len(slots) >= limit
        if reused is not None:
            reloan = getattr(factory, "reloan", None)
            if reloan is not None:
                reloan(reused.msg)
            return reused.msg, reused
        msg = factory()
        if not isinstance(msg, Message):
            raise LoanError(f"the loan factory {factory!r} returned {type(msg).__name__}, "
                            "not a message")
        if not full and _rearmable(msg):
            slot = _Slot(msg)
            with self._lock:
                # Checked again: other threads may have pooled theirs while the factory ran.
                if len(slots) < limit:
                    slots.append(slot)
                    self.created += 1
                    return msg, slot
        with self._lock:
            self.unpooled += 1
        return msg, None

    def give_back(self, slot: _Slot) -> None:
        """The loan ended (published or abandoned); a slot whose buffers were replaced is
        dropped (its message is then an ordinary one)."""
        with self._lock:
            slot.loaned = False
            if not slot.intact():
                for slots in self._slots.values():
                    if slot in slots:
                        slots.remove(slot)

    def stats(self) -> dict[str, int]:
        with self._lock:
            pooled = sum(len(slots) for slots in self._slots.values())
            return {"created": self.created, "reused": self.reused, "unpooled": self.unpooled,
                    "pooled": pooled}

    def clear(self) -> None:
        with self._lock:
            self._slots.clear()


class Loan:
    """``with publisher.loan(factory) as msg:`` (see the module docstring).

    The message is the publisher's until the block ends: on a normal exit it is published (the
    loan ends at publish: buffers are sealed, and a backend may make a view kept past it
    unwritable, as warp_buffer does on its cpu device); on an exception nothing is published
    and the message goes back to the pool. A loaned message published intra-process is not
    reused while any subscriber still references it.
    """

    __slots__ = ("_publisher", "_factory", "_max_loans", "_msg", "_slot")

    def __init__(self, publisher: Publisher, factory: Callable[[], Message],
                 max_loans: int | None = None) -> None:
        self._publisher = publisher
        self._factory = factory
        self._max_loans = max_loans
        self._msg: Message | None = None
        self._slot: _Slot | None = None

    def __enter__(self) -> Message:
        if self._msg is not None:
            raise LoanError("a Loan is entered once; call publisher.loan(...) for the next one")
        self._msg, self._slot = self._publisher._loans.take(self._factory, self._max_loans)
        return self._msg

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        msg, slot = self._msg, self._slot
        self._msg = self._slot = None  # our references must not count as holds
        try:
            if exc_type is None and msg is not None:
                self._publisher.publish(msg)
        finally:
            del msg
            if slot is not None:
                self._publisher._loans.give_back(slot)

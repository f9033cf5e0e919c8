"""Loaned messages: a publisher hands out messages whose buffers it reuses, as rclcpp's loaned
messages and iceoryx2's ``loan`` do.

    with publisher.loan(factory) as msg:
        fill msg in place
    # published on exit; an exception in the block publishes nothing and returns the loan

``factory`` makes a new message for the pool (called only when no pooled one is free).

**Pools are keyed by what the factory makes**: ``factory.loan_key`` when it has one (a loan spec
of ``tensor_conversions``: the message type and the spec's arguments), else its call site: a
function's code with the values its closure and defaults hold, so ``lambda: make(h, w)``
written inside a frame loop is one pool, whichever function object each frame builds. A bound
method is its function and object, a ``functools.partial`` its function and arguments, any
other callable itself. A publisher keeps at most :data:`MAX_POOLS` keys: a new key past that
drops the least recently used pool none of whose messages is on loan (its messages are then
ordinary ones). So neither keys nor pooled messages grow without bound: at most ``MAX_POOLS``
times ``max_loans`` messages.

**A pooled message is handed out again only when nobody can read its storage**, decided by
tokens, never by counting references:

- every loan hands out ``Buffer`` objects of its own over the pooled storage (the message's
  buffer fields get fresh ones when the pool takes the message back): a ``Buffer`` an earlier
  loan handed out is its holders' token: the message's publish put it in every in-process
  subscriber's snapshot, and a user who keeps ``msg.data`` keeps it. The pool sees it alive
  through a weak reference;
- views of the storage hold tokens of the backend's (``BufferImplBase.reclaim``: a warp loan's
  lease, CPU storage's tracked views), and the backend tells whether a peer in another process
  may still read the memory.

The loan ends at publish: the message object itself goes back to the pool (keeping it is not a
hold, as with rclcpp's loaned messages: the next loan may hand out that very object); keep its
``Buffer`` or a view to keep reading a frame. Otherwise the pool grows, up to ``max_loans``
messages per key; past that a loan is a fresh, unpooled message (correct, just not reused).
Messages whose storage cannot be re-armed (a plain warp buffer), with no buffer at all, or
with buffers inside sequences of messages are never pooled.

This module knows backends only through ``reclaim``; what a loan's buffers and native views
are comes from the factory (``tensor_conversions`` provides loan specs for tensors, images and
point clouds).
"""

from __future__ import annotations

import collections
import functools
import threading
import types
from collections.abc import Callable, Hashable
from typing import Any

from rosidl_buffer import Buffer, BufferImplBase
from rosidl_buffer.native import load_extension
from rosidl_buffer.messages import FieldKind, Message, buffer_fields, fields_of

from .errors import InvalidEndpointError, LoanError

_loans = load_extension("buffer_pubsub._loans")
_loans.configure(Buffer, LoanError)

__all__ = ["DEFAULT_MAX_LOANS", "MAX_POOLS", "Loan", "LoanPool", "flat_buffer_fields",
           "loan_key"]

DEFAULT_MAX_LOANS = 16
#: Factory keys a publisher pools at once (see the module docstring).
MAX_POOLS = 16


def flat_buffer_fields(msg_type: type[Message]) -> tuple[str, ...] | None:
    """The buffer fields of a message type without nested messages (the common case: one
    getattr each), or None when nested messages need the full walk."""
    if any(spec.kind is FieldKind.MESSAGE for spec in fields_of(msg_type)):
        return None
    return tuple(sorted(buffer_fields(msg_type)))


# ------------------------------------------------------------------------------ pool keys
class _Identity:
    """An unhashable value in a key, compared by identity (and kept alive, so its id is not
    reused while the key exists)."""

    __slots__ = ("value",)

    def __init__(self, value: Any) -> None:
        self.value = value

    def __hash__(self) -> int:
        return id(self.value)

    def __eq__(self, other: object) -> bool:
        return type(other) is _Identity and other.value is self.value


def _value_key(value: Any) -> Hashable:
    try:
        hash(value)
    except TypeError:
        return _Identity(value)
    return (type(value), value)


def loan_key(factory: Callable[[], Message]) -> Hashable:
    """The pool key of ``factory`` (see the module docstring)."""
    key = getattr(factory, "loan_key", None)
    if key is not None:
        return key
    if type(factory) is types.FunctionType:
        try:
            captured = tuple(_value_key(cell.cell_contents) for cell in factory.__closure__ or ())
        except ValueError:  # a cell not yet bound: only this function object is known
            return _value_key(factory)
        kwdefaults = factory.__kwdefaults__
        return ("function", factory.__code__, captured,
                tuple(_value_key(v) for v in factory.__defaults__ or ()),
                tuple(sorted((k, _value_key(v)) for k, v in kwdefaults.items()))
                if kwdefaults else ())
    if type(factory) is types.MethodType:
        return ("method", loan_key(factory.__func__), _Identity(factory.__self__))
    if type(factory) is functools.partial:
        return ("partial", loan_key(factory.func), tuple(_value_key(v) for v in factory.args),
                tuple(sorted((k, _value_key(v)) for k, v in factory.keywords.items())))
    return _value_key(factory)


# ------------------------------------------------------------------------------ pooled messages
def _places(msg: Message) -> list[tuple[Message, str]] | None:
    """``(message, field)`` of every buffer of ``msg`` (nested messages included), or None
    when a buffer sits in a sequence of messages (not pooled)."""
    places = []
    cls = type(msg)
    for name in sorted(buffer_fields(cls)):
        places.append((msg, name))
    for spec in fields_of(cls):
        if spec.kind is FieldKind.MESSAGE:
            value = getattr(msg, spec.name)
            if isinstance(value, list):
                if any(isinstance(item, Message) and _places(item) for item in value):
                    return None
            elif isinstance(value, Message):
                nested = _places(value)
                if nested is None:
                    return None
                places += nested
    return places


# One pooled message (where its buffers sit, the storage they hold, the Buffers it put there
# and those earlier loans handed out: their holders' tokens) and its ``reusable()``: C, with
# the Loan context manager (see :mod:`._loans`).
_Slot = _loans._Slot


def _rearmable(msg: Message) -> list[tuple[Message, str]] | None:
    """Where the buffers of ``msg`` sit, when every one of them can be re-armed for a later loan
    (its impl has a ``reclaim``), else None: a pool of messages whose storage never can would
    only pin them (a plain warp buffer). A message with no buffer is not pooled either:
    in-process readers hold snapshots of it that share its arrays, which no token covers."""
    places = _places(msg)
    if not places:
        return None
    for owner, name in places:
        buffer = getattr(owner, name)
        if type(buffer.get_impl()).reclaim is BufferImplBase.reclaim:
            return None
    return places


class _Pool:
    __slots__ = ("slots",)

    def __init__(self) -> None:
        self.slots: list[_Slot] = []


class LoanPool:
    """The pooled messages of one publisher, by factory key (see the module docstring)."""

    def __init__(self, max_loans: int = DEFAULT_MAX_LOANS, max_pools: int = MAX_POOLS,
                 msg_type: type[Message] | None = None) -> None:
        """``msg_type``: what the publisher publishes (a factory making anything else is
        refused when the loan is taken, not when the block ends)."""
        self.msg_type = msg_type
        self.max_loans = max_loans
        self.max_pools = max_pools
        #: ids of the messages inside an open ``with`` block, which publishes them when it ends
        #: (a publish() of one inside its block would send it twice).
        self.in_blocks: set[int] = set()
        self._lock = threading.Lock()
        self._pools: collections.OrderedDict[Hashable, _Pool] = collections.OrderedDict()
        self.created = 0  # pooled messages made by a factory
        self.reused = 0  # loans served by a pooled message
        self.unpooled = 0  # loans not kept: past max_loans, or storage that cannot be re-armed

    def take(self, factory: Callable[[], Message],
             max_loans: int | None = None) -> tuple[Message, _Slot | None]:
        """A pooled message of ``factory``'s key that nobody can read (handed to
        ``factory.reloan`` if it has one, so a loan starts as the factory made it), else a new
        one, pooled while the key has fewer than ``max_loans`` (default: the pool's) and its
        buffers can be re-armed at all."""
        key = getattr(factory, "loan_key", None)  # (loan_key's first case, inline: per loan)
        if key is None:
            key = loan_key(factory)
        limit = self.max_loans if max_loans is None else max_loans
        reused = None
        with self._lock:
            pools = self._pools
            pool = pools.get(key)
            if pool is None:
                pool = pools[key] = _Pool()
                if len(pools) > self.max_pools:
                    self._evict()
            else:
                pools.move_to_end(key)
            slots = pool.slots
            # Least recently loaned first; the one taken goes last (the one just published is
            # the likeliest to be still held: probing it costs a reclaim that fails).
            reused = _loans.reuse(slots)
            if reused is not None:
                self.reused += 1
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
        msg_type = self.msg_type
        if msg_type is not None and not isinstance(msg, msg_type):
            raise InvalidEndpointError(
                f"a publisher of {msg_type.__msgtype__} cannot loan a "
                f"{type(msg).__msgtype__}: publish that type on a publisher of its own")
        places = None if full else _rearmable(msg)
        if places is not None:
            slot = _Slot(msg, places)
            with self._lock:
                # Checked again: other threads may have pooled theirs while the factory ran,
                # or the key's pool was dropped meanwhile.
                if pools.get(key) is pool and len(slots) < limit:
                    slots.append(slot)
                    self.created += 1
                    return msg, slot
        with self._lock:
            self.unpooled += 1
        return msg, None

    def _evict(self) -> None:
        """Drop the least recently used pool none of whose messages is on loan (call with the
        lock held, past ``max_pools`` keys)."""
        for key, pool in self._pools.items():
            if not any(slot.loaned for slot in pool.slots):
                del self._pools[key]
                return

    def stats(self) -> dict[str, int]:
        with self._lock:
            pooled = sum(len(pool.slots) for pool in self._pools.values())
            return {"created": self.created, "reused": self.reused, "unpooled": self.unpooled,
                    "pooled": pooled}

    def pools(self) -> int:
        """Factory keys pooled now (at most ``max_pools``)."""
        with self._lock:
            return len(self._pools)

    def clear(self) -> None:
        with self._lock:
            self._pools.clear()


#: ``with publisher.loan(factory) as msg:`` (see the module docstring): C, as a loan's
#: per-message path (``Loan(pool, publish, factory, max_loans=None)``, made by
#: :meth:`Publisher.loan`).
Loan = _loans.Loan

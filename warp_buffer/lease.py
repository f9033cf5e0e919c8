"""The lease of local memory: one owner, its readers, and when the bytes may be written again.

A :class:`Lease` is one owner's use of a block of a pool (:mod:`warp_buffer.pool`), or of private
memory (a cpu clone, until its first export moves it into a block). It is the one place where that
use changes state; every transition is one method that takes the lease's lock once::

    FREE --acquire--> WRITABLE --open_write--> WRITING --close_write--> WRITTEN
                         |                        |                        |
                         +------ seal (a publish) or mark_read (a reader) -+
                                               v
                      PUBLISHED (or READ): no write any more; export(peer) sends the
                      block to peers, readers in this process hold tokens (hold)
                                               |
                      reclaim: no token alive, every peer delivered, no reader in
                      another process, CUDA last uses complete --> WRITABLE (a loan)
                                               |
                      the lease collected (owner, its arrays, every token gone)
                      --> FREE: the pool reuses the block by the same rule

The operations are few on purpose (a native core replaces this class without changing its
callers): the pool's ``acquire`` makes a lease; ``open_write`` / ``close_write``, ``seal``,
``mark_read``, ``export``, ``hold``, ``end_publish`` (a loan's pages turn read-only) and
``reclaim`` are its transitions; its collection gives the block back.

**Tokens.** A reader of a re-armable lease (a loan) holds a :class:`Token` from :meth:`Lease.hold`
for as long as anything it made over the bytes lives: the token sits in the base chain of its
NumPy array, in the deleter of its ``wp.array``, in a read handle. The lease keeps weak
references to its tokens: a token's hold ends exactly when the token object is gone (dropped
explicitly or collected), which CPython reports without anyone counting references, and no
finalizer runs. A token keeps the lease, and so the block, alive. A lease that is never re-armed
(a plain buffer) is its own token: holding it keeps the block from the pool, and its bytes are
never written after the seal.

**Exports.** The block's part (:class:`Exports`, a base of every pool block) outlives one owner:
the generation of its current export (started by :meth:`Lease.export`), the peers it was sent to
with their delivery numbers, and the probe that ends the export when no peer can still read it
(the arena's delivery accounting and its write-lock probe on the block's lock range; CUDA
blocks add their readers' last-use events).

Nothing here waits, sleeps or runs on a timer; the lease's finalizer (its give-back) only
appends the block to the pool's lock-free queue, and a collected write handle ends its write
without the lock (:meth:`Lease.end_write_quietly`).
"""

from __future__ import annotations

import threading
import weakref
from typing import Any

from .arena import NO_PEER, SEQ_BITS
from .errors import WriteHandleError

__all__ = [
    "FREE",
    "PUBLISHED",
    "READ",
    "WRITABLE",
    "WRITING",
    "WRITTEN",
    "Exports",
    "Lease",
    "Token",
    "WriteState",
]

FREE, WRITABLE, WRITING, WRITTEN, READ, PUBLISHED = range(6)
_STATE_NAMES = ("free", "writable", "writing", "written", "read", "published")
_new = object.__new__
_ref = weakref.ref
#: Dead token references are dropped once this many are kept (a lease read often, never reclaimed).
_PRUNE_AT = 32


class WriteState:
    """The state of one buffer's (only) write, shared by the lease and its write handle."""

    __slots__ = ("stream", "sealed", "closed")

    def __init__(self, stream: Any) -> None:
        # The CUDA stream the user named for the writes, None for "the current one" (resolved
        # when the write completes: Warp's current stream joined with torch's, see
        # cuda.write_stream); always None on cpu.
        self.stream = stream
        self.sealed: str | None = None  # why writes ended early: "published" or "read"
        self.closed = False  # its handle was collected (the write ended, recorded unlocked)


class Token:
    """A reader's hold on a re-armable lease (see the module docstring). It keeps the lease alive;
    the hold ends when the token is gone. ``release`` is not needed: drop the last reference."""

    __slots__ = ("lease", "__weakref__")


class Exports:
    """The export state of a block (a base of the pool's blocks): ``generation`` of the current
    export (0: not exported since it was last free), ``pending`` maps each peer slot the block
    was sent to onto the delivery sequence of the last descriptor sent with it. ``arena`` and
    ``offset`` name the block's lock range (0: none yet)."""

    arena: Any = None
    offset = 0
    cuda_uses: Any = None  # last-use events of local readers (cuda.BlockUses), CUDA blocks

    def __init__(self) -> None:
        self.arena = None
        self.offset = 0
        self.generation = 0
        self.pending: dict[int, int] = {}

    def ensure_arena_range(self) -> None:
        """Give the block its arena range (host blocks have one from the start)."""

    def try_reclaim(self) -> bool:
        """May the block be written again or freed now? Ends its export if so: every peer it
        was sent to imported it (or a later descriptor: keep-last), or is gone, and no reader in
        another process holds its lock (a write-lock probe). A late import of the retired
        export then finds another generation and is refused as stale."""
        if self.generation == 0:
            return True
        arena = self.arena
        if self.pending and not arena.delivered(self.pending):
            return False  # a descriptor is still on its way to a live peer
        if not arena.try_retire(self.offset):
            return False  # a reader holds it
        self.generation = 0
        self.pending = {}
        return True


class Lease:
    """One owner's use of local memory (see the module docstring).

    ``pool`` gets ``block`` back when the owner is gone (None: nobody to give it back to, a
    private clone's memory or a test's block); ``device`` is the Warp device of the memory;
    ``rearmable``: :meth:`reclaim` may make the bytes writable again (a loan), so readers hold
    tokens of their own.
    """

    __slots__ = ("pool", "block", "device", "on_cpu", "state", "writer", "event", "rearmable",
                 "fence", "write_stream", "_readers", "_lock", "__weakref__")

    def __init__(self, pool: Any, block: Any, device: Any, rearmable: bool = False) -> None:
        self.pool = pool
        self.block = block
        self.device = device
        self.on_cpu = bool(device.is_cpu)
        self.state = WRITABLE
        self.writer: WriteState | None = None  # the open write, if any
        self.event: Any = None  # CUDA: event recorded when the last write completed
        self.rearmable = rearmable
        # What fences a published re-armable lease off from stale writes (a loan's pages, made
        # read-only at end_publish and writable at reclaim; closed before the block goes
        # back): ``protected``, ``protect(writable=False)``, ``close()``. None: nothing does.
        self.fence: Any = None
        # CUDA: the stream a loan's views write on (no handle); the seal records there
        self.write_stream: Any = None
        self._readers: list[weakref.ref[Token]] = []
        self._lock = threading.Lock()

    def __repr__(self) -> str:
        return f"Lease({_STATE_NAMES[self.state]}, block={self.block!r})"

    # -- the owner's end ----------------------------------------------------------------------
    def __call__(self, ptr: int = 0, size: int = 0) -> None:
        """As the ``deleter`` of an array over the memory: nothing to do, the array only keeps
        the lease alive (the block goes back when the lease itself is gone)."""

    def __del__(self) -> None:
        """Owner, arrays and tokens are all gone: FREE. What the lease kept is released first,
        then the block goes back to the pool. No lock (a finalizer: the pool's queue is
        lock-free)."""
        self.state = FREE
        fence, self.fence = self.fence, None
        if fence is not None:
            fence.close()
        if self.pool is not None:
            self.pool._give_back(self.block)

    # -- writing ------------------------------------------------------------------------------
    def open_write(self, stream: Any) -> WriteState:
        """WRITABLE -> WRITING: the buffer's one write handle (``stream``: the CUDA stream the
        user named, None for the current ones). Raises :class:`WriteHandleError` otherwise."""
        with self._lock:
            state = self.state
            if state != WRITABLE:
                raise WriteHandleError(
                    "this buffer was published; it can no longer be written" if state == PUBLISHED
                    else "this buffer was read; it can no longer be written" if state == READ
                    else "a buffer accepts one write handle, ever")
            self.state = WRITING
            self.writer = writer = WriteState(stream)
            return writer

    def close_write(self, writer: WriteState) -> None:
        """WRITING -> WRITTEN: the handle ``writer`` was released; its completion is recorded."""
        with self._lock:
            if self.writer is writer:
                self.writer = None
                if self.state == WRITING:
                    self.state = WRITTEN
                if not writer.closed:
                    self._complete(writer.stream)

    def end_write_quietly(self, writer: WriteState) -> None:
        """The handle ``writer`` was collected (a finalizer, which may run inside any critical
        section): its write ends without the lock. The completion is recorded now (CUDA) and
        the next transition finds the write closed."""
        if writer.closed or writer.sealed is not None or self.writer is not writer:
            return
        writer.closed = True
        self._complete(writer.stream)

    def seal(self) -> None:
        """-> PUBLISHED, once per publish (idempotent; the transport calls it once): an open
        write is ended and its completion recorded. CUDA: an event on the write's stream; for
        bytes written without a handle (a loan's views) on :attr:`write_stream` (None: the
        current streams)."""
        if self.state == PUBLISHED and self.writer is None:
            return  # sealed already: only reclaim (the owner's, never concurrent) changes it
        with self._lock:
            writer, self.writer = self.writer, None
            if writer is not None and not writer.closed:
                writer.sealed = "published"
                self._complete(writer.stream)
            elif self.state == WRITABLE and not self.on_cpu:
                self._complete(self.write_stream)  # written without a handle, or not at all
            self.state = PUBLISHED

    def mark_read(self) -> None:
        """-> READ (a reader took it; a published lease stays PUBLISHED): an open write ends
        (its handle refuses further access), and no write handle opens after this."""
        if self.state >= READ and self.writer is None:
            return
        with self._lock:
            writer, self.writer = self.writer, None
            if writer is not None and not writer.closed:
                writer.sealed = "read"
                self._complete(writer.stream)
            if self.state < READ:
                self.state = READ

    def complete_write(self, stream: Any) -> None:
        """Record that every write enqueued so far on ``stream`` (None: the current streams)
        completed (CUDA; cpu writes are synchronous). Used by copies that write without a
        handle (a clone, a promotion)."""
        with self._lock:
            self._complete(stream)

    def _complete(self, stream: Any) -> None:
        if self.on_cpu:
            return
        from . import cuda

        device = self.device
        stream = cuda.write_stream(device, stream)
        block = self.block
        if block is not None:
            event = block.event
        else:
            import warp as wp

            event = wp.Event(device)
        stream.record_event(event)
        self.event = event

    def order_after_write(self, stream: Any) -> None:
        """Order work on CUDA ``stream`` after the write (an open one, or the recorded one)."""
        if self.on_cpu:
            return
        from . import cuda

        with self._lock:
            writer = self.writer
            if writer is not None and not writer.closed:
                writes = cuda.write_stream(self.device, writer.stream)
                if writes.cuda_stream != stream.cuda_stream:
                    stream.wait_stream(writes)
            elif self.event is not None:
                stream.wait_event(self.event)

    # -- readers ------------------------------------------------------------------------------
    def hold(self) -> Any:
        """A reader's token: a :class:`Token` for a re-armable lease, the lease itself
        otherwise (see the module docstring). Keep it while reading."""
        if not self.rearmable:
            return self
        token = _new(Token)
        token.lease = self
        with self._lock:
            readers = self._readers
            if len(readers) >= _PRUNE_AT:
                readers[:] = [r for r in readers if r() is not None]
            readers.append(_ref(token))
        return token

    def export(self, peer: Any) -> tuple[int, int, int]:
        """Published to a peer: ``(generation, slot, sequence)`` of a descriptor of the block's
        current export for ``peer`` (a :class:`warp_buffer.arena.PeerSlot`; None: no delivery
        accounting, slot ``NO_PEER``). The block now waits for that peer's delivery. Raises
        OSError when the block gets no lock range (a CUDA block in a full arena)."""
        block = self.block
        with self._lock:
            generation = block.generation
            if not generation:  # the first export since the block was free: a new generation
                if block.arena is None:
                    block.ensure_arena_range()
                generation = block.generation = block.arena.new_generation(block.offset,
                                                                            block.capacity)
            if peer is None:
                return generation, NO_PEER, 0
            number = next(peer.numbers)  # atomic under the GIL, unlike += on an attribute
            if number > peer.issued:
                peer.issued = number
            slot, sequence = peer.index, peer.epoch << SEQ_BITS | number
            block.pending[slot] = sequence
            return generation, slot, sequence

    def end_publish(self) -> None:
        """Every route of the publish sent the message: the fence goes up (a loan's pages turn
        read-only in this process), off the path a reader waits on."""
        fence = self.fence
        if fence is None or fence.protected:
            return
        with self._lock:
            if self.state == PUBLISHED and not fence.protected:
                fence.protect()

    # -- reuse --------------------------------------------------------------------------------
    def reclaim(self) -> bool:
        """SEALED -> WRITABLE when nobody can read the bytes any more: no token alive, and the
        block's export retired (:meth:`Exports.try_reclaim`); the fence comes down. False while
        held (nothing changes). A lease never sealed is writable already (True)."""
        with self._lock:
            for ref in self._readers:
                if ref() is not None:
                    return False
            self._readers.clear()
            block = self.block
            if block is not None and not block.try_reclaim():
                return False
            fence = self.fence
            if fence is not None and fence.protected:
                fence.protect(writable=True)
            self.state, self.writer, self.event, self.write_stream = WRITABLE, None, None, None
            return True

    def adopt(self, block: Any, pool: Any) -> None:
        """Private memory moved into ``block`` of ``pool`` (a clone's first export); the lease
        now gives the block back when its owner is gone."""
        with self._lock:
            self.block, self.pool = block, pool

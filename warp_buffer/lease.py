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

The state machine is native (:mod:`warp_buffer._core`: ``Lease``, ``Token``, ``Exports``): the
pool's ``acquire`` makes a lease; ``open_write`` / ``close_write``, ``seal``, ``mark_read``,
``export``, ``hold``, ``end_publish`` (a loan's pages turn read-only) and ``reclaim`` are its
transitions, each one C call under the lease's one lock; its collection gives the block back.
This module keeps what is Python's: the write handle's state, and the CUDA work the transitions
ask for (events recorded on streams), which the lease calls with its lock held.

**Tokens.** A reader of a re-armable lease (a loan) holds a :class:`Token` from :meth:`Lease.hold`
for as long as anything it made over the bytes lives: the token sits in the base chain of its
NumPy array, in the deleter of its ``wp.array``, in a read handle. The lease counts its tokens: a
token's hold ends exactly when the token object is gone (dropped explicitly or collected), one
decrement in C, no weak reference and no finalizer. A token keeps the lease, and so the block,
alive. A lease that is never re-armed (a plain buffer) is its own token: holding it keeps the
block from the pool, and its bytes are never written after the seal.

**Exports.** The block's part (:class:`Exports`, a base of every pool block) outlives one owner:
the generation of its current export (started by :meth:`Lease.export`), the peers it was sent to
with their delivery numbers, and the probe that ends the export when no peer can still read it
(the arena's delivery accounting and its write-lock probe on the block's lock range,
:class:`warp_buffer._core.ArenaCore`; CUDA blocks add their readers' last-use events).

Nothing here waits, sleeps or runs on a timer; the lease's finalizer (its give-back) only
appends the block to the pool's lock-free queue, and a collected write handle ends its write
without the lock (:meth:`Lease.end_write_quietly`).
"""

from __future__ import annotations

from typing import Any

from .descriptor import _core
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

FREE, WRITABLE, WRITING, WRITTEN, READ, PUBLISHED = (
    _core.FREE, _core.WRITABLE, _core.WRITING, _core.WRITTEN, _core.READ, _core.PUBLISHED)

#: ``Lease(pool, block, device, rearmable=False)``: ``pool`` gets ``block`` back when the owner
#: is gone (None: nobody to give it back to, a private clone's memory or a test's block);
#: ``device`` is the Warp device of the memory; ``rearmable``: ``reclaim`` may make the bytes
#: writable again (a loan), so readers hold tokens of their own.
Lease = _core.Lease
#: A reader's hold on a re-armable lease (see the module docstring).
Token = _core.Token
#: The export state of a block (a base of the pool's blocks): ``generation`` of the current
#: export (0: not exported since it was last free), ``pending`` (peer slot -> the delivery
#: sequence of the last descriptor sent with it), ``arena`` and ``offset`` (the block's lock
#: range), ``cuda_uses``; ``try_reclaim()`` ends the export once no peer can still read it.
Exports = _core.Exports


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


def _complete(lease: Any, stream: Any) -> None:
    """Record the completion of the writes enqueued on ``stream`` (None: the current streams)
    on the block's event (CUDA; the lease calls this with its lock held, never on cpu)."""
    from . import cuda

    device = lease.device
    stream = cuda.write_stream(device, stream)
    block = lease.block
    if block is not None:
        event = block.event
    else:
        import warp as wp

        event = wp.Event(device)
    stream.record_event(event)
    lease.event = event


def _order_after_write(lease: Any, stream: Any) -> None:
    """Order work on CUDA ``stream`` after the write (an open one, or the recorded one); the
    lease calls this with its lock held."""
    from . import cuda

    writer = lease.writer
    if writer is not None and not writer.closed:
        writes = cuda.write_stream(lease.device, writer.stream)
        if writes.cuda_stream != stream.cuda_stream:
            stream.wait_stream(writes)
    elif lease.event is not None:
        stream.wait_event(lease.event)


_core.configure(WriteState, _complete, _order_after_write, WriteHandleError)

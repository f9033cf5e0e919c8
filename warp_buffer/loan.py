"""Warp buffers a publisher loans again and again (``Publisher.loan`` in ``buffer_pubsub``).

A loaned buffer keeps its pool block for its whole life: each loan fills it in place, publish
seals it, and :meth:`LoanedBufferImpl.reclaim` re-arms it for the next loan once nobody can read
it: its lease (:mod:`warp_buffer.lease`) is re-armable, so readers in this process hold tokens
of their own, and it is re-armed when no token is alive and the block's export retired (every
peer it was sent to imported it or a later descriptor, or is gone, and no reader's lock is
held): the same rule the pool applies before reusing a block.

Stale writes are refused by the memory itself on Warp's ``cpu`` device: between publish and the
next loan of the block its pages are read-only in the publisher (``mprotect``), so writing
through a view kept past ``publish()`` (a torch tensor, a NumPy array, a ``wp.array``) faults
(SIGSEGV) instead of silently changing what zero-copy subscribers read. The pages are writable
again when the block is re-loaned and when it goes back to the pool. Blocks whose start is not
page-aligned (never the case for the arena) and CUDA memory are not protected: there, a view
kept past publish must not be written (documented on ``loan``).

The pages are the lease's fence: they turn read-only at :meth:`LoanedBufferImpl.end_publish`,
which the publisher calls once every route has sent the message (still inside ``publish()``), so
the call is not on the path a reader waits on, and writable again when the lease is re-armed. The protection costs two ``mprotect`` calls per loan, on the pages the buffer's
bytes cover (not the whole block). They act on the loan's own mapping of its block (a *window*:
one more ``mmap`` of the arena's memfd at the block's offset, made once per pooled buffer,
unmapped when the buffer and its arrays are gone): every view, the impl's own arrays included,
is built over it, so mprotect neither splits nor merges the arena's large mapping: 1.7 us a
call instead of 3.4 in a hot loop here. In a publisher that sleeps between frames, making the
pages writable again at the next loan still costs 6-10 us, whatever the mapping: the kernel's
work after the thread slept, not ours. Readers in other processes map the arena themselves and never see the
window.
``WARP_BUFFER_LOAN_PROTECT=0`` turns it off for buffers allocated afterwards (no window then); a
write through a stale view then changes what zero-copy readers see, as with any shared memory.
"""

from __future__ import annotations

import mmap
from typing import Any

from rosidl_buffer import Buffer
from rosidl_buffer.buffer_impl import array_at

from . import memory
from ._env import env_flag
from .descriptor import _core
from .buffer_impl import WarpBufferImpl, wrap_bytes

__all__ = ["LoanedBufferImpl", "loan_buffer", "protection_enabled"]

_PAGE = mmap.PAGESIZE
#: The pages a loan protects, the lease's fence (:attr:`warp_buffer.lease.Lease.fence`), native:
#: ``Fence(addr, nbytes, window)``, ``protect(writable=False)`` (an ``mprotect``), ``close()``
#: (before the block goes back to the pool: writable whatever the last loan left; a window is
#: unmapped), ``protected``.
_Fence = _core.Fence


def protection_enabled() -> bool:
    """``WARP_BUFFER_LOAN_PROTECT`` (default on): loaned host blocks are read-only between
    publish and their next loan."""
    return env_flag("WARP_BUFFER_LOAN_PROTECT", True)


def _protected_pages(block: Any, nbytes: int) -> Any:
    """The pages of a new loaned host buffer to protect: a window onto its arena block, else
    (private memory, or no mapping left) the block's own pages; None when the block does not
    start on a page."""
    if block.data_ptr % _PAGE:
        return None
    length = -(-nbytes // _PAGE) * _PAGE  # the pages the bytes cover, no more
    if block.shared:
        try:
            return _Fence(memory.map_fd(block.arena.fd, length, block.offset), length, True)
        except OSError:  # vm.max_map_count reached: protect the arena's pages themselves
            pass
    return _Fence(block.data_ptr, length, False)


class LoanedBufferImpl(WarpBufferImpl):
    """A :class:`WarpBufferImpl` that can be written again after it was published, once
    :meth:`reclaim` found nobody able to read it (see the module docstring).

    Its ``seal``, ``end_publish`` and ``reclaim`` are its lease's transitions themselves (bound
    on the instance, one call less per loan than forwarding methods)."""

    _pages: Any = None  # the lease's fence (a host block, protection on)

    @classmethod
    def allocate(cls, nbytes: int, device: Any = None,  # type: ignore[override]
                 rearmable: bool = True) -> LoanedBufferImpl:
        impl = super().allocate(nbytes, device, rearmable=True)
        assert isinstance(impl, LoanedBufferImpl)
        lease = impl.lease
        impl.seal, impl.end_publish, impl.reclaim = (  # type: ignore[method-assign]
            lease.seal, lease.end_publish, lease.reclaim)  # type: ignore[union-attr]
        if impl.host is None or not protection_enabled():
            return impl
        pages = _protected_pages(impl.block, nbytes)
        if pages is not None:
            impl._pages = lease.fence = pages  # type: ignore[union-attr]
            if pages.window:  # the impl's storage is the window now: its arrays and every
                impl.data_ptr = pages.addr  # view over them are protected with it
                impl.host = array_at(pages.addr, nbytes)
        return impl

    def seal(self) -> None:
        """End the write (publish; CUDA: record the write's completion on the stream the loan's
        views write on). The pages turn read-only at :meth:`end_publish`."""
        self.lease.seal()  # type: ignore[union-attr]

    def end_publish(self) -> None:
        """The message left on every route: make the pages read-only in this process now. The
        publisher's thread is still inside ``publish()``, so no write of its own comes between,
        and the ``mprotect`` (6-10 us after a sleep) runs while readers already wake."""
        self.lease.end_publish()  # type: ignore[union-attr]

    def reclaim(self) -> bool:
        """Re-arm for the next loan if nobody can read the block (see the module docstring):
        writable again, one write handle allowed, not published. False while held."""
        return self.lease.reclaim()  # type: ignore[union-attr]

    @property
    def array(self) -> Any:
        """The storage as a 1-D uint8 ``wp.array`` that holds a reader's token (a new one per
        call): the loan is not re-armed while it, or a view of it, lives."""
        owner = self.wp_array
        return wrap_bytes(owner.ptr, self.nbytes, self.wp_device, self.lease.hold())  # type: ignore[union-attr]

    def write_on(self, stream: Any) -> None:
        """CUDA: this loan's views write on ``stream`` (a ``wp.Stream``); publish records the
        write's completion there. A second stream is ordered after the first."""
        lease = self.lease
        current = lease.write_stream  # type: ignore[union-attr]
        if current is not None and current is not stream:
            stream.wait_stream(current)
        lease.write_stream = stream  # type: ignore[union-attr]

    @property
    def is_protected(self) -> bool:
        """The pages are read-only in this process now (published, not yet re-loaned)."""
        pages = self._pages
        return pages is not None and pages.protected


def loan_buffer(nbytes: int, device: Any = None) -> Buffer:
    """A warp-backed :class:`~rosidl_buffer.Buffer` of ``nbytes`` for a publisher's loans."""
    return Buffer(LoanedBufferImpl.allocate(int(nbytes), device))

"""Warp buffers a publisher loans again and again (``Publisher.loan`` in ``buffer_pubsub``).

A loaned buffer keeps its pool block for its whole life: each loan fills it in place, publish
seals it, and :meth:`LoanedBufferImpl.reclaim` re-arms it for the next loan once no reader
holds it (the same rule the pool applies before reusing a block: every peer it was sent to
imported it or a later descriptor, and no reader's lock is held).

Stale writes are refused by the memory itself on Warp's ``cpu`` device: between publish and the
next loan of the block its pages are read-only in the publisher (``mprotect``), so writing
through a view kept past ``publish()`` (a torch tensor, a NumPy array, a ``wp.array``) faults
(SIGSEGV) instead of silently changing what zero-copy subscribers read. The pages are writable
again when the block is re-loaned and when it goes back to the pool. Blocks whose start is not
page-aligned (never the case for the arena) and CUDA memory are not protected: there, a view
kept past publish must not be written (documented on ``loan``).

The pages turn read-only at :meth:`LoanedBufferImpl.end_publish`, which the publisher calls once
every route has sent the message (still inside ``publish()``), so the call is not on the path a
reader waits on. The protection costs two ``mprotect`` calls per loan, on the pages the buffer's
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

import ctypes
import mmap
import os
import sys
from typing import Any

from rosidl_buffer import Buffer

from . import memory
from ._env import env_flag
from .arena import host_view
from .buffer_impl import WarpBufferImpl

__all__ = ["LoanedBufferImpl", "loan_buffer", "protection_enabled"]

_PAGE = mmap.PAGESIZE
_OWN_ARRAY_REFS = 3  # self._arr, the local name in _array_in_use, getrefcount's argument
_libc = ctypes.CDLL(None, use_errno=True)
_libc.mprotect.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)


def protection_enabled() -> bool:
    """``WARP_BUFFER_LOAN_PROTECT`` (default on): loaned host blocks are read-only between
    publish and their next loan."""
    return env_flag("WARP_BUFFER_LOAN_PROTECT", True)


def _protect(ptr: int, nbytes: int, writable: bool) -> None:
    prot = mmap.PROT_READ | (mmap.PROT_WRITE if writable else 0)
    if _libc.mprotect(ptr, nbytes, prot) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, f"mprotect of a loaned block failed: {os.strerror(errno)}")


class _Pages:
    """The pages a loan protects, and the owner of its lease (the deleter of the impl's array):
    when the impl and every array over it are gone the block goes back to the pool, writable,
    whatever the last loan left: a window is unmapped (the arena's own mapping was never
    protected), a block protected in place is made writable again."""

    __slots__ = ("lease", "addr", "nbytes", "window", "__weakref__")

    def __init__(self, lease: Any, addr: int, nbytes: int, window: bool) -> None:
        self.lease, self.addr, self.nbytes, self.window = lease, addr, nbytes, window

    def __call__(self, ptr: int = 0, size: int = 0) -> None:
        lease, self.lease = self.lease, None
        if lease is not None:
            if self.window:
                memory.unmap(self.addr, self.nbytes)
            else:
                _protect(self.addr, self.nbytes, True)
            lease()

    def __del__(self) -> None:
        self()


def _protected_pages(block: Any, nbytes: int, lease: Any) -> _Pages | None:
    """The pages of a new loaned host buffer to protect: a window onto its arena block, else
    (private memory, or no mapping left) the block's own pages; None when the block does not
    start on a page."""
    if block.data_ptr % _PAGE:
        return None
    length = -(-nbytes // _PAGE) * _PAGE  # the pages the bytes cover, no more
    if block.shared:
        try:
            return _Pages(lease, memory.map_fd(block.arena.fd, length, block.offset), length,
                          window=True)
        except OSError:  # vm.max_map_count reached: protect the arena's pages themselves
            pass
    return _Pages(lease, block.data_ptr, length, window=False)


class LoanedBufferImpl(WarpBufferImpl):
    """A :class:`WarpBufferImpl` that can be written again after it was published, once
    :meth:`reclaim` found no reader holding it (see the module docstring)."""

    _protected = False  # pages read-only now
    _pages: _Pages | None = None  # what seal protects (a host block, protection on)
    _write_stream: Any = None  # CUDA: the stream this loan's views write on

    @classmethod
    def allocate(cls, nbytes: int, device: Any = None) -> LoanedBufferImpl:
        impl = super().allocate(nbytes, device)
        assert isinstance(impl, LoanedBufferImpl)
        if impl._host is None or not protection_enabled():
            return impl
        pages = _protected_pages(impl._block, nbytes, impl._owner)
        if pages is not None:
            impl._pages = impl._owner = pages
            if pages.window:  # the impl's storage is the window now: its arrays and every
                impl._ptr = pages.addr  # view over them are protected with it
                impl._host = host_view(pages.addr, nbytes)
        return impl

    def seal(self) -> None:
        """End the write (publish; CUDA: record the write's completion on the stream the loan's
        views write on). The pages turn read-only at :meth:`end_publish`."""
        if self._sealed_host():
            return  # sealed already (every route seals; the first one did the work)
        with self._lock:
            if self._writer is None and self._host is None:
                # CUDA: the loan's views write without a handle; order readers after the work
                # queued on the stream they write on (write_on), else Warp's current stream
                self._complete_write(self._write_stream)
            self._mark_published()

    def end_publish(self) -> None:
        """The message left on every route: make the pages read-only in this process now. The
        publisher's thread is still inside ``publish()``, so no write of its own comes between,
        and the ``mprotect`` (6-10 us after a sleep) runs while readers already wake."""
        pages = self._pages
        if pages is None or self._protected:
            return
        with self._lock:
            if self._published and not self._protected:
                _protect(pages.addr, pages.nbytes, False)
                self._protected = True

    def reclaim(self) -> bool:
        """Re-arm for the next loan if no reader holds the block (see the module docstring):
        writable again, one write handle allowed, not published. False while held."""
        with self._lock:
            if self._released or self._array_in_use() or not self._block.try_reclaim():
                return False
            if self._protected:
                pages = self._pages
                _protect(pages.addr, pages.nbytes, True)  # type: ignore[union-attr]
                self._protected = False
            self._writer = self._event = self._write_stream = None
            self._write_opened = self._published = self._read = False
            return True

    def _array_in_use(self) -> bool:
        """Host memory: is the impl's own ``wp.array`` referenced beyond the impl (a view of a
        ``warp_buffer`` handle, ``impl.array`` kept by an in-process reader)? Those views hold
        neither the message nor its ``Buffer``, whose references the loan pool counts."""
        array = self._arr
        return (array is not None and self._host is not None
                and sys.getrefcount(array) > _OWN_ARRAY_REFS)

    def write_on(self, stream: Any) -> None:
        """CUDA: this loan's views write on ``stream`` (a ``wp.Stream``); publish records the
        write's completion there. A second stream is ordered after the first."""
        with self._lock:
            current = self._write_stream
            if current is not None and current is not stream:
                stream.wait_stream(current)
            self._write_stream = stream

    @property
    def is_protected(self) -> bool:
        """The pages are read-only in this process now (published, not yet re-loaned)."""
        return self._protected


def loan_buffer(nbytes: int, device: Any = None) -> Buffer:
    """A warp-backed :class:`~rosidl_buffer.Buffer` of ``nbytes`` for a publisher's loans."""
    return Buffer(LoanedBufferImpl.allocate(int(nbytes), device))

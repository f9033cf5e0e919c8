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

The protection costs two ``mprotect`` calls per loan (a few us each, more on a loaded machine:
the kernel splits and merges the mapping and flushes other cores' TLBs).
``WARP_BUFFER_LOAN_PROTECT=0`` turns it off for buffers allocated afterwards; a write through
a stale view then changes what zero-copy readers see, as with any shared memory.
"""

from __future__ import annotations

import ctypes
import mmap
import os
from typing import Any

from rosidl_buffer import Buffer

from .buffer_impl import WarpBufferImpl

__all__ = ["LoanedBufferImpl", "loan_buffer", "protection_enabled"]

_PAGE = mmap.PAGESIZE
_libc = ctypes.CDLL(None, use_errno=True)
_libc.mprotect.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)


def protection_enabled() -> bool:
    """``WARP_BUFFER_LOAN_PROTECT`` (default on): loaned host blocks are read-only between
    publish and their next loan."""
    value = os.environ.get("WARP_BUFFER_LOAN_PROTECT", "1").strip().lower()
    return value not in ("0", "false", "no", "off")


def _protect(ptr: int, nbytes: int, writable: bool) -> None:
    prot = mmap.PROT_READ | (mmap.PROT_WRITE if writable else 0)
    if _libc.mprotect(ptr, nbytes, prot) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, f"mprotect of a loaned block failed: {os.strerror(errno)}")


class _WritableOnReturn:
    """Deleter of a protected block's array (and owner of its lease): the block goes back to
    the pool writable, whatever state the last loan left it in."""

    __slots__ = ("lease", "ptr", "nbytes", "__weakref__")

    def __init__(self, lease: Any, ptr: int, nbytes: int) -> None:
        self.lease, self.ptr, self.nbytes = lease, ptr, nbytes

    def __call__(self, ptr: int = 0, size: int = 0) -> None:
        lease, self.lease = self.lease, None
        if lease is not None:
            _protect(self.ptr, self.nbytes, True)
            lease()

    def __del__(self) -> None:
        self()


class LoanedBufferImpl(WarpBufferImpl):
    """A :class:`WarpBufferImpl` that can be written again after it was published, once
    :meth:`reclaim` found no reader holding it (see the module docstring)."""

    _protected = False  # pages read-only now
    _protectable = False  # a page-aligned host block
    _write_stream: Any = None  # CUDA: the stream this loan's views write on

    @classmethod
    def allocate(cls, nbytes: int, device: Any = None) -> LoanedBufferImpl:
        impl = super().allocate(nbytes, device)
        assert isinstance(impl, LoanedBufferImpl)
        block = impl._block
        if impl._host is not None and block.data_ptr % _PAGE == 0 and protection_enabled():
            impl._protectable = True
            impl._owner = _WritableOnReturn(impl._owner, block.data_ptr, block.capacity)
        return impl

    def seal(self) -> None:
        """End the write (publish) and make the pages read-only in this process (CUDA: record
        the write's completion on the device's current stream)."""
        with self._lock:
            if self._writer is None and self._host is None:
                # CUDA: the loan's views write without a handle; order readers after the work
                # queued on the stream they write on (write_on), else Warp's current stream
                self._complete_write(self._write_stream)
            self._mark_published()
            if self._protectable and not self._protected:
                _protect(self._block.data_ptr, self._block.capacity, False)
                self._protected = True

    def reclaim(self) -> bool:
        """Re-arm for the next loan if no reader holds the block (see the module docstring):
        writable again, one write handle allowed, not published. False while held."""
        with self._lock:
            if self._released or not self._block.try_reclaim():
                return False
            if self._protected:
                _protect(self._block.data_ptr, self._block.capacity, True)
                self._protected = False
            self._writer = self._event = self._write_stream = None
            self._write_opened = self._published = self._read = False
            return True

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

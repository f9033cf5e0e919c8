"""Raw memory primitives of the IPC core: libc ``mmap``/``munmap``, hole punching, and the
open-file-description (OFD) byte-range locks that are a reader's hold on a block.

Raw libc mappings rather than :mod:`mmap`, so an address can be wrapped by Warp and NumPy and
unmapped deterministically, with no Python buffer export pinning it.

Why OFD locks (``F_OFD_SETLK``): they belong to an open file description, are released by the
kernel when the last fd of that description closes (a reader's death included), and two
descriptions conflict even inside one process. An fd received over ``SCM_RIGHTS`` *shares* the
sender's description, so an importer re-opens the arena through ``/proc/self/fd`` to get its own
(:func:`reopen`) before it locks anything.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import mmap
import os
import struct

__all__ = ["map_fd", "unmap", "punch_hole", "reopen", "try_lock", "unlock", "LockBusy"]

_libc = ctypes.CDLL(None, use_errno=True)
_libc.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.c_int,
                       ctypes.c_int64]
_libc.mmap.restype = ctypes.c_void_p
_libc.munmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
_libc.munmap.restype = ctypes.c_int
_libc.fallocate.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int64, ctypes.c_int64]
_libc.fallocate.restype = ctypes.c_int
_MAP_FAILED = ctypes.c_void_p(-1).value
_MAP_NORESERVE = 0x4000
_FALLOC_FL_KEEP_SIZE = 0x01
_FALLOC_FL_PUNCH_HOLE = 0x02

# fcntl commands and struct flock (x86-64 / aarch64 layout: two shorts, two off_t, a pid_t).
F_OFD_SETLK = getattr(fcntl, "F_OFD_SETLK", 37)
_FLOCK = struct.Struct("hh4xqqi4x")
#: ``lock_request(kind, whence, offset, length, 0)``: the ``struct flock`` bytes of an OFD lock
#: request, for callers that make the one ``fcntl`` call a hold costs inline (:func:`try_lock`).
lock_request = _FLOCK.pack
BUSY = (errno.EAGAIN, errno.EACCES)  # what a conflicting lock fails with


class LockBusy(Exception):
    """A non-blocking lock request met a conflicting lock (internal: callers translate it)."""


def map_fd(fd: int, length: int, offset: int = 0, *, writable: bool = True) -> int:
    """``mmap`` ``length`` bytes of ``fd`` at ``offset`` (page aligned), shared; returns the
    address. ``MAP_NORESERVE``: a large arena costs address space, not commit charge."""
    prot = mmap.PROT_READ | (mmap.PROT_WRITE if writable else 0)
    addr = _libc.mmap(None, length, prot, mmap.MAP_SHARED | _MAP_NORESERVE, fd, offset)
    if addr is None or addr == _MAP_FAILED:
        err = ctypes.get_errno()
        raise OSError(err, f"mmap of {length} bytes failed: {os.strerror(err)}")
    return addr


def unmap(addr: int, length: int) -> None:
    if _libc.munmap(addr, length) != 0:  # pragma: no cover - only on a bad address
        err = ctypes.get_errno()
        raise OSError(err, os.strerror(err))


def punch_hole(fd: int, offset: int, length: int) -> None:
    """Give the pages of ``[offset, offset+length)`` back to the system; the file keeps its size
    (allowed under ``F_SEAL_SHRINK | F_SEAL_GROW``), later reads see zeros."""
    if _libc.fallocate(fd, _FALLOC_FL_PUNCH_HOLE | _FALLOC_FL_KEEP_SIZE, offset, length) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"fallocate(PUNCH_HOLE) failed: {os.strerror(err)}")


def reopen(fd: int) -> int:
    """A new open file description of the file behind ``fd`` (its own OFD locks)."""
    return os.open(f"/proc/self/fd/{fd}", os.O_RDWR | os.O_CLOEXEC)


def try_lock(fd: int, offset: int, exclusive: bool, length: int = 1) -> None:
    """Take a read (shared) or write (exclusive) lock on ``length`` bytes at ``offset`` of
    ``fd``'s description, without waiting; raises :class:`LockBusy` when a conflicting lock is
    held."""
    kind = fcntl.F_WRLCK if exclusive else fcntl.F_RDLCK
    try:
        fcntl.fcntl(fd, F_OFD_SETLK, _FLOCK.pack(kind, os.SEEK_SET, offset, length, 0))
    except OSError as exc:
        if exc.errno in BUSY:
            raise LockBusy from None
        raise


def unlock(fd: int, offset: int, length: int = 1) -> None:
    fcntl.fcntl(fd, F_OFD_SETLK, _FLOCK.pack(fcntl.F_UNLCK, os.SEEK_SET, offset, length, 0))

"""Raw memory primitives of the IPC core: libc ``mmap``/``munmap``, hole punching, and the open
file descriptions whose byte-range locks (OFD) are a reader's hold on a block (taken by the
native core, :mod:`warp_buffer._core`).

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
import mmap
import os

__all__ = ["map_fd", "unmap", "punch_hole", "reopen"]

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

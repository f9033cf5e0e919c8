"""Who holds a bag: an exclusive ``flock`` on its directory.

The recorder's writer holds it from creating the bag until it is finalized; ``bag reindex``
holds it while it repairs one, and refuses a bag it cannot get (still being recorded). The
kernel drops the lock when the holding process ends, however it ends: nothing is left behind.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from collections.abc import Iterator

__all__ = ["BagBusyError", "lock_directory", "locked_bag"]


class BagBusyError(OSError):
    """Another process holds the bag's directory (it records it, or reindexes it)."""


def lock_directory(path: str | os.PathLike[str]) -> int:
    """An open descriptor of directory ``path`` holding its exclusive ``flock`` (close it to
    let go); :class:`BagBusyError` if another holder has it."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise BagBusyError(f"{os.fspath(path)} is held by another process "
                           "(a recording still running?)") from None
    except BaseException:
        os.close(fd)
        raise
    return fd


@contextlib.contextmanager
def locked_bag(path: str | os.PathLike[str]) -> Iterator[None]:
    """Hold the bag directory ``path`` for the block (:class:`BagBusyError` if taken)."""
    fd = lock_directory(path)
    try:
        yield
    finally:
        os.close(fd)

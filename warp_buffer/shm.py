"""Shared-memory files under ``/dev/shm``: names, block headers, sessions, locks and the sweep.

Layout
------
Every file lives under the per-user prefix ``/dev/shm/warp_buffer.<uid>.`` (:func:`shm_prefix`),
is created with ``O_EXCL | O_NOFOLLOW`` and mode 0600, and is named by numbers only::

    warp_buffer.<uid>.<pid>-<session:016x>.lock      held LOCK_EX by its owner for its life
    warp_buffer.<uid>.<pid>-<session:016x>.b<block>  a block: a 4 KiB header, then the data

A *session* is one owner process's set of files; ``session`` is 64 random bits drawn when the
session starts, so names cannot be guessed and a recycled pid never matches an old session. An
importer rebuilds a name from the numbers a descriptor carries and its own prefix: it never opens a
path a peer chose.

Holds and liveness (all released by the kernel when a process dies, no timers)
-----------------------------------------------------------------------------
- A reader holds a block with ``flock(LOCK_SH)`` on the block file; the owner recycles or frees a
  block only after it takes ``LOCK_EX | LOCK_NB``, so never while a reader holds it. A reader that
  meets a block being recycled (its ``LOCK_SH | LOCK_NB`` fails) gets :class:`StaleBufferError`.
- The owner holds ``LOCK_EX`` on its session lock file. :func:`sweep_orphans` removes the files of
  sessions whose lock it can take, i.e. whose owner died (SIGKILL included).

Header (little endian, :class:`BlockHeader`): magic, version, header size, the export ``uid`` (0
when not exported), the writer's ``generation`` stamp, the data ``capacity``, ``session``, owner
pid, block id, kind, and 64 acknowledgement bytes, one per descriptor issued for the current uid.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import logging
import mmap
import os
import re
import secrets
import stat
import threading
import time
from dataclasses import dataclass

from .errors import ForeignExportError, StaleBufferError

__all__ = [
    "SHM_DIR",
    "HEADER_SIZE",
    "ACK_SLOTS",
    "NO_ACK_SLOT",
    "BlockHeader",
    "ExportFile",
    "Session",
    "current_session",
    "shm_prefix",
    "list_exports",
    "sweep_orphans",
    "map_fd",
    "unmap",
]

_log = logging.getLogger(__name__)

SHM_DIR = "/dev/shm"
NAME_STEM = "warp_buffer"
HEADER_SIZE = 4096
MAGIC = b"WARPBUF\x01"
HEADER_VERSION = 1
ACK_SLOTS = 64
NO_ACK_SLOT = 0xFFFF
#: A session lock (or a block without one) this old whose lock is free belongs to a dead owner
#: even when its pid was reused by an unrelated process.
ORPHAN_MIN_AGE_S = 5.0

KIND_HOST_DATA = 0  # header + data in the file
KIND_HEADER_ONLY = 1  # header only (the data is CUDA memory shared by a CUDA IPC handle)


class BlockHeader(ctypes.Structure):
    """The first bytes of every block file (the rest of the 4 KiB header page is reserved)."""

    _pack_ = 8
    _fields_ = [
        ("magic", ctypes.c_char * 8),
        ("version", ctypes.c_uint32),
        ("header_size", ctypes.c_uint32),
        ("uid", ctypes.c_uint64),
        ("generation", ctypes.c_uint64),
        ("capacity", ctypes.c_uint64),
        ("session", ctypes.c_uint64),
        ("owner_pid", ctypes.c_uint32),
        ("block_id", ctypes.c_uint32),
        ("kind", ctypes.c_uint32),
        ("reserved", ctypes.c_uint32),
        ("acks", ctypes.c_uint8 * ACK_SLOTS),
    ]


GENERATION_OFFSET = BlockHeader.generation.offset
assert ctypes.sizeof(BlockHeader) <= HEADER_SIZE

# -------------------------------------------------------------------------------- raw mmap
_libc = ctypes.CDLL(None, use_errno=True)
_libc.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.c_int,
                       ctypes.c_int64]
_libc.mmap.restype = ctypes.c_void_p
_libc.munmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
_libc.munmap.restype = ctypes.c_int
_MAP_FAILED = ctypes.c_void_p(-1).value


def map_fd(fd: int, length: int, offset: int = 0, *, writable: bool = True,
           private: bool = False) -> int:
    """``mmap`` ``length`` bytes of ``fd`` at ``offset`` (page aligned); returns the address.

    Raw libc mapping rather than :mod:`mmap` so the address can be wrapped by Warp and NumPy and
    unmapped deterministically, with no Python buffer exports pinning it.
    """
    prot = mmap.PROT_READ | (mmap.PROT_WRITE if writable else 0)
    flags = mmap.MAP_PRIVATE if private else mmap.MAP_SHARED
    addr = _libc.mmap(None, length, prot, flags, fd, offset)
    if addr is None or addr == _MAP_FAILED:
        err = ctypes.get_errno()
        raise OSError(err, f"mmap of {length} bytes failed: {os.strerror(err)}")
    return addr


def unmap(addr: int, length: int) -> None:
    if _libc.munmap(addr, length) != 0:  # pragma: no cover - only on a bad address
        err = ctypes.get_errno()
        raise OSError(err, os.strerror(err))


# -------------------------------------------------------------------------------- names
def shm_prefix(uid: int | None = None) -> str:
    """Path prefix of every shared-memory file of this user: ``/dev/shm/warp_buffer.<uid>.``."""
    return f"{SHM_DIR}/{NAME_STEM}.{os.getuid() if uid is None else uid}."


_NAME_RE = re.compile(
    r"^" + re.escape(NAME_STEM) + r"\.(\d+)\.(\d+)-([0-9a-f]{16})\.(lock|b(\d+))$"
)


def session_token(pid: int, session: int) -> str:
    return f"{pid}-{session:016x}"


def block_path(pid: int, session: int, block_id: int) -> str:
    """The one path a (pid, session, block id) can name, under this user's prefix."""
    return f"{shm_prefix()}{session_token(pid, session)}.b{block_id}"


def lock_path(pid: int, session: int) -> str:
    return f"{shm_prefix()}{session_token(pid, session)}.lock"


@dataclass(frozen=True)
class ExportFile:
    """One file under this user's prefix, as :func:`list_exports` reports it."""

    path: str
    owner_pid: int
    session: int
    block_id: int | None  # None for a session lock file
    nbytes: int

    @property
    def is_lock(self) -> bool:
        return self.block_id is None


def _scan(uid: int) -> list[ExportFile]:
    found = []
    try:
        names = os.listdir(SHM_DIR)
    except OSError:
        return found
    for name in names:
        match = _NAME_RE.match(name)
        if match is None or int(match.group(1)) != uid:
            continue
        path = f"{SHM_DIR}/{name}"
        try:
            st = os.lstat(path)
        except FileNotFoundError:
            continue
        if st.st_uid != uid or not stat.S_ISREG(st.st_mode):
            continue
        block = match.group(5)
        found.append(ExportFile(path, int(match.group(2)), int(match.group(3), 16),
                                None if block is None else int(block), st.st_size))
    found.sort(key=lambda f: f.path)
    return found


def list_exports(pid: int | None = None) -> list[ExportFile]:
    """Every shared-memory file of this user (block files and session locks), optionally only
    those of owner ``pid``. A leak check expects none from dead processes, and none at all once
    every process of the library exited cleanly."""
    files = _scan(os.getuid())
    return files if pid is None else [f for f in files if f.owner_pid == pid]


def pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_orphans() -> list[str]:
    """Remove the files of sessions whose owner process died; returns the removed paths.

    A session is dead when its lock file can be locked (the kernel dropped the owner's lock when
    it died) and its pid is gone or the lock is older than a few seconds (a recycled pid); files
    of a session without a lock file are judged by pid and age the same way. Readers that still
    map a removed block keep their mapping: unlinking only removes the name.
    """
    uid = os.getuid()
    own = _session.token if _session is not None else None
    by_session: dict[str, list[ExportFile]] = {}
    for f in _scan(uid):
        by_session.setdefault(session_token(f.owner_pid, f.session), []).append(f)
    removed: list[str] = []
    now = time.time()
    for token, files in by_session.items():
        if token == own:
            continue
        pid = files[0].owner_pid
        lock = next((f for f in files if f.is_lock), None)
        lock_fd = None
        try:
            if lock is not None:
                try:
                    lock_fd = os.open(lock.path, os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC)
                    fcntl.flock(lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except (BlockingIOError, FileNotFoundError):
                    continue  # alive (or already swept by someone else)
                age = now - os.fstat(lock_fd).st_mtime
            else:
                age = now - max(_mtime(f.path) for f in files)
            if pid_alive(pid) and age < ORPHAN_MIN_AGE_S:
                continue  # a starting owner, not yet holding its lock: leave it
            for f in sorted(files, key=lambda f: f.is_lock):  # the lock file last
                try:
                    os.unlink(f.path)
                    removed.append(f.path)
                except FileNotFoundError:
                    pass
        except OSError as exc:  # pragma: no cover - permissions changed under us
            _log.warning("sweep of warp_buffer session %s failed: %s", token, exc)
        finally:
            if lock_fd is not None:
                os.close(lock_fd)
    if removed:
        _log.info("swept %d shared-memory file(s) of dead warp_buffer processes", len(removed))
    return removed


def _mtime(path: str) -> float:
    try:
        return os.stat(path).st_mtime
    except OSError:
        return 0.0


# -------------------------------------------------------------------------------- sessions
class Session:
    """This process's set of shared-memory files, with the lock file that proves it alive."""

    def __init__(self) -> None:
        self.pid = os.getpid()
        self.files: set[str] = set()
        self._next_block = 1
        for _ in range(16):
            self.session = secrets.randbits(64) or 1
            self.token = session_token(self.pid, self.session)
            self.lock_path = lock_path(self.pid, self.session)
            try:
                fd = os.open(self.lock_path,
                             os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                             0o600)
            except FileExistsError:
                continue
            fcntl.flock(fd, fcntl.LOCK_EX)
            # A sweeper may have taken the fresh, not yet locked file for an orphan's and
            # removed it: then our lock guards nothing and we start over under a new name.
            try:
                same = os.stat(self.lock_path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                self.lock_fd = fd
                return
            os.close(fd)
        raise OSError(errno.EEXIST, "cannot create a warp_buffer session lock file")

    def new_block_id(self) -> int:
        block_id = self._next_block
        self._next_block += 1
        return block_id

    def create_file(self, block_id: int, nbytes: int) -> tuple[str, int]:
        """Create block file ``block_id`` of ``nbytes`` (0600, space reserved up front so that a
        full /dev/shm fails here with ENOSPC rather than later with SIGBUS)."""
        path = block_path(self.pid, self.session, block_id)
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                     0o600)
        try:
            os.fchmod(fd, 0o600)
            os.posix_fallocate(fd, 0, nbytes)
        except BaseException:
            os.close(fd)
            _unlink(path)
            raise
        self.files.add(path)
        return path, fd

    def remove_file(self, path: str) -> None:
        self.files.discard(path)
        _unlink(path)

    def close(self) -> None:
        """Remove every file of the session, then the lock file (in that order: a sweeper never
        sees block files of a live session without its lock)."""
        for path in list(self.files):
            _unlink(path)
        self.files.clear()
        _unlink(self.lock_path)
        try:
            os.close(self.lock_fd)
        except OSError:  # pragma: no cover
            pass


def _unlink(path: str) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


_session: Session | None = None
_session_lock = threading.RLock()
_swept_once = False


def current_session() -> Session:
    """This process's session, started on first use (after sweeping dead processes' files)."""
    global _session, _swept_once
    with _session_lock:
        if _session is None or _session.pid != os.getpid():
            if not _swept_once:
                _swept_once = True
                sweep_orphans()
            _session = Session()
        return _session


def create_block_file(nbytes: int) -> tuple[Session, int, str, int]:
    """Create a block file of ``nbytes`` in this process's session (started if needed); returns
    (session, block id, path, fd). Atomic with respect to :func:`close_session_if_empty`."""
    with _session_lock:
        session = current_session()
        block_id = session.new_block_id()
        path, fd = session.create_file(block_id, nbytes)
        return session, block_id, path, fd


def sweep_once() -> None:
    """Sweep orphans once per process (called when the IPC layer or the backend starts)."""
    global _swept_once
    with _session_lock:
        if not _swept_once:
            _swept_once = True
            sweep_orphans()


def close_session_if_empty() -> None:
    """Drop the session (and its lock file) once it owns no block file any more."""
    global _session
    with _session_lock:
        if _session is not None and not _session.files and _session.pid == os.getpid():
            _session.close()
            _session = None


def close_session() -> None:
    """Remove every file of this process's session (clean shutdown)."""
    global _session
    with _session_lock:
        if _session is not None and _session.pid == os.getpid():
            _session.close()
        _session = None


def _after_fork_in_child() -> None:
    # The parent's files are not ours: a child starts its own session when it needs one.
    global _session, _session_lock
    _session = None
    _session_lock = threading.RLock()


os.register_at_fork(after_in_child=_after_fork_in_child)


# -------------------------------------------------------------------------------- import side
def open_block_file(pid: int, session: int, block_id: int) -> tuple[int, os.stat_result]:
    """Open block ``block_id`` of session (pid, session) for import and take a shared hold.

    Checks, before anything is mapped: a regular file (no symlink), owned by this user, mode
    0600, at least a header long. Raises :class:`StaleBufferError` when it is missing or being
    recycled and :class:`ForeignExportError` when it is not this user's file.
    """
    path = block_path(pid, session, block_id)
    try:
        fd = os.open(path, os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK)
    except FileNotFoundError:
        raise StaleBufferError(
            f"export {block_id} of process {pid} is gone (its owner freed it or exited)"
        ) from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise ForeignExportError(f"{path} is a symbolic link, not an export") from None
        if exc.errno in (errno.EACCES, errno.EPERM):
            raise ForeignExportError(f"{path} is not accessible to this user") from None
        raise StaleBufferError(f"cannot open export {path}: {exc}") from exc
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ForeignExportError(f"{path} is not a regular file")
        if st.st_uid != os.getuid():
            raise ForeignExportError(
                f"{path} is owned by uid {st.st_uid}, not by this user ({os.getuid()})"
            )
        if st.st_mode & 0o077:
            raise ForeignExportError(
                f"{path} has mode {stat.S_IMODE(st.st_mode):o}; exports are 0600"
            )
        if st.st_size < HEADER_SIZE:
            raise StaleBufferError(f"{path} is truncated ({st.st_size} bytes)")
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            raise StaleBufferError(
                f"export {block_id} of process {pid} is being recycled"
            ) from None
    except BaseException:
        os.close(fd)
        raise
    return fd, st

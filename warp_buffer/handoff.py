"""Hand-off of an arena's fd to a same-user peer: an abstract Unix socket and ``SCM_RIGHTS``.

The publisher session listens on the abstract name ``warp_buffer.<uid>.<pid>.<session:016x>``
(numbers only; abstract names live in the network namespace, leave nothing in the filesystem and
vanish with the process). A peer connects once per (its process, publisher session), and:

- both sides check the other's credentials with ``SO_PEERCRED`` (the kernel's word, not the
  peer's): the server serves only its own uid; the client accepts only a server of its own uid
  whose pid is the session's owner pid (a squatter on a dead owner's name cannot pass);
- the server sends the arena hello (:data:`warp_buffer.arena.HELLO`) with the memfd attached;
- the client checks the hello (magic, version, session, geometry), that the fd carries the seals
  ``F_SEAL_SHRINK | F_SEAL_GROW | F_SEAL_SEAL`` (nobody can shrink it: no SIGBUS) and that its
  size is the arena's, before anything is mapped.

Every failure is a typed :mod:`warp_buffer.errors` error, never a raw ``OSError``.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import socket
import struct
import threading
import time
from typing import Any

from .arena import HELLO, MAGIC, SEALS, VERSION, Arena, Geometry, alive
from .errors import DescriptorError, ExportError, ForeignExportError, StaleBufferError

__all__ = ["socket_name", "Server", "fetch_arena", "linger_s"]

_log = logging.getLogger(__name__)
_UCRED = struct.Struct("3i")
CONNECT_TIMEOUT_S = 5.0


def socket_name(uid: int, pid: int, session: int) -> bytes:
    return f"\0warp_buffer.{uid}.{pid}.{session:016x}".encode()


def linger_s() -> float:
    """``WARP_BUFFER_EXIT_LINGER_S`` (default 2): how long a cleanly exiting publisher keeps
    serving peers that were sent descriptors but never fetched the arena."""
    try:
        return max(0.0, float(os.environ.get("WARP_BUFFER_EXIT_LINGER_S", "2")))
    except ValueError:
        return 2.0


def _peer_cred(sock: socket.socket) -> tuple[int, int]:
    pid, uid, _gid = _UCRED.unpack(sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                   _UCRED.size))
    return pid, uid


class Server:
    """The session's listener: one daemon thread that hands the arena fd to each peer."""

    def __init__(self, arena: Arena) -> None:
        self._arena = arena
        self._hello = arena.hello()
        self.connected: set[int] = set()  # pids that fetched the arena
        self._cond = threading.Condition()
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        self._sock.bind(socket_name(os.getuid(), arena.pid, arena.session))
        self._sock.listen(128)
        self._closed = False
        self._thread = threading.Thread(target=self._serve, daemon=True,
                                        name="warp_buffer-handoff")
        self._thread.start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return  # closed
            try:
                with conn:
                    pid, uid = _peer_cred(conn)
                    if uid != os.getuid():
                        _log.warning("refused arena hand-off to pid %d of uid %d", pid, uid)
                        continue
                    conn.settimeout(CONNECT_TIMEOUT_S)
                    socket.send_fds(conn, [self._hello], [self._arena.fd])
                with self._cond:
                    self.connected.add(pid)
                    self._cond.notify_all()
            except OSError as exc:  # a peer that went away mid-hand-off
                _log.debug("arena hand-off failed: %s", exc)

    def linger(self, pids: set[int], timeout: float) -> None:
        """Wait (at most ``timeout``) until each pid in ``pids`` that is still alive fetched the
        arena: a peer with queued descriptors can then read them after we exit."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                waiting = {p for p in pids - self.connected if alive(p)}
                left = deadline - time.monotonic()
                if not waiting or left <= 0:
                    return
                self._cond.wait(min(left, 0.05))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._sock.shutdown(socket.SHUT_RDWR)  # wakes the accept()
        except OSError:
            pass
        self._sock.close()


def fetch_arena(owner_pid: int, session: int) -> tuple[int, Geometry]:
    """Connect to session ``(owner_pid, session)`` of this user and receive its arena fd, checked
    (seals, size, credentials); returns ``(fd, geometry)``. The fd shares the publisher's open
    file description: re-open it before taking locks (:func:`warp_buffer.memory.reopen`)."""
    where = f"session {session:016x} of process {owner_pid}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
    fds: list[int] = []
    try:
        sock.settimeout(CONNECT_TIMEOUT_S)
        try:
            sock.connect(socket_name(os.getuid(), owner_pid, session))
        except (ConnectionRefusedError, FileNotFoundError):
            raise StaleBufferError(f"{where} is gone (the publisher exited before this process "
                                   "attached to its memory)") from None
        except OSError as exc:
            raise ExportError(f"cannot reach {where}: {exc}") from None
        pid, uid = _peer_cred(sock)
        if uid != os.getuid() or pid != owner_pid:
            raise ForeignExportError(f"{where} is served by pid {pid} of uid {uid}, not by its "
                                     f"owner under this user ({os.getuid()})")
        try:
            data, fds, _flags, _addr = socket.recv_fds(sock, HELLO.size, 1)
        except OSError as exc:
            raise StaleBufferError(f"{where}: the hand-off failed ({exc})") from None
        if len(fds) != 1 or len(data) != HELLO.size:
            raise StaleBufferError(f"{where}: the hand-off carried no arena")
        fd = fds.pop()
        try:
            geometry = _check(fd, data, owner_pid, session, where)
        except BaseException:
            os.close(fd)
            raise
        return fd, geometry
    finally:
        for extra in fds:
            os.close(extra)
        sock.close()


def _check(fd: int, hello: bytes, owner_pid: int, session: int, where: str) -> Geometry:
    magic, version, pid, tag, data_offset, data_bytes, file_size = HELLO.unpack(hello)
    if magic != MAGIC or version != VERSION:
        raise DescriptorError(f"{where}: not a warp_buffer arena of version {VERSION}")
    if pid != owner_pid or tag != session:
        raise StaleBufferError(f"{where}: the socket serves another session ({tag:016x})")
    if data_bytes < 1 or data_bytes & (data_bytes - 1) or data_bytes > 1 << 46:
        raise DescriptorError(f"{where}: arena of {data_bytes} data bytes")
    geometry = Geometry(data_bytes)
    if geometry.data_offset != data_offset or geometry.file_size != file_size:
        raise DescriptorError(f"{where}: the arena layout does not match its size")
    try:
        seals = fcntl.fcntl(fd, fcntl.F_GET_SEALS)
        size = os.fstat(fd).st_size
    except OSError as exc:
        if exc.errno == errno.EINVAL:
            raise ForeignExportError(f"{where}: the fd is not a sealable memfd") from None
        raise ExportError(f"{where}: cannot inspect the arena fd: {exc}") from None
    if seals & SEALS != SEALS:
        raise ForeignExportError(f"{where}: the arena is not sealed against shrinking "
                                 f"(seals {seals:#x})")
    if size != file_size:
        raise StaleBufferError(f"{where}: the arena is {size} bytes, its hello says {file_size}")
    return geometry


def start_server(arena: Arena) -> Any:
    """The arena's server, started once."""
    if arena.server is None:
        arena.server = Server(arena)
    return arena.server

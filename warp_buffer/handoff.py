"""Hand-off of a session's fds to a same-user peer: an abstract Unix socket and ``SCM_RIGHTS``.

The publisher session listens on the abstract name ``warp_buffer.<uid>.<pid>.<session:016x>``
(numbers only; abstract names live in the network namespace, leave nothing in the filesystem and
vanish with the process). A peer connects once per (its process, publisher session), and:

- both sides check the other's credentials with ``SO_PEERCRED`` (the kernel's word, not the
  peer's): the server serves only its own uid; the client accepts only a server of its own uid
  whose pid is the session's owner pid (a squatter on a dead owner's name cannot pass);
- the client sends one :data:`REQUEST` and the server answers it:

  - ``ASK_ARENA``: the arena hello (:data:`warp_buffer.arena.HELLO`) with the memfd attached;
    the client checks the hello (magic, version, session, geometry), that the fd carries the
    seals ``F_SEAL_SHRINK | F_SEAL_GROW | F_SEAL_SEAL`` (nobody can shrink it: no SIGBUS) and
    that its size is the arena's, before anything is mapped. Both ends then keep this
    connection open and silent: it closes when the publisher's session ends (clean exit,
    crash, SIGKILL: the kernel closes it), which is how the peer learns the session is gone
    (:data:`session_gone_hooks`, run by a watcher thread).
  - ``ASK_CUDA_VMM``: a :data:`VMM_REPLY` with a POSIX fd of one CUDA VMM block
    (``cuMemExportToShareableHandle``), named by its arena offset and its allocation serial
    (both from a descriptor the peer holds), or a refusal without an fd.

Every failure is a typed :mod:`warp_buffer.errors` error, never a raw ``OSError``.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import select
import socket
import struct
import threading
import time
from collections.abc import Callable
from typing import Any

from ._env import env_float
from .arena import HELLO, MAGIC, SEALS, VERSION, Arena, Geometry, alive
from .errors import DescriptorError, ExportError, ForeignExportError, StaleBufferError

__all__ = ["socket_name", "Server", "fetch_arena", "fetch_cuda_block", "linger_s",
           "session_gone", "session_gone_hooks"]

_log = logging.getLogger(__name__)
_UCRED = struct.Struct("3i")
CONNECT_TIMEOUT_S = 5.0
#: A request that is not there this soon after its connection is waited for on its own thread.
PROMPT_REQUEST_S = 0.05
#: Peers waited for at once that way; more are refused (a flood of idle connections).
MAX_STRAGGLERS = 32
WATCH_POLL_S = 0.2  # how soon a newly fetched session is watched
#: A peer's request: what, block offset, allocation serial (both 0 for the arena).
REQUEST = struct.Struct("<8sQQ")
ASK_ARENA = b"WBARENA2"
ASK_CUDA_VMM = b"WBVMM\x00\x00\x01"
#: The answer to ``ASK_CUDA_VMM``: magic, offset, serial, allocation bytes (0: refused, no fd).
VMM_REPLY = struct.Struct("<8sQQQ")

#: Called with ``(owner_pid, session)`` when a session this process fetched is gone: its hand-off
#: socket reports the publisher gone (the kept connection closed, or a connection refused), or
#: its mapping was let go (owner gone, nothing held), so caches keyed by session (the CUDA import
#: cache) let it go at once.
session_gone_hooks: list[Callable[[tuple[int, int]], None]] = []


def socket_name(uid: int, pid: int, session: int) -> bytes:
    return f"\0warp_buffer.{uid}.{pid}.{session:016x}".encode()


def linger_s() -> float:
    """``WARP_BUFFER_EXIT_LINGER_S`` (default 2): how long a cleanly exiting publisher keeps
    serving peers that were sent descriptors but never fetched the arena."""
    return max(0.0, env_float("WARP_BUFFER_EXIT_LINGER_S", 2.0))


def _peer_cred(sock: socket.socket) -> tuple[int, int]:
    pid, uid, _gid = _UCRED.unpack(sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                   _UCRED.size))
    return pid, uid


def _recv_exact(sock: socket.socket, nbytes: int) -> bytes:
    data = b""
    while len(data) < nbytes:
        chunk = sock.recv(nbytes - len(data))
        if not chunk:
            raise ConnectionError("the peer closed the connection")
        data += chunk
    return data


def _request_ready(sock: socket.socket, timeout_s: float) -> bool:
    """Has a whole request arrived on ``sock`` within ``timeout_s`` (poll: any fd number; a
    peer that sent part of one is as slow as one that sent nothing)?"""
    poller = select.poll()
    poller.register(sock, select.POLLIN)
    if not poller.poll(timeout_s * 1000):
        return False
    try:
        data = sock.recv(REQUEST.size, socket.MSG_PEEK | socket.MSG_DONTWAIT)
    except OSError:
        return True  # failed: answering it fails at once, on this thread
    return len(data) >= REQUEST.size or not data  # whole, or closed (fails at once too)


def _closed(sock: socket.socket) -> bool:
    """Has the other end of an idle, blocking ``sock`` gone (EOF or error, never waits)?"""
    try:
        return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
    except BlockingIOError:
        return False
    except OSError:
        return True


class Server:
    """The session's listener: one daemon thread that answers each peer's request (the arena
    fd, or a CUDA VMM block's fd) and keeps each peer's arena connection open until either
    side goes (so the peer sees this session end). A peer whose request is not there at once
    (frozen or idle after connecting) is waited for on a thread of its own, so it never delays
    the others."""

    def __init__(self, arena: Arena) -> None:
        self._arena = arena
        self._hello = arena.hello()
        self.connected: set[int] = set()  # pids that fetched the arena
        self._cond = threading.Condition()
        self._peers: list[socket.socket] = []  # kept arena connections (under _cond)
        self._stragglers = 0  # peers waited for on threads of their own (under _cond)
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
            self._sweep()
            if _request_ready(conn, PROMPT_REQUEST_S):
                self._handle(conn)  # the usual case: the request came with the connection
                continue
            with self._cond:
                straggling = self._stragglers < MAX_STRAGGLERS
                self._stragglers += straggling
            if not straggling:
                _log.debug("hand-off: too many peers slow to ask, one refused")
                conn.close()
                continue
            try:
                threading.Thread(target=self._handle, args=(conn, True), daemon=True,
                                 name="warp_buffer-handoff-peer").start()
            except RuntimeError as exc:  # no thread to spare: refuse this one, serve the next
                _log.debug("hand-off: cannot wait for a slow peer: %s", exc)
                with self._cond:
                    self._stragglers -= 1
                conn.close()

    def _handle(self, conn: socket.socket, straggler: bool = False) -> None:
        """Answer ``conn`` and keep it or close it."""
        keep = False
        try:
            keep = self._answer(conn)
        except OSError as exc:  # a peer that went away (or stalled) mid-hand-off
            _log.debug("hand-off failed: %s", exc)
        with self._cond:
            self._stragglers -= straggler
            if keep and not self._closed:
                self._peers.append(conn)
                return
        conn.close()

    def _answer(self, conn: socket.socket) -> bool:
        """Answer one request; True when ``conn`` is a peer's arena connection to keep."""
        pid, uid = _peer_cred(conn)
        if uid != os.getuid():
            _log.warning("refused arena hand-off to pid %d of uid %d", pid, uid)
            return False
        conn.settimeout(CONNECT_TIMEOUT_S)
        what, offset, serial = REQUEST.unpack(_recv_exact(conn, REQUEST.size))
        if what == ASK_ARENA:
            socket.send_fds(conn, [self._hello], [self._arena.fd])
            conn.settimeout(None)  # kept idle and blocking: _closed() probes it without waiting
            with self._cond:
                self.connected.add(pid)
                self._cond.notify_all()
            return True
        if what == ASK_CUDA_VMM:
            self._send_cuda_block(conn, offset, serial)
        else:
            _log.debug("unknown hand-off request %r from pid %d", what, pid)
        return False

    def _send_cuda_block(self, conn: socket.socket, offset: int, serial: int) -> None:
        block = self._arena.cuda_exports.get(offset)
        fd = -1
        if block is not None and block.serial == serial:
            try:
                fd = block.export_fd()
            except Exception as exc:  # noqa: BLE001 - a closed or unexportable block: refuse
                _log.debug("CUDA VMM block %#x not exported: %s", offset, exc)
        if fd < 0:
            conn.sendall(VMM_REPLY.pack(ASK_CUDA_VMM, offset, serial, 0))
            return
        try:
            socket.send_fds(conn, [VMM_REPLY.pack(ASK_CUDA_VMM, offset, serial,
                                                  block.vmm_bytes)], [fd])
        finally:
            os.close(fd)  # the peer holds its own copy now

    def _sweep(self) -> None:
        """Close kept connections whose peer went away (one fd per live peer process)."""
        with self._cond:
            gone = [conn for conn in self._peers if _closed(conn)]
            for conn in gone:
                self._peers.remove(conn)
        for conn in gone:
            conn.close()

    @property
    def peers(self) -> int:
        """Kept peer connections (peers that fetched the arena and may still be alive)."""
        with self._cond:
            return len(self._peers)

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

    def abandon(self) -> None:
        """In a forked child: close this process's copies of the sockets, without the shutdown
        that would end the parent's (which keeps serving). No lock: a thread of the parent may
        have held it at the fork, and the child has that thread no more."""
        self._cond = threading.Condition()
        self._closed = True
        peers, self._peers = self._peers, []
        self._sock.close()
        for conn in peers:
            conn.close()

    def close(self) -> None:
        """Stop serving; every peer's kept connection closes (they learn the session ended)."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            peers, self._peers = self._peers, []
        try:
            self._sock.shutdown(socket.SHUT_RDWR)  # wakes the accept()
        except OSError:
            pass
        self._sock.close()
        for conn in peers:
            conn.close()


def _why_gone(owner_pid: int) -> str:
    """Why a session's socket refused us, as far as its pid tells."""
    try:
        os.kill(owner_pid, 0)
    except ProcessLookupError:
        return "the publisher exited before this process attached to its memory"
    except PermissionError:
        pass  # alive, another user's
    return (f"process {owner_pid} runs but serves no such session: the session ended, or the "
            "descriptor names one that never was")


def _connect(owner_pid: int, session: int, where: str) -> socket.socket:
    """A connection to session ``(owner_pid, session)``'s socket, its server's credentials
    checked. A refused connection means the session is gone: :data:`session_gone_hooks` run."""
    try:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
    except OSError as exc:  # out of file descriptors, typically
        raise ExportError(f"cannot reach {where}: no socket for it: {exc}") from None
    try:
        sock.settimeout(CONNECT_TIMEOUT_S)
        try:
            sock.connect(socket_name(os.getuid(), owner_pid, session))
        except (ConnectionRefusedError, FileNotFoundError):
            session_gone((owner_pid, session))
            raise StaleBufferError(f"{where} is gone ({_why_gone(owner_pid)})") from None
        except OSError as exc:
            raise ExportError(f"cannot reach {where}: {exc}") from None
        pid, uid = _peer_cred(sock)
        if uid != os.getuid() or pid != owner_pid:
            raise ForeignExportError(f"{where} is served by pid {pid} of uid {uid}, not by its "
                                     f"owner under this user ({os.getuid()})")
    except BaseException:
        sock.close()
        raise
    return sock


def _ask(sock: socket.socket, request: bytes) -> None:
    """Send ``request``; a server that already answered and closed (EPIPE) is judged by what
    it sent, which stays readable."""
    try:
        sock.sendall(request)
    except (BrokenPipeError, ConnectionResetError):
        pass


def _exchange(sock: socket.socket, where: str, request: bytes, reply_size: int,
              fds: list[int]) -> bytes:
    """Send ``request``; the reply of at most ``reply_size`` bytes, its fd (if any) appended to
    ``fds`` (the caller closes what it does not keep)."""
    try:
        _ask(sock, request)
        data, received, _flags, _addr = socket.recv_fds(sock, reply_size, 1)
    except OSError as exc:
        raise StaleBufferError(f"{where}: the hand-off failed ({exc})") from None
    fds.extend(received)
    return data


def fetch_arena(owner_pid: int, session: int) -> tuple[int, Geometry]:
    """Connect to session ``(owner_pid, session)`` of this user and receive its arena fd, checked
    (seals, size, credentials); returns ``(fd, geometry)``. The fd shares the publisher's open
    file description: re-open it before taking locks (:func:`warp_buffer.memory.reopen`). The
    connection is kept, watched: when it closes, :data:`session_gone_hooks` run."""
    where = f"session {session:016x} of process {owner_pid}"
    sock = _connect(owner_pid, session, where)
    fds: list[int] = []
    try:
        data = _exchange(sock, where, REQUEST.pack(ASK_ARENA, 0, 0), HELLO.size, fds)
        if len(fds) != 1 or len(data) != HELLO.size:
            raise StaleBufferError(f"{where}: the hand-off carried no arena")
        fd = fds.pop()
        try:
            geometry = _check(fd, data, owner_pid, session, where)
        except BaseException:
            os.close(fd)
            raise
        _watcher.watch(sock, (owner_pid, session))
        sock = None
        return fd, geometry
    finally:
        for extra in fds:
            os.close(extra)
        if sock is not None:
            sock.close()


def fetch_cuda_block(owner_pid: int, session: int, offset: int, serial: int) -> tuple[int, int]:
    """Receive a POSIX fd of the CUDA VMM block at arena ``offset`` (allocation ``serial``) of
    session ``(owner_pid, session)``; returns ``(fd, allocation bytes)``, the fd the caller's to
    close once imported. Ask only while holding the block (the publisher cannot recycle it
    then). Raises :class:`StaleBufferError` when the session or the block is gone."""
    where = f"CUDA block {offset:#x} of session {session:016x} of process {owner_pid}"
    sock = _connect(owner_pid, session, where)
    fds: list[int] = []
    try:
        data = _exchange(sock, where, REQUEST.pack(ASK_CUDA_VMM, offset, serial),
                         VMM_REPLY.size, fds)
        if len(data) != VMM_REPLY.size:
            raise StaleBufferError(f"{where}: the hand-off carried no answer")
        magic, got_offset, got_serial, nbytes = VMM_REPLY.unpack(data)
        if magic != ASK_CUDA_VMM or (got_offset, got_serial) != (offset, serial):
            raise DescriptorError(f"{where}: answered for another block")
        if nbytes == 0 or len(fds) != 1:
            raise StaleBufferError(f"{where}: the publisher no longer exports it")
        return fds.pop(), nbytes
    finally:
        for extra in fds:
            os.close(extra)
        sock.close()


def session_gone(key: tuple[int, int]) -> None:
    """Run :data:`session_gone_hooks` for ``key``: its hand-off connection closed, or its
    mapping was let go (owner gone, nothing held)."""
    for hook in list(session_gone_hooks):
        try:
            hook(key)
        except Exception:  # noqa: BLE001 - one failing hook must not stop the others
            _log.exception("warp_buffer: a session-gone hook failed")


class _Watcher:
    """One daemon thread that waits for the kept arena connections of this process to close
    (their publisher session ended) and then runs :data:`session_gone_hooks` for it. It runs
    only while some connection is watched. ``select.poll`` needs no fd of its own, and new
    connections are picked up at the next wake-up (every :data:`WATCH_POLL_S`): the watch
    costs one socket per fetched session, nothing more."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._incoming: list[tuple[socket.socket, tuple[int, int]]] = []
        self._thread: threading.Thread | None = None
        self._count = 0  # connections registered with the running thread

    def watch(self, sock: socket.socket, key: tuple[int, int]) -> None:
        sock.settimeout(None)
        with self._lock:
            self._incoming.append((sock, key))
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, daemon=True,
                                                name="warp_buffer-session-watch")
                self._thread.start()

    @property
    def watched(self) -> int:
        """Connections watched now (one per fetched session whose publisher is alive)."""
        with self._lock:
            return self._count + len(self._incoming)

    def _run(self) -> None:
        poller = select.poll()
        watched: dict[int, tuple[socket.socket, tuple[int, int]]] = {}
        while True:
            with self._lock:
                for sock, key in self._incoming:
                    watched[sock.fileno()] = (sock, key)
                    poller.register(sock, select.POLLIN)
                self._incoming = []
                self._count = len(watched)
                if not watched:
                    self._thread = None
                    return
            for fileno, _mask in poller.poll(WATCH_POLL_S * 1000):
                sock, key = watched[fileno]
                if _closed(sock):
                    poller.unregister(fileno)
                    del watched[fileno]
                    sock.close()
                    session_gone(key)
                else:  # a server never writes here; discard what a forged one sent
                    try:
                        sock.recv(4096, socket.MSG_DONTWAIT)
                    except OSError:
                        pass


_watcher = _Watcher()


def _after_fork_in_child() -> None:
    # The parent's watched connections are the parent's: a child attaches afresh.
    global _watcher
    _watcher = _Watcher()


os.register_at_fork(after_in_child=_after_fork_in_child)


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

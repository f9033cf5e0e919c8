"""The same-host fast lane: small messages (descriptor CDR) between processes, through rings in
the publisher's memory with an eventfd doorbell (the native core, :mod:`buffer_pubsub._ring`).

Zenoh stays the discovery layer and the transport between hosts; between two processes of one
host and user the lane carries what the transport would otherwise put on a subscription's own
Zenoh channel ``<data key>/_buf/<subscriber gid>``: at most :data:`MAX_PAYLOAD` opaque bytes per
message.

- A subscription's :class:`LaneReader` listens on an abstract Unix socket named after the route
  (:func:`address`: numbers and a hash only; abstract names leave nothing in the filesystem and
  vanish with the process), made before the subscription is announced, so that a publisher that
  discovers it finds it.
- A publisher's :class:`LaneWriter` connects (the kernel's credentials: same user only, both
  ways), makes a ring (a sealed anonymous memfd: one frame per slot, keep-last) and an eventfd,
  and hands both over in one message; the connection stays open and silent, which is how each
  side learns that the other is gone. ``write()`` copies the frame into the next slot and rings
  the doorbell only when the reader sleeps; it never waits.
- :class:`LaneWaker` is the node's executor waker: one thread sleeps in ``ppoll`` (the GIL
  released) on its notify eventfd, the doorbells and the readers' sockets, and runs the lane
  callbacks itself when frames arrive (no extra thread hop). ``LaneWaker(busy_poll_s=...)``
  spins that long first (GIL released, a core at 100%) before it blocks.

Everything is reclaimed by the kernel when a process ends, however it ends: the memfd goes with
the last mapping, sockets and eventfds with their last descriptor; nothing has a name in
``/dev/shm`` or the filesystem, and nothing needs cleaning up after a crash. The reader trusts
nothing the writer puts in the ring (lengths, indexes and stamps are checked), and the writer
nothing the reader puts there.

Turn the lane off with ``WARP_BUFFER_FAST_LANE=0`` (or ``Node(..., fast_lane=False)``, see
:func:`enabled`).
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import logging
import os
import select
import socket
import struct
import threading
import weakref
from collections.abc import Callable
from typing import Any

from rosidl_buffer.native import load_extension

from .connectivity import out_of_fds_hint
from .errors import PubSubError

_ring = load_extension("buffer_pubsub._ring")

__all__ = ["ENV_SWITCH", "MAX_PAYLOAD", "NODE_OPTION", "LaneError", "LaneReader", "LaneStatus",
           "LaneUnavailableError", "LaneWaker", "LaneWriter", "address", "enabled",
           "resource_prefix", "service_name", "status"]

_log = logging.getLogger(__name__)

#: ``WARP_BUFFER_FAST_LANE=0`` (or ``false``/``off``/``no``) turns the lane off in a process.
ENV_SWITCH = "WARP_BUFFER_FAST_LANE"
#: The ``Node`` keyword that turns the lane on or off per node: ``Node(..., fast_lane=False)``.
NODE_OPTION = "fast_lane"
#: Largest message the lane carries; bigger ones take the Zenoh route. A descriptor is at most
#: 4096 B (rosidl::Buffer's kMaxBufferDescriptorSize); the rest is the message's other fields.
MAX_PAYLOAD = 8192
#: Writers one reader admits at once (the listening socket's backlog, too).
MAX_WRITERS = 32
#: The deepest keep-last subscription the lane serves (a ring is depth slots of ~MAX_PAYLOAD).
MAX_DEPTH = 1024
#: A writer's ring when the route does not say how deep the reader keeps (``LaneWriter(depth=)``).
DEFAULT_DEPTH = 64
_OFF = {"0", "false", "off", "no"}
_ON = {"", "1", "true", "on", "yes"}
_warned_values: dict[str, bool] = {}
_SERVICE_ROOT = "warp_buffer"
#: The hello a writer sends with the ring's memfd and doorbell: magic, version, writer pid,
#: ring depth, slot bytes, largest frame.
HELLO = struct.Struct("<8sIIIII")
MAGIC = b"WBLANE\x00\x01"
VERSION = 1
_UCRED = struct.Struct("3i")


class LaneError(PubSubError, RuntimeError):
    """A fast-lane operation failed (the message says which and why)."""


class LaneUnavailableError(LaneError):
    """The lane cannot be used for this route (no reader, another user's, out of descriptors):
    the transport uses Zenoh instead."""


_ring.set_error_class(LaneError)


@dataclasses.dataclass(frozen=True)
class LaneStatus:
    """Whether the lane can run in this process; ``reason`` says why not (empty when it can)."""

    available: bool
    reason: str = ""


def enabled(option: bool | None = None) -> bool:
    """Whether the lane is wanted: ``option`` (the Node's ``fast_lane``) when given, else the
    environment (:data:`ENV_SWITCH`, on unless ``0``/``false``/``off``/``no``)."""
    if option is not None:
        return bool(option)
    value = os.environ.get(ENV_SWITCH, "1").strip().lower()
    if value not in _OFF and value not in _ON and not _warned_values.get(value):
        _warned_values[value] = True  # once per value: it is read at every node
        _log.warning("%s=%r is neither on (1/true/yes/on) nor off (0/false/no/off): the lane "
                     "stays on", ENV_SWITCH, value)
    return value not in _OFF


_logged = False


def status(option: bool | None = None) -> LaneStatus:
    """Whether the lane runs here: it runs wherever it is wanted (:func:`enabled`); the reason
    it does not is logged once per process."""
    global _logged
    if enabled(option):
        return LaneStatus(True)
    result = LaneStatus(False, f"turned off ({ENV_SWITCH}=0 or {NODE_OPTION}=False)")
    if not _logged:
        _logged = True
        _log.info("fast lane off, Zenoh carries same-host messages: %s", result.reason)
    return result


def service_name(data_key: str, subscriber_gid: bytes) -> str:
    """The lane of the route ``<data_key>/_buf/<subscriber gid>``: the Zenoh key itself when it
    is printable ASCII of at most 255 characters, else a SHA-256 of it (both sides derive the
    same name from the same key)."""
    name = f"{_SERVICE_ROOT}/{data_key}/_buf/{subscriber_gid.hex()}"
    if len(name) <= 255 and name.isascii() and name.isprintable():
        return name
    return f"{_SERVICE_ROOT}/sha256/{hashlib.sha256(name.encode()).hexdigest()}"


def resource_prefix() -> str:
    """The prefix of every name the lane takes (abstract Unix socket names, ``@`` shown for the
    leading NUL as ``ss -x`` does): ``@warp_buffer.lane.<uid>.``; nothing else is named."""
    return f"@warp_buffer.lane.{os.getuid()}."


def address(name: str) -> bytes:
    """The abstract socket address of lane ``name``'s reader (this user's: the kernel's uid)."""
    digest = hashlib.sha256(name.encode()).hexdigest()[:40]
    return f"\0warp_buffer.lane.{os.getuid()}.{digest}".encode()


def _peer_uid(sock: socket.socket) -> int:
    _pid, uid, _gid = _UCRED.unpack(sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                    _UCRED.size))
    return uid


def _slot_bytes(max_payload: int) -> int:
    return -(-(max_payload + _ring.SLOT_HEAD) // 64) * 64


def _close_quietly(*fds: int) -> None:
    for fd in fds:
        try:
            os.close(fd)
        except OSError:
            pass


class LaneWriter(_ring.RingWriter):
    """Publishes messages to one reader's lane (the publisher side of one route); ``depth``:
    frames its ring keeps for a reader that falls behind (the reader keeps at most its own
    depth of them). ``write(*parts) -> bool`` and ``fits(nbytes) -> bool`` are the ring's own
    (one C call per message, atomic under the GIL against the publisher's other threads):
    ``write`` copies the concatenation of ``parts`` into the next slot, wakes the reader if it
    sleeps, never waits, and returns False when the reader is gone (the message reached
    nobody); it raises :class:`LaneError` for a message over ``max_payload`` or once closed.

    Raises:
        LaneUnavailableError: no reader listens on this route here (the subscription is on
            another host, runs as another user, has the lane off), it admits no more writers,
            or this process is out of file descriptors.
    """

    def __init__(self, name: str, max_payload: int = MAX_PAYLOAD,
                 depth: int = DEFAULT_DEPTH) -> None:
        self.name = name
        self.max_payload = max_payload
        self._conn = _connect(name)
        try:
            super().__init__(min(max(1, depth), MAX_DEPTH), _slot_bytes(max_payload),
                             max_payload)
            memfd = self.take_memfd()
            try:
                socket.send_fds(self._conn, [HELLO.pack(MAGIC, VERSION, os.getpid(), self.depth,
                                                        self.slot_bytes, max_payload)],
                                [memfd, self.doorbell], socket.MSG_DONTWAIT)
            finally:
                os.close(memfd)  # the mapping keeps the ring; the reader has its own fd
            self.watch(self._conn.fileno())
        except (OSError, LaneError) as error:
            self.close()
            raise LaneUnavailableError(f"no lane to {name!r}: {error}") from None

    def __repr__(self) -> str:
        return f"LaneWriter({self.name!r})"

    def close(self) -> None:
        """Tell the reader this end is closed (it takes what is left, then lets the ring go);
        idempotent."""
        super().close()
        self._conn.close()


def _connect(name: str) -> socket.socket:
    try:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_CLOEXEC
                             | socket.SOCK_NONBLOCK)
    except OSError as error:
        raise LaneUnavailableError(f"no lane to {name!r}: no socket ({error})") from None
    try:
        sock.connect(address(name))
        if _peer_uid(sock) != os.getuid():
            raise LaneUnavailableError(f"the lane reader of {name!r} runs as another user")
    except (FileNotFoundError, ConnectionRefusedError):
        sock.close()
        raise LaneUnavailableError(f"no lane reader for {name!r}") from None
    except BlockingIOError:
        sock.close()
        raise LaneUnavailableError(f"the lane reader of {name!r} admits no more writers "
                                   f"now") from None
    except OSError as error:
        sock.close()
        raise LaneUnavailableError(f"no lane to {name!r}: {error}") from None
    except BaseException:
        sock.close()
        raise
    return sock


@dataclasses.dataclass
class _Inbound:
    """One writer's connection to a reader: its ring once its hello came."""

    conn: socket.socket
    ring: Any = None


class LaneReader:
    """Receives one route's messages (the subscription side); create it before the subscription
    is announced, so that a writer that discovers the subscription finds it.

    ``depth``: keep-last; of the frames a writer sent that were not taken yet, the newest
    ``depth`` are delivered, the older ones dropped (a reader that falls behind).

    Raises:
        LaneUnavailableError: another reader has this route, or no socket could be made.
    """

    def __init__(self, name: str, depth: int = 16) -> None:
        self.name = name
        self.depth = min(max(1, depth), MAX_DEPTH)
        self._inbound: dict[int, _Inbound] = {}  # by connection fd
        self._closed = False
        try:
            self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET
                                           | socket.SOCK_CLOEXEC | socket.SOCK_NONBLOCK)
        except OSError as error:
            raise LaneUnavailableError(f"cannot create lane reader {name!r}: {error}") from None
        try:
            self._listener.bind(address(name))
            self._listener.listen(MAX_WRITERS)
        except OSError as error:
            self._listener.close()
            why = "one reader per route" if error.errno == errno.EADDRINUSE else str(error)
            raise LaneUnavailableError(f"cannot create lane reader {name!r}: {why}") from None

    def __repr__(self) -> str:
        return f"LaneReader({self.name!r})"

    @property
    def listener(self) -> socket.socket | None:
        """The listening socket (None once closed)."""
        return None if self._closed else self._listener

    # -- the waiting thread ---------------------------------------------------------------------
    def rings(self) -> list[Any]:
        """The rings of the writers connected now (``buffer_pubsub._ring.RingReader``)."""
        return [inbound.ring for inbound in self._inbound.values() if inbound.ring is not None]

    def watched(self) -> list[tuple[int, int]]:
        """``(fd, poll events)`` the waker watches for this reader: new writers, hellos still
        to come, and hang-ups of connected writers."""
        if self._closed:
            return []
        fds = [(self._listener.fileno(), select.POLLIN)]
        fds += [(fd, select.POLLIN if inbound.ring is None else 0)
                for fd, inbound in self._inbound.items()]
        return fds

    def handle(self, fd: int, revents: int) -> bool:
        """React to ``revents`` on one of :meth:`watched`'s fds; True when the set of rings or
        watched fds changed."""
        if self._closed:
            return False
        if fd == self._listener.fileno():
            return self.accept()
        inbound = self._inbound.get(fd)
        if inbound is None:
            return False
        if inbound.ring is None and revents & select.POLLIN:
            return self._hello(fd, inbound)
        if revents & (select.POLLHUP | select.POLLERR | select.POLLNVAL):
            self._drop(fd)  # the writer is gone: its frames were delivered before this
            return True
        return False

    def accept(self) -> bool:
        """Take in every writer that connected (and its ring, when its hello is there)."""
        changed = False
        while len(self._inbound) < MAX_WRITERS * 2:
            try:
                conn, _ = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                break
            except OSError as error:  # out of descriptors: the writer sees a hang-up
                _log.debug("lane %r: cannot accept a writer: %s", self.name, error)
                break
            conn.setblocking(False)
            try:
                uid = _peer_uid(conn)
            except OSError:
                uid = -1
            if uid != os.getuid():
                _log.warning("lane %r: refused a writer of uid %d", self.name, uid)
                conn.close()
                continue
            self._inbound[conn.fileno()] = inbound = _Inbound(conn)
            self._hello(conn.fileno(), inbound)
            changed = True
        return changed

    def _hello(self, fd: int, inbound: _Inbound) -> bool:
        """Receive a writer's hello and ring; True when it came (or the writer was refused)."""
        try:
            data, fds, _flags, _addr = socket.recv_fds(inbound.conn, HELLO.size, 2,
                                                       socket.MSG_DONTWAIT)
        except (BlockingIOError, InterruptedError):
            return False  # not there yet: watched for it
        except OSError as error:
            _log.debug("lane %r: a writer's hello failed: %s", self.name, error)
            self._drop(fd)
            return True
        try:
            inbound.ring = self._ring_of(data, fds)
        except LaneError as error:
            _log.warning("lane %r: refused a writer: %s", self.name, error)
            self._drop(fd)
        finally:
            _close_quietly(*fds)
        return True

    def _ring_of(self, data: bytes, fds: list[int]) -> Any:
        if len(data) != HELLO.size or len(fds) != 2:
            raise LaneError(f"a hello of {len(data)} bytes with {len(fds)} fds")
        magic, version, _pid, depth, slot_bytes, _max = HELLO.unpack(data)
        if magic != MAGIC or version != VERSION:
            raise LaneError(f"not a lane hello of version {VERSION}")
        return _ring.RingReader(fds[0], fds[1], depth, slot_bytes, self.depth)

    def _drop(self, fd: int) -> None:
        inbound = self._inbound.pop(fd, None)
        if inbound is None:
            return
        if inbound.ring is not None:
            inbound.ring.close()
        inbound.conn.close()

    # -- without a waker ------------------------------------------------------------------------
    def take(self) -> bytes | None:
        """The oldest waiting message of a writer (copied out of its ring), or None. For a
        reader that is not attached to a waker (the waker delivers attached ones)."""
        if self._closed:
            return None
        self.accept()
        for fd, inbound in list(self._inbound.items()):
            if inbound.ring is None:
                self._hello(fd, inbound)
            if inbound.ring is not None:
                frame = inbound.ring.take()
                if frame is not None:
                    return frame
        return None

    def has_samples(self) -> bool:
        """Whether a message waits (non-blocking)."""
        return any(inbound.ring is not None and inbound.ring.pending
                   for inbound in self._inbound.values())

    def close(self) -> None:
        """Stop listening and tell every writer this end is closed (their ``write()`` returns
        False from now on); idempotent. Detach the reader from its waker first (the waker
        watches its sockets): :meth:`LaneWaker.detach` with ``close=True`` does both."""
        if self._closed:
            return
        self._closed = True
        self._listener.close()
        for fd in list(self._inbound):
            self._drop(fd)


OnMessage = Callable[[bytes], None]


@dataclasses.dataclass
class _Attachment:
    reader: LaneReader
    on_message: OnMessage
    close_reader: bool = False  # a detach request that closes the reader once detached


#: Every waker of this process, for the at-fork hook below
_WAKERS: weakref.WeakSet[LaneWaker] = weakref.WeakSet()


def _forget_waiters_in_child() -> None:
    # The thread waiting in a waker at the fork is the parent's: the child has no such thread,
    # and a close there must not wait for it to let the eventfd go.
    for waker in list(_WAKERS):
        waker._waiter = None
        _ring.Waker.after_fork(waker)


os.register_at_fork(after_in_child=_forget_waiters_in_child)


class LaneWaker(_ring.Waker):
    """The executor's wait primitive (``wait(timeout)`` / ``notify()``) that also wakes for lane
    messages and delivers them on the waiting thread.

    ``notify()`` is the core's own (any thread, one C call). :meth:`attach` / :meth:`detach`
    may be called from any thread; the waiting thread applies them; one thread waits at a time.
    ``busy_poll_s`` > 0: each :meth:`wait` first spins that long (the GIL released, a core at
    100%) checking the rings and notifications, then blocks.

    Raises:
        LaneUnavailableError: no eventfd could be made (out of file descriptors).
    """

    def __init__(self, busy_poll_s: float = 0.0) -> None:
        try:
            super().__init__(_callback_failed, max(0.0, float(busy_poll_s)))
        except (OSError, LaneError) as error:
            hint = out_of_fds_hint(str(error))
            raise LaneUnavailableError(f"no eventfd for the executor's waker ({error})"
                                       + (f": {hint}" if hint else "")) from None
        self._lock = threading.Lock()
        self._pending: list[tuple[bool, _Attachment]] = []  # (attach?, attachment)
        self._attached: dict[int, _Attachment] = {}  # id(reader) -> attachment
        self._by_fd: dict[int, LaneReader] = {}
        self._waiter: int | None = None  # the thread in wait(), if any
        self._released = threading.Event()
        self._closed = False
        _WAKERS.add(self)

    # -- any thread ----------------------------------------------------------------------------
    def attach(self, reader: LaneReader, on_message: OnMessage) -> None:
        """Deliver ``reader``'s messages to ``on_message(bytes)`` on the waiting thread."""
        with self._lock:
            self._pending.append((True, _Attachment(reader, on_message)))
        self.notify()

    def detach(self, reader: LaneReader, close: bool = False) -> None:
        """Stop delivering ``reader``'s messages (applied by the waiting thread, or when the
        waker closes); with ``close``, close the reader once it is detached."""
        with self._lock:
            self._pending.append((False, _Attachment(reader, _ignore, close_reader=close)))
        self.notify()

    def close(self, timeout: float = 1.0) -> None:
        """Release the eventfd (and close the readers detached with ``close``). A thread waiting
        meanwhile is woken and releases it itself; close waits up to ``timeout`` s for that."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            waiter = self._waiter
        if waiter is None:
            self._release()
            return
        self.notify()
        if waiter != threading.get_ident():
            self._released.wait(timeout)

    # -- the waiting thread --------------------------------------------------------------------
    def wait(self, timeout: float | None = None) -> None:
        """Sleep until :meth:`notify`, a lane message (delivered here before returning), or
        ``timeout`` seconds (None: no limit)."""
        with self._lock:
            if self._closed:
                return
            self._waiter = threading.get_ident()
        try:
            if self._pending:  # perf: read without the lock; attach/detach notify after adding
                self._apply_pending()
            events = _core_wait(self, timeout)
            if events:
                self._handle(events)
            if self._pending:  # requests that woke us take effect before we return
                self._apply_pending()
                _core_wait(self, 0)  # frames written before an attachment: delivered now
        finally:
            with self._lock:
                self._waiter = None
                release = self._closed
            if release:
                self._release()

    def _handle(self, events: tuple[tuple[int, int], ...]) -> None:
        changed = False
        for fd, revents in events:
            reader = self._by_fd.get(fd)
            if reader is not None and reader.handle(fd, revents):
                changed = True
        if changed:
            self._rebuild()
            _core_wait(self, 0)  # a new writer's ring may hold frames already: deliver them

    def _apply_pending(self) -> None:
        with self._lock:
            pending, self._pending = self._pending, []
        for attach, attachment in pending:
            reader = attachment.reader
            self._attached.pop(id(reader), None)
            if attachment.close_reader:
                self._rebuild()  # the core lets go of its sockets before they close
                reader.close()
            if attach and reader.listener is not None:
                reader.accept()  # writers that came before the attachment
                self._attached[id(reader)] = attachment
        self._rebuild()

    def _rebuild(self) -> None:
        rings: list[tuple[Any, OnMessage, LaneReader]] = []
        fds: list[tuple[int, int]] = []
        by_fd: dict[int, LaneReader] = {}
        for attachment in self._attached.values():
            reader = attachment.reader
            rings += [(ring, attachment.on_message, reader) for ring in reader.rings()]
            for fd, events in reader.watched():
                fds.append((fd, events))
                by_fd[fd] = reader
        self.watch(rings, fds)
        self._by_fd = by_fd

    def _release(self) -> None:
        with self._lock:
            pending, self._pending = self._pending, []
        self._attached.clear()
        self._by_fd = {}
        _ring.Waker.close(self)
        for _attach, attachment in pending:
            if attachment.close_reader:
                attachment.reader.close()
        self._released.set()


_core_wait = _ring.Waker.wait


def _callback_failed(reader: LaneReader, error: BaseException) -> None:
    """One bad callback must not strand the messages behind it: logged, delivery goes on."""
    _log.error("lane callback of %r failed", reader, exc_info=error)


def _ignore(data: bytes) -> None:
    """The callback of a detach request (never called)."""

"""The same-host fast lane: small messages (descriptor CDR) between processes over iceoryx2.

Zenoh stays the discovery layer and the transport between hosts; between two processes of one
host and user the lane carries what the transport would otherwise put on a subscription's own
Zenoh channel ``<data key>/_buf/<subscriber gid>``: at most :data:`MAX_PAYLOAD` opaque bytes per
message. One iceoryx2 publish-subscribe service (plus an event service of the same name, for the
wake-up) per such channel, created by the subscription's :class:`LaneReader` before it is
announced; a publisher's :class:`LaneWriter` opens it, so opening succeeds exactly when the
subscription is on this host, runs as this user and has the lane on (iceoryx2's files are
owner-only).

Wake-ups are iceoryx2 events, never a poll: :class:`LaneWaker` waits on an iceoryx2 ``WaitSet``
holding every attached reader's listener and an ``eventfd`` that :meth:`LaneWaker.notify`
writes, so one thread (the node's executor, or the user's own ``spin``) sleeps until either a
lane message or anything else (a Zenoh-route delivery, a timer) needs it, and runs the lane
callbacks itself: no extra thread hop. ``LaneWaker(busy_poll_s=...)`` spins that long before it
blocks: lower latency, at the price of a core held at 100% (and the GIL) while it spins.

Turn it off with ``WARP_BUFFER_FAST_LANE=0`` (or ``Node(..., fast_lane=False)``, see
:func:`enabled`). When iceoryx2 is missing or cannot start,
:func:`status` says why (logged once per process) and the transport keeps using Zenoh.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import hashlib
import logging
import os
import queue
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

from . import _iox2
from ._iox2 import ENV_DOMAIN, LaneStartError, cleanup_dead_nodes, resource_prefix
from .errors import PubSubError

__all__ = ["ENV_DOMAIN", "ENV_SWITCH", "MAX_PAYLOAD", "NODE_OPTION", "LaneError",
           "LaneReader", "LaneStatus", "LaneUnavailableError", "LaneWaker", "LaneWriter",
           "cleanup_dead_nodes", "enabled", "resource_prefix", "service_name", "status"]

_log = logging.getLogger(__name__)

#: ``WARP_BUFFER_FAST_LANE=0`` (or ``false``/``off``/``no``) turns the lane off in a process.
ENV_SWITCH = "WARP_BUFFER_FAST_LANE"
#: The ``Node`` keyword that turns the lane on or off per node: ``Node(..., fast_lane=False)``.
NODE_OPTION = "fast_lane"
#: Largest message the lane carries; bigger ones take the Zenoh route. A descriptor is at most
#: 4096 B (rosidl::Buffer's kMaxBufferDescriptorSize); the rest is the message's other fields.
MAX_PAYLOAD = 8192
#: Services and ports a lane service admits: publishers of one topic on this host per subscription.
MAX_WRITERS = 32
#: The deepest keep-last subscription the lane serves: iceoryx2 preallocates its queue (about
#: MAX_PAYLOAD bytes a slot, in /dev/shm), so deeper ones stay on Zenoh, which does not.
MAX_DEPTH = 1024
_OFF = {"0", "false", "off", "no"}
_ON = {"", "1", "true", "on", "yes"}
_warned_values: dict[str, bool] = {}
_string_at = ctypes.string_at
_SERVICE_ROOT = "warp_buffer"


class LaneError(PubSubError, RuntimeError):
    """A fast-lane operation failed (the message says which and why)."""


class LaneUnavailableError(LaneError):
    """The lane cannot be used for this route (iceoryx2 missing, no reader, service full):
    the transport uses Zenoh instead."""


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


_status_lock = threading.Lock()
_probed: dict[int, LaneStatus] = {}  # by pid: a forked child probes again
_logged = False


def status(option: bool | None = None) -> LaneStatus:
    """Whether the lane runs here: wanted (:func:`enabled`), iceoryx2 importable, and this
    process's iceoryx2 node created (which also cleans up dead nodes of our domain). The reason
    it does not is logged once per process."""
    global _logged
    if not enabled(option):
        result = LaneStatus(False, f"turned off ({ENV_SWITCH}=0 or {NODE_OPTION}=False)")
    else:
        with _status_lock:
            result = _probed.get(os.getpid())
            if result is None:
                try:
                    _iox2.process_node()
                    result = LaneStatus(True)
                except LaneStartError as error:
                    result = LaneStatus(False, str(error))
                _probed[os.getpid()] = result
    if not result.available and not _logged:
        _logged = True
        _log.info("fast lane off, Zenoh carries same-host messages: %s", result.reason)
    return result


def service_name(data_key: str, subscriber_gid: bytes) -> str:
    """The iceoryx2 service of the route ``<data_key>/_buf/<subscriber gid>``.

    The Zenoh key itself when it is a valid iceoryx2 service name (printable ASCII, at most 255
    characters), else a SHA-256 of it: both sides derive the same name from the same key.
    """
    name = f"{_SERVICE_ROOT}/{data_key}/_buf/{subscriber_gid.hex()}"
    if len(name) <= 255 and name.isascii() and name.isprintable():
        return name
    return f"{_SERVICE_ROOT}/sha256/{hashlib.sha256(name.encode()).hexdigest()}"


def _services(name: str, create: bool, depth: int) -> tuple[Any, Any]:
    """The publish-subscribe and event services of ``name`` (the reader creates them)."""
    try:
        iox2 = _iox2.load()
        node = _iox2.process_node()
    except LaneStartError as error:
        raise LaneUnavailableError(str(error)) from None
    service = iox2.ServiceName.new(name)
    pubsub = node.service_builder(service).publish_subscribe(iox2.Slice[ctypes.c_uint8])
    event = node.service_builder(service).event()
    if not create:
        return pubsub.open(), event.open()
    pubsub = (pubsub.max_publishers(MAX_WRITERS).max_subscribers(1).history_size(0)
              .subscriber_max_buffer_size(depth).enable_safe_overflow(True).create())
    return pubsub, event.max_notifiers(MAX_WRITERS).max_listeners(1).create()


@contextlib.contextmanager
def _ports_of(owner: Any, failure: str) -> Iterator[None]:
    """Create ``owner``'s ports inside: on an iceoryx2 error, delete what was made and raise
    :class:`LaneUnavailableError` starting with ``failure``; on success, close at exit."""
    try:
        yield
    except LaneUnavailableError:
        owner.close()
        raise
    except Exception as error:  # iceoryx2's open / create errors: no lane for this route
        owner.close()
        raise LaneUnavailableError(f"{failure}: {type(error).__name__}: {error}") from None
    _iox2.track(owner)


def _delete_ports(owner: Any, attributes: tuple[str, ...]) -> None:
    """Take ``owner``'s ports under its lock, then delete them (idempotent)."""
    with owner._lock:
        ports = [getattr(owner, a) for a in attributes]
        for attribute in attributes:
            setattr(owner, attribute, None)
    for port in ports:
        if port is not None:
            port.delete()


class LaneWriter:
    """Publishes messages to one reader's lane service (the publisher side of one route).

    Raises:
        LaneUnavailableError: iceoryx2 does not run here, or no reader created the service
            (the subscription is on another host, runs as another user, or has the lane off),
            or it admits no more writers.
    """

    def __init__(self, name: str, max_payload: int = MAX_PAYLOAD) -> None:
        self.name = name
        self.max_payload = max_payload
        self._lock = threading.Lock()
        self._publisher: Any = None
        self._notifier: Any = None
        with _ports_of(self, f"no lane reader for {name!r}"):
            pubsub, event = _services(name, create=False, depth=0)
            iox2 = _iox2.load()
            # Keep-last: the service's safe overflow drops a full reader's oldest message. Say
            # DiscardData too: iceoryx2's default, RetryUntilDelivered, blocks (GIL held) behind
            # a full reader of any service made without safe overflow.
            self._publisher = (pubsub.publisher_builder().initial_max_slice_len(max_payload)
                               .max_loaned_samples(1)
                               .backpressure_strategy(iox2.BackpressureStrategy.DiscardData)
                               .create())
            self._notifier = event.notifier_builder().create()

    def __repr__(self) -> str:
        return f"LaneWriter({self.name!r})"

    def fits(self, nbytes: int) -> bool:
        """Whether a message of ``nbytes`` can travel on the lane."""
        return nbytes <= self.max_payload

    def write(self, *parts: bytes | bytearray | memoryview) -> bool:
        """Send one message, the concatenation of ``parts`` (e.g. an attachment and a CDR
        payload: joined, then copied into iceoryx2's segment with one ``memmove``; both copies
        are of at most :data:`MAX_PAYLOAD` bytes, cheaper than slicing views in Python), and
        wake the reader; False when no reader is connected any more (the message reached
        nobody).

        Raises:
            LaneError: the message is larger than ``max_payload``, the writer is closed, or
                iceoryx2 failed to loan or send.
        """
        data = parts[0] if len(parts) == 1 and type(parts[0]) is bytes else b"".join(parts)
        nbytes = len(data)
        if nbytes > self.max_payload:
            raise LaneError(f"{nbytes} B message exceeds the lane's {self.max_payload} B")
        with self._lock:
            if self._publisher is None:
                raise LaneError(f"{self!r} is closed")
            try:
                sample = self._publisher.loan_slice_uninit(nbytes)
                if nbytes:
                    ctypes.memmove(sample.payload_ptr, data, nbytes)
                reached = sample.assume_init().send()
                if reached:  # the wake-up (a syscall waking the reader) only when one got it
                    self._notifier.notify()
            except Exception as error:  # LoanError / SendError / NotifierNotifyError
                raise LaneError(f"{self!r}: {type(error).__name__}: {error}") from None
        return bool(reached)

    def close(self) -> None:
        """Delete the ports (idempotent; also run at exit)."""
        _delete_ports(self, ("_notifier", "_publisher"))


class LaneReader:
    """Receives one route's messages (the subscription side); create it before the subscription
    is announced, so that a writer that discovers the subscription finds the service.

    ``depth``: iceoryx2's queue for this reader, keep-last (the oldest message is overwritten
    when the reader falls behind by more than ``depth``).

    Raises:
        LaneUnavailableError: iceoryx2 does not run here or the service cannot be created.
    """

    def __init__(self, name: str, depth: int = 16) -> None:
        self.name = name
        self._lock = threading.Lock()
        self._subscriber: Any = None
        self.listener: Any = None
        with _ports_of(self, f"cannot create lane reader {name!r}"):
            pubsub, event = _services(name, create=True, depth=max(1, depth))
            self._subscriber = pubsub.subscriber_builder().buffer_size(max(1, depth)).create()
            self.listener = event.listener_builder().create()

    def __repr__(self) -> str:
        return f"LaneReader({self.name!r})"

    def take(self) -> bytes | None:
        """The oldest waiting message (copied out, so iceoryx2's sample is released at once),
        or None."""
        with self._lock:
            subscriber = self._subscriber
            sample = None if subscriber is None else subscriber.receive()
            if sample is None:
                return None
            try:
                return _string_at(sample.payload_ptr, sample.header.number_of_elements)
            finally:
                sample.delete()

    def has_samples(self) -> bool:
        """Whether a message waits (non-blocking; for busy-polling)."""
        with self._lock:
            return self._subscriber is not None and self._subscriber.has_samples()

    def consume_events(self) -> bool:
        """Clear the pending wake-ups; True when there were any. Call it after draining, and
        drain again until it says False: see :meth:`LaneWaker._deliver`."""
        with self._lock:
            return self.listener is not None and bool(self.listener.try_wait())

    def close(self) -> None:
        """Delete the ports; iceoryx2 removes the services with their last port. Detach the
        reader from its waker first (the WaitSet watches the listener)."""
        _delete_ports(self, ("listener", "_subscriber"))


OnMessage = Callable[[bytes], None]


@dataclasses.dataclass
class _Attachment:
    reader: LaneReader
    on_message: OnMessage
    guard: Any = None
    close_reader: bool = False  # a detach request that closes the reader once detached


class LaneWaker:
    """The executor's wait primitive (``wait(timeout)`` / ``notify()``) that also wakes for lane
    messages and delivers them on the waiting thread.

    :meth:`attach` / :meth:`detach` may be called from any thread; the waiting thread applies
    them (iceoryx2's WaitSet must not change while a wait runs); one thread waits at a time.
    While no reader is attached (a node with no same-host lane peer yet, or only in-process
    ones) a wait blocks on a ``queue.SimpleQueue`` instead of the WaitSet, as the default
    :class:`~buffer_pubsub._waker.ThreadWaker` does: that wake-up costs ~7-18 us less here.
    ``busy_poll_s`` > 0: each :meth:`wait` first spins that long (a core at 100% and the GIL
    held meanwhile) checking the readers and notifications, then blocks.
    """

    def __init__(self, busy_poll_s: float = 0.0) -> None:
        try:
            self._iox2 = iox2 = _iox2.load()
        except LaneStartError as error:
            raise LaneUnavailableError(str(error)) from None
        self.busy_poll_s = busy_poll_s
        self._lock = threading.Lock()
        self._pending: list[tuple[bool, _Attachment]] = []  # (attach?, attachment)
        self._attached: dict[int, _Attachment] = {}  # id(reader) -> attachment
        self._by_id: dict[Any, _Attachment] = {}  # WaitSetAttachmentId -> attachment
        self._notified = False
        # A wait with nothing attached blocks on this queue, and notify() puts a token there
        # instead of writing the eventfd (both decided under the lock: no wake-up is lost).
        self._queue: queue.SimpleQueue[None] = queue.SimpleQueue()
        self._queue_mode = False
        self._fd_written = False  # the eventfd holds a count that a wake-up must read
        self.lost_wakeups = 0  # messages found by the timeout's check, not by an event
        self._waiter: int | None = None  # the thread in wait(), if any
        self._released = threading.Event()
        self._closed = False
        try:
            self._eventfd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        except OSError as error:  # out of file descriptors: the node runs without the lane
            raise LaneUnavailableError(f"no eventfd for the lane's waker: {error}") from None
        try:
            self._waitset = (iox2.WaitSetBuilder.new()
                             .signal_handling_mode(iox2.SignalHandlingMode.Disabled)
                             .create(iox2.ServiceType.Ipc))
            # Kept: the WaitSet's guard refers to this object without owning it.
            self._wake_fd = iox2.FileDescriptor.non_owning_new(self._eventfd)
            self._wake_guard = self._waitset.attach_notification_fd(self._wake_fd)
            self._wake_id = iox2.WaitSetAttachmentId.from_guard(self._wake_guard)
        except Exception as error:  # WaitSetCreateError (InsufficientResources: fds), ...
            self._wake_guard = self._wake_fd = self._waitset = None
            os.close(self._eventfd)
            raise LaneUnavailableError(
                f"iceoryx2 cannot make the lane's WaitSet: {type(error).__name__}: {error}"
            ) from None
        _iox2.track(self, early=True)

    # -- any thread ----------------------------------------------------------------------------
    def notify(self) -> None:
        """Wake the waiting thread (or make its next wait return at once)."""
        self._notified = True
        if self._waiter == threading.get_ident():
            return  # a lane callback on the waiting thread: wait() sees the flag, no syscall
        with self._lock:  # never write to a closed (and maybe reused) descriptor number
            if self._queue_mode:
                self._queue.put(None)
            elif self._eventfd >= 0:
                os.eventfd_write(self._eventfd, 1)
                self._fd_written = True

    def attach(self, reader: LaneReader, on_message: OnMessage) -> None:
        """Deliver ``reader``'s messages to ``on_message(bytes)`` on the waiting thread."""
        with self._lock:
            self._pending.append((True, _Attachment(reader, on_message)))
        self.notify()

    def detach(self, reader: LaneReader, close: bool = False) -> None:
        """Stop delivering ``reader``'s messages (applied by the waiting thread, or when the
        waker closes); with ``close``, close the reader once it is detached (a reader must not
        be closed while a WaitSet watches its listener)."""
        with self._lock:
            self._pending.append((False, _Attachment(reader, _ignore, close_reader=close)))
        self.notify()

    def close(self, timeout: float = 1.0) -> None:
        """Release the WaitSet and the eventfd. A thread waiting meanwhile is woken and releases
        them itself; close waits up to ``timeout`` s for that (at exit, a wait left running
        would keep the iceoryx2 node, and its files, alive)."""
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
            # Nothing attached and nothing to attach: block on the queue (see notify). Decided
            # here, under the lock notify() takes, so no wake-up is lost in between.
            self._queue_mode = (not self._attached and not self._pending
                                and not self.busy_poll_s)
        try:
            self._apply_pending()
            self._wait_once(timeout)
            self._apply_pending()  # requests that woke us take effect before we return
        finally:
            with self._lock:
                self._waiter = None
                self._queue_mode = False  # also after a KeyboardInterrupt inside the wait
                release = self._closed
            if release:
                self._release()

    def _wait_once(self, timeout: float | None) -> None:
        if timeout is not None:
            # clamped (NaN -> 0): an unrepresentable Duration aborts the process in iceoryx2
            timeout = min(timeout, threading.TIMEOUT_MAX) if timeout > 0 else 0.0
        if self.busy_poll_s > 0 and self._spin(timeout):
            return
        if self._queue_mode:  # set by wait(); reset in its finally
            try:
                if not self._notified:  # read after the mode is set: a notify is seen or queued
                    self._queue.get(timeout=timeout)
            except queue.Empty:
                pass
            self._consume_notification()
            return
        if self._notified:  # notified before we got here: no need to sleep
            self._consume_notification()
            return
        if timeout is None:
            ready, _ = self._waitset.wait_and_process()
        else:
            ready, _ = self._waitset.wait_and_process_with_timeout(
                self._iox2.Duration.from_secs_f64(timeout))
        for attachment_id in ready:
            attachment = self._by_id.get(attachment_id)
            if attachment is not None:
                self._deliver(attachment)
            elif attachment_id == self._wake_id:
                self._fd_written = True  # readable: read it, whatever the flag said
                self._consume_notification()
        if not ready:
            # Timed out (the executor's tick): a safety net for a wake-up iceoryx2 lost (see
            # _deliver), so a message waits at most one tick instead of until the next one.
            for attachment in list(self._attached.values()):
                if attachment.reader.has_samples():
                    self.lost_wakeups += 1
                    _log.debug("lane %r: message found without its wake-up", attachment.reader)
                    self._deliver(attachment)

    def _spin(self, timeout: float | None) -> bool:
        """Busy-poll up to ``busy_poll_s``; True when something was handled."""
        spin = self.busy_poll_s if timeout is None else min(self.busy_poll_s, timeout)
        deadline = time.perf_counter() + spin
        attachments = list(self._attached.values())
        while True:
            if self._notified:
                self._consume_notification()
                return True
            handled = False
            for attachment in attachments:
                if attachment.reader.has_samples():
                    self._deliver(attachment)
                    handled = True
            if handled:
                return True
            if time.perf_counter() >= deadline:
                return False

    def _consume_notification(self) -> None:
        self._notified = False
        if self._fd_written:  # perf: no syscall when every notify went through the queue
            self._fd_written = False
            try:
                os.eventfd_read(self._eventfd)
            except BlockingIOError:  # already consumed
                pass
        while not self._queue.empty():  # tokens of notifies already seen through the flag
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break

    def _deliver(self, attachment: _Attachment) -> None:
        reader = attachment.reader
        on_message = attachment.on_message
        take = reader.take
        while True:
            # Messages first, their wake-ups after: the first callback runs without waiting
            # for a syscall. A message written meanwhile either raised the wake-up consumed
            # below (so we drain again) or raises a later one (the WaitSet wakes us for it).
            while (data := take()) is not None:
                try:
                    on_message(data)
                except Exception:  # one bad callback must not strand the messages behind it
                    _log.exception("lane callback of %r failed", reader)
            # iceoryx2 0.10 skips the wake-up datagram while its listener state says "notified";
            # a notify racing a try_wait can leave that state set with the datagram already
            # consumed, and the next notify would then wake nobody. Ending on a try_wait that
            # found nothing resets the state; one that found something means drain again.
            if not reader.consume_events():
                return

    def _apply_pending(self) -> None:
        if not self._pending:  # perf: read without the lock; attach/detach notify after adding
            return
        with self._lock:
            pending, self._pending = self._pending, []
        for attach, attachment in pending:
            key = id(attachment.reader)
            old = self._attached.pop(key, None)
            if old is not None:
                self._forget(old)
            if attachment.close_reader:
                attachment.reader.close()
            if not attach or attachment.reader.listener is None:
                continue
            attachment.guard = self._waitset.attach_notification(attachment.reader.listener)
            self._by_id[self._iox2.WaitSetAttachmentId.from_guard(attachment.guard)] = attachment
            self._attached[key] = attachment
            # Messages written before the attachment raised no event this WaitSet saw.
            self._deliver(attachment)

    def _forget(self, attachment: _Attachment) -> None:
        self._by_id = {k: v for k, v in self._by_id.items() if v is not attachment}
        if attachment.guard is not None:
            attachment.guard.delete()
            attachment.guard = None

    def _release(self) -> None:
        with self._lock:
            pending, self._pending = self._pending, []
        for _attach, attachment in pending:
            if attachment.close_reader:
                attachment.reader.close()
        for attachment in list(self._attached.values()):
            self._forget(attachment)
        self._attached.clear()
        self._wake_guard.delete()
        self._waitset.delete()
        with self._lock:
            fd, self._eventfd = self._eventfd, -1
        os.close(fd)
        self._released.set()


def _ignore(data: bytes) -> None:
    """The callback of a detach request (never called)."""

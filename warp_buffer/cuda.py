"""CUDA primitives of warp_buffer: checked IPC opens, handle caches, stream-ordered release and
reuse, the stream a write ran on, device identity, IPC-exportable allocation, pinned staging and
VMM (exporter-independent) memory.

The IPC core (pool, export, import) calls these; nothing here knows descriptors or pools, so each
piece can be tested alone (the bookkeeping on the cpu device, with fake events).

Why each piece exists (read against Warp 1.19's source):

- **Checked opens.** ``wp.from_ipc_handle`` passes the pointer ``cuIpcOpenMemHandle`` gave to
  ``wp.array(ptr=...)``; on failure that pointer is NULL and ``wp.array(ptr=None)`` allocates
  fresh, uninitialised memory. ``wp.event_from_ipc_handle`` on failure builds a *new*,
  never-recorded event, so waiting on it orders nothing. :func:`open_ipc_memory` and
  :func:`open_ipc_event` call the native opens themselves and raise :class:`StaleBufferError`.
- **One open per (publisher session, block).** A CUDA IPC memory handle may be opened once per
  context; opening costs tens of microseconds. :class:`ImportCache` keeps each open mapping and
  event and hands the same one out again (weakly once evicted, so a mapping still viewed is
  never opened twice).
- **Stream-ordered reuse.** :class:`BlockUses` keeps, per block, one last-use event per stream
  that read or wrote it (torch's ``record_stream``, CUDA's stream-ordered allocators); a block
  is reusable when every such event completed (:func:`ready_for_reuse`), or a new writer's stream
  is ordered after them on the device (:meth:`BlockUses.order_after`). A reader in another
  process drops its hold on a block only once its release event completed
  (:class:`ReleaseQueue`), so the publisher never recycles memory a reader's kernel still reads.
- **The stream a write ran on.** Torch writes on torch's current stream, Warp on Warp's; they are
  the same only on torch's legacy default stream. :func:`write_stream` joins torch's current
  stream into Warp's on the device (no host wait) so one event covers both.
- **Device identity by UUID.** MIG instances share a PCI bus id; :func:`find_device` matches
  ``wp.Device.uuid``.
- **Allocation.** :func:`alloc_ipc_memory` takes each IPC-exportable block straight from Warp's
  default (``cudaMalloc``) allocator, per allocation: no ``ScopedMempool`` flip (global, racy) and
  no user-set allocator in the way (``wp.set_device_allocator``), whose memory
  ``array.ipc_handle()`` refuses with a ``RuntimeError``. :func:`ipc_mem_handle` raises
  :class:`ExportUnavailableError` for memory it cannot export, so the caller falls back to
  staging.
- **Staging.** :func:`stage_to_host` copies device memory into pinned (page-locked) host memory
  asynchronously and returns the completion event; :func:`register_host_memory` pins an existing
  host mapping (a shared-memory arena) so the staging copy lands in memory peers map.
- **VMM.** :class:`VmmMemory` is device memory from ``cuMemCreate``, exported as a POSIX file
  descriptor (``cuMemExportToShareableHandle``) that travels over a Unix socket like the cpu
  arenas, imported (``cuMemImportFromShareableHandle``) and mapped read-only
  (``cuMemSetAccess`` with ``PROT_READ``). The importer's handle keeps the physical memory alive
  after the exporter exits, unlike legacy CUDA IPC memory, which dies with the exporting process
  and is mapped writable. It uses the CUDA driver API through ``ctypes`` (``libcuda.so.1``), no
  new dependency.

None of this has run on a GPU in the session that wrote it (none was lent); see
``benchmarks/gpu_check.py`` for the checks that exercise it on one.
"""

from __future__ import annotations

import collections
import ctypes
import itertools
import logging
import os
import sys
import threading
import time
import weakref
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any

import warp as wp

from .errors import (  # DeviceMemoryError / CudaDriverError are re-exported (they began here)
    CudaDriverError,
    DescriptorError,
    DeviceMemoryError,
    DeviceUnavailableError,
    ExportUnavailableError,
    StaleBufferError,
)

__all__ = [
    "IPC_HANDLE_SIZE",
    "DeviceMemoryError",
    "CudaDriverError",
    "DeviceCapabilities",
    "capabilities",
    "find_device",
    "alloc_ipc_memory",
    "is_ipc_allocation",
    "ipc_mem_handle",
    "new_ipc_event",
    "ipc_event_handle",
    "open_ipc_memory",
    "open_ipc_event",
    "ImportCache",
    "BlockUses",
    "record_use",
    "ready_for_reuse",
    "ReleaseQueue",
    "release_after",
    "flush_releases",
    "torch_current_stream",
    "stream_from_handle",
    "stream_from_dlpack",
    "write_stream",
    "pinned_host_array",
    "register_host_memory",
    "HostRegistration",
    "stage_to_host",
    "vmm_supported",
    "vmm_granularity",
    "VmmMemory",
]

_log = logging.getLogger(__name__)

#: Bytes of a CUDA IPC memory or event handle.
IPC_HANDLE_SIZE = 64


def _runtime() -> Any:
    wp.init()
    return wp._src.context.runtime


def _native_error() -> str:
    try:
        return _runtime().get_error_string() or "no error message"
    except Exception:  # pragma: no cover - only while the interpreter shuts down
        return "no error message"


def _cuda_device(device: Any) -> Any:
    from .buffer_impl import resolve_device  # (buffer_impl imports this module)

    device = resolve_device(device)
    if not device.is_cuda:
        raise ExportUnavailableError(f"{device.alias} is not a CUDA device")
    return device


def _ipc_device(device: Any) -> Any:
    device = _cuda_device(device)
    if not device.is_ipc_supported:
        raise ExportUnavailableError(f"{device.alias} does not support CUDA IPC")
    return device


# ------------------------------------------------------------------------------ device identity
@dataclass(frozen=True)
class DeviceCapabilities:
    """What one CUDA device offers the IPC paths (``capabilities("cuda:0")``)."""

    alias: str
    name: str
    uuid: str
    pci_bus_id: str
    ipc: bool  # legacy CUDA IPC (cuIpc*Handle)
    mempool_supported: bool
    mempool_enabled: bool  # Warp's current allocator for the device is the mempool one
    custom_allocator: bool  # a user-set allocator (wp.set_device_allocator) is active
    vmm: bool  # cuMemCreate and a POSIX fd export (exporter-independent lifetime)


def capabilities(device: Any) -> DeviceCapabilities:
    """The IPC-relevant capabilities of CUDA ``device``."""
    device = _cuda_device(device)
    return DeviceCapabilities(
        alias=device.alias, name=device.name, uuid=device.uuid or "",
        pci_bus_id=device.pci_bus_id or "", ipc=bool(device.is_ipc_supported),
        mempool_supported=bool(device.is_mempool_supported),
        mempool_enabled=bool(device.is_mempool_enabled),
        custom_allocator=getattr(device, "_custom_allocator", None) is not None,
        vmm=vmm_supported(device),
    )


def find_device(uuid: str, devices: list[Any] | None = None) -> Any:
    """The local CUDA device whose UUID is ``uuid`` (``wp.Device.uuid``; Warp reads it with
    ``cuDeviceGetUuid_v2``, which gives each MIG instance its own). Matching by PCI bus id is
    wrong: MIG instances of one GPU share it.

    Raises :class:`ExportUnavailableError` when no local device has that UUID.
    """
    if not isinstance(uuid, str) or not uuid:
        raise DescriptorError(f"a CUDA device uuid must be a non-empty string, not {uuid!r}")
    for device in wp.get_cuda_devices() if devices is None else devices:
        if device.uuid == uuid:
            return device
    raise ExportUnavailableError(f"no local CUDA device has uuid {uuid!r}")


# ------------------------------------------------------------------------------ allocation
class _DefaultFree:
    """Deleter of an :func:`alloc_ipc_memory` array: gives the memory back to ``cudaFree``
    (Warp defers the free while a graph capture is running)."""

    __slots__ = ("context", "__weakref__")

    def __init__(self, context: Any) -> None:
        self.context = context

    def __call__(self, ptr: int, size: int = 0) -> None:
        context, self.context = self.context, None
        if context is not None and not sys.is_finalizing():
            _runtime().core.wp_free_device_default(context, ptr)


def alloc_ipc_memory(device: Any, nbytes: int) -> wp.array:
    """``nbytes`` of device memory that CUDA IPC can export, as a 1-D uint8 ``wp.array``.

    The memory comes from ``cudaMalloc`` (Warp's default allocator) for this allocation only:
    the device's current allocator (mempool, or one the user set) is neither consulted nor
    changed, so other threads' allocations are unaffected. Freed when the array is collected.
    Raises :class:`DeviceMemoryError` when the device is out of memory.
    """
    device = _cuda_device(device)
    if nbytes <= 0:
        raise ValueError(f"an allocation holds at least one byte, not {nbytes}")
    core = _runtime().core
    ptr = core.wp_alloc_device_default(device.context, nbytes, None)
    if not ptr:
        raise DeviceMemoryError(f"cannot allocate {nbytes} bytes on {device.alias}: "
                                f"{_native_error()}")
    return wp.array(ptr=ptr, dtype=wp.uint8, shape=(nbytes,), device=device,
                    deleter=_DefaultFree(device.context))


def is_ipc_allocation(array: wp.array) -> bool:
    """Is ``array`` a whole allocation CUDA IPC can export (from :func:`alloc_ipc_memory`, or
    Warp's default allocator)?"""
    if array.device is None or not array.device.is_cuda:
        return False
    if isinstance(getattr(array, "deleter", None), _DefaultFree):
        return True
    kinds = wp._src.context
    return (isinstance(getattr(array, "_allocator", None), kinds.CudaDefaultAllocator)
            and getattr(array, "_ref", None) is None)


def ipc_mem_handle(array: wp.array) -> bytes:
    """The 64-byte CUDA IPC handle of ``array``'s allocation.

    Raises :class:`ExportUnavailableError` (never a bare ``RuntimeError``) when it cannot be
    exported: not CUDA, no IPC on the device, a mempool / managed / user-allocator / foreign
    allocation, or a view into one. The caller then stages the bytes instead.
    """
    device = array.device
    if device is None or not device.is_cuda:
        raise ExportUnavailableError("CUDA IPC needs a CUDA array")
    if not device.is_ipc_supported:
        raise ExportUnavailableError(f"{device.alias} does not support CUDA IPC")
    if not is_ipc_allocation(array):
        raise ExportUnavailableError(
            f"this {device.alias} array is not a whole default-allocator allocation (mempool, "
            "managed, user-set allocator, foreign memory or a view): CUDA IPC cannot export it")
    out = (ctypes.c_char * IPC_HANDLE_SIZE)()
    _runtime().core.wp_cuda_ipc_get_mem_handle(array.ptr, out)
    if out.raw == bytes(IPC_HANDLE_SIZE):
        raise ExportUnavailableError(f"cuIpcGetMemHandle failed on {device.alias}: "
                                     f"{_native_error()}")
    return out.raw


def new_ipc_event(device: Any) -> wp.Event:
    """A new interprocess CUDA event on ``device`` (timing disabled, as IPC requires)."""
    return wp.Event(_ipc_device(device), interprocess=True)


def ipc_event_handle(event: wp.Event) -> bytes:
    """The 64-byte IPC handle of interprocess ``event``; :class:`ExportUnavailableError` if it
    has none (not created interprocess, or the device lacks IPC)."""
    if not event.device.is_ipc_supported:
        raise ExportUnavailableError(f"{event.device.alias} does not support CUDA IPC")
    out = (ctypes.c_char * IPC_HANDLE_SIZE)()
    _runtime().core.wp_cuda_ipc_get_event_handle(event.device.context, event.cuda_event, out)
    if out.raw == bytes(IPC_HANDLE_SIZE):
        raise ExportUnavailableError("this event has no IPC handle (create it with "
                                     f"new_ipc_event): {_native_error()}")
    return out.raw


# ------------------------------------------------------------------------------ checked opens
def _check_handle(handle: bytes, what: str) -> bytes:
    if not isinstance(handle, (bytes, bytearray)):
        raise DescriptorError(f"a CUDA IPC {what} handle is bytes, not {type(handle).__name__}")
    if len(handle) != IPC_HANDLE_SIZE:
        raise DescriptorError(f"a CUDA IPC {what} handle is {IPC_HANDLE_SIZE} bytes, not "
                              f"{len(handle)}")
    if not any(handle):
        raise DescriptorError(f"an all-zero CUDA IPC {what} handle")
    return bytes(handle)


def _close_ipc_memory(ptr: int, size: int = 0) -> None:
    if not sys.is_finalizing():
        _runtime().core.wp_cuda_ipc_close_mem_handle(ptr)


def open_ipc_memory(handle: bytes, nbytes: int, device: Any) -> wp.array:
    """Open another process's allocation from its CUDA IPC ``handle`` as a 1-D uint8 array of
    ``nbytes`` on ``device``; closed (``cuIpcCloseMemHandle``) when the array is collected.

    Raises :class:`StaleBufferError` when the open fails (the exporter exited or freed it, a
    forged handle), instead of returning fresh memory as ``wp.from_ipc_handle`` does.
    """
    handle = _check_handle(handle, "memory")
    device = _ipc_device(device)
    ptr = _runtime().core.wp_cuda_ipc_open_mem_handle(device.context, handle)
    if not ptr:
        raise StaleBufferError(f"cannot open a CUDA IPC memory handle on {device.alias} (the "
                               f"exporting process exited or freed it?): {_native_error()}")
    return wp.array(ptr=ptr, dtype=wp.uint8, shape=(nbytes,), device=device,
                    deleter=_close_ipc_memory)


def open_ipc_event(handle: bytes, device: Any) -> wp.Event:
    """Open another process's interprocess event from its IPC ``handle``.

    Raises :class:`StaleBufferError` when the open fails, instead of returning a new event that
    was never recorded (``wp.event_from_ipc_handle``), whose wait would order nothing.
    """
    handle = _check_handle(handle, "event")
    device = _ipc_device(device)
    raw = _runtime().core.wp_cuda_ipc_open_event_handle(device.context, handle)
    if not raw:
        raise StaleBufferError(f"cannot open a CUDA IPC event handle on {device.alias}: "
                               f"{_native_error()}")
    event = wp.Event(device=device, cuda_event=raw)
    event.owner = True  # an opened IPC event is destroyed with cuEventDestroy
    return event


class _Entry:
    __slots__ = ("handle", "value")

    def __init__(self, handle: bytes, value: Any) -> None:
        self.handle = handle
        self.value = value


class ImportCache:
    """Imported CUDA memory and events, one open per (publisher session, block).

    ``memory()`` / ``event()`` return the cached object for a key whose handle is unchanged, and
    open (through ``open_memory`` / ``open_event``, injectable for tests) otherwise. At most
    ``max_entries`` of each are kept, least recently used dropped first; a dropped entry stays
    reachable while anything still uses it (a weak reference), so a handle is never opened
    twice while mapped. A mapping closes when the cache dropped it and its last view is gone.
    Thread-safe.
    """

    def __init__(self, open_memory: Callable[[bytes, int, Any], Any] = open_ipc_memory,
                 open_event: Callable[[bytes, Any], Any] = open_ipc_event,
                 max_entries: int = 1024) -> None:
        self._open_memory = open_memory
        self._open_event = open_event
        self._max = max(1, int(max_entries))
        self._lock = threading.Lock()
        self._strong: dict[str, collections.OrderedDict[Hashable, _Entry]] = {
            "memory": collections.OrderedDict(), "event": collections.OrderedDict()}
        self._weak: dict[str, dict[Hashable, tuple[bytes, weakref.ref]]] = {
            "memory": {}, "event": {}}
        self.opens = 0  # handles opened (a test and benchmark counter)

    def memory(self, session: Hashable, block: Hashable, handle: bytes, nbytes: int,
               device: Any, opener: Callable[[], Any] | None = None) -> Any:
        """The opened allocation of ``block`` of publisher ``session`` (a ``wp.array``);
        ``opener`` (default: open ``handle`` as CUDA IPC memory) opens it when not cached, e.g.
        a VMM import whose ``handle`` words only identify the allocation."""
        return self._get("memory", (session, block), handle,
                         opener or (lambda: self._open_memory(handle, nbytes, device)))

    def event(self, session: Hashable, block: Hashable, handle: bytes, device: Any) -> Any:
        """The opened interprocess event of ``block`` of publisher ``session``."""
        return self._get("event", (session, block), handle,
                         lambda: self._open_event(handle, device))

    def _get(self, kind: str, key: Hashable, handle: bytes, opener: Callable[[], Any]) -> Any:
        handle = bytes(handle)
        with self._lock:
            strong, weak = self._strong[kind], self._weak[kind]
            entry = strong.get(key)
            if entry is not None and entry.handle == handle:
                strong.move_to_end(key)
                return entry.value
            known = weak.get(key)
            value = known[1]() if known is not None and known[0] == handle else None
            if value is None:
                value = opener()  # raises StaleBufferError: nothing is cached then
                self.opens += 1
                weak[key] = (handle, weakref.ref(value, self._forget(kind, key)))
            strong[key] = _Entry(handle, value)
            strong.move_to_end(key)
            while len(strong) > self._max:
                strong.popitem(last=False)
            return value

    def _forget(self, kind: str, key: Hashable) -> Callable[[Any], None]:
        weak = self._weak[kind]

        def forget(ref: weakref.ref) -> None:
            # Runs at collection, maybe under our lock on this thread: no locking here.
            known = weak.get(key)
            if known is not None and known[1] is ref:
                weak.pop(key, None)
        return forget

    def drop(self, session: Hashable, block: Hashable | None = None) -> int:
        """Forget the entries of ``session`` (one ``block`` of it, or all); returns how many.
        Their mappings close once nothing views them."""
        return len(self.take(session, block))

    def take(self, session: Hashable, block: Hashable | None = None) -> list[Any]:
        """Forget the entries of ``session`` (one ``block`` of it, or all) and return their
        opened objects, so the caller decides when the cache's references go (a close ordered
        after the streams that may still read them)."""
        taken = []
        with self._lock:
            for strong in self._strong.values():
                doomed = [k for k in strong if k[0] == session and (block is None or k[1] == block)]
                for key in doomed:
                    taken.append(strong.pop(key).value)
        return taken

    def clear(self) -> None:
        with self._lock:
            for strong in self._strong.values():
                strong.clear()

    def __len__(self) -> int:
        with self._lock:
            return sum(len(s) for s in self._strong.values())


# ------------------------------------------------------------------------------ reuse ordering
def _new_event(device: Any) -> wp.Event:
    return wp.Event(device)


class BlockUses:
    """The last-use events of one block: one per stream that used it since it was last free.

    ``record_use(stream)`` records (or re-records) that stream's event after the work enqueued
    so far; a later record on the same stream supersedes the earlier one (streams run in order).
    ``ready_for_reuse()`` is True once every recorded event completed; ``order_after(stream)``
    makes ``stream`` wait for them on the device instead (no host wait). ``event_factory``
    (default ``wp.Event``) and the stream objects are duck-typed: tests use fakes.
    """

    __slots__ = ("_events", "_factory", "_lock", "_noted")

    def __init__(self, event_factory: Callable[[Any], Any] = _new_event) -> None:
        self._events: dict[Any, Any] = {}  # stream key -> event
        self._factory = event_factory
        self._lock = threading.Lock()
        # (stream key, event) recorded by note() without the lock, merged under it
        self._noted: collections.deque[tuple[Any, Any]] = collections.deque()

    @staticmethod
    def _key(stream: Any) -> Any:
        return (id(stream.device), int(stream.cuda_stream or 0))

    def _merge(self) -> None:  # under the lock: a noted use supersedes an earlier one
        noted = self._noted
        while noted:
            key, event = noted.popleft()
            self._events[key] = event

    def record_use(self, stream: Any) -> None:
        if stream is None:
            return  # cpu work is synchronous: done when it returned
        key = self._key(stream)
        with self._lock:
            self._merge()
            event = self._events.get(key)
            if event is None:
                event = self._events[key] = self._factory(stream.device)
            stream.record_event(event)

    def note(self, stream: Any) -> None:
        """:meth:`record_use` from a finalizer (a read handle collected): a new event recorded
        now, handed over through a lock-free queue."""
        if stream is not None:
            self._noted.append((self._key(stream), stream.record_event()))

    def ready_for_reuse(self) -> bool:
        with self._lock:
            self._merge()
            done = [key for key, event in self._events.items() if event.is_complete]
            for key in done:
                del self._events[key]
            return not self._events

    def order_after(self, stream: Any) -> None:
        """Make ``stream``'s later work wait for every recorded use (device-side)."""
        with self._lock:
            self._merge()
            for event in self._events.values():
                stream.wait_event(event)

    @property
    def pending(self) -> int:
        with self._lock:
            self._merge()
            return len(self._events)


def _uses_of(block: Any) -> BlockUses:
    uses = getattr(block, "cuda_uses", None)
    if uses is None:
        uses = BlockUses()
        block.cuda_uses = uses
    return uses


def record_use(block: Any, stream: Any) -> None:
    """Record that work on ``stream`` used ``block`` (a reader's release, a clone's copy): the
    block is not reused before that work completed. Keeps the events in ``block.cuda_uses``."""
    _uses_of(block).record_use(stream)


def note_use(block: Any, stream: Any) -> None:
    """:func:`record_use` without a lock, for a finalizer (see :meth:`BlockUses.note`)."""
    uses = getattr(block, "cuda_uses", None)
    if uses is None:  # (created once; a racing creator's use lands in the one kept)
        uses = BlockUses()
        if getattr(block, "cuda_uses", None) is None:
            block.cuda_uses = uses
        uses = block.cuda_uses
    uses.note(stream)


def ready_for_reuse(block: Any) -> bool:
    """True when every use recorded on ``block`` completed (or none was recorded)."""
    uses = getattr(block, "cuda_uses", None)
    return True if uses is None else uses.ready_for_reuse()


class ReleaseQueue:
    """Callbacks that run once their event completed, off the caller's thread.

    A reader in another process ``defer``s dropping its hold on a block (its lock, its mapping)
    until the release event recorded on its stream completed, so the publisher sees the hold
    go only after the reader's kernels finished with the bytes. A daemon thread, started by the
    first deferral, polls the pending events (every ``poll_s``) while there are any and sleeps
    on an eventfd otherwise; :meth:`poll` runs what is ready on the caller's thread, and
    :meth:`flush` waits for everything (shutdown). ``defer`` takes no lock (it runs from token
    finalizers): an atomic queue append and an eventfd write.
    """

    def __init__(self, poll_s: float = 0.0002) -> None:
        self._poll_s = poll_s
        self._incoming: collections.deque[tuple[Any, Callable[[], None]]] = collections.deque()
        self._pending: list[tuple[Any, Callable[[], None]]] = []  # under _lock
        self._lock = threading.Lock()
        self._starts = itertools.count()  # the first deferral (ticket 0) starts the thread
        self._wake = -1  # the thread's eventfd, once it runs

    def defer(self, event: Any, callback: Callable[[], None]) -> None:
        if event is None or event.is_complete:
            callback()
            return
        self._incoming.append((event, callback))  # deque appends are atomic
        if next(self._starts) == 0:
            self._wake = os.eventfd(0, os.EFD_CLOEXEC)
            threading.Thread(target=self._run, daemon=True,
                             name="warp_buffer-cuda-release").start()
        elif self._wake >= 0:
            os.eventfd_write(self._wake, 1)

    def poll(self) -> int:
        """Run the callbacks whose events completed; returns how many ran."""
        with self._lock:
            while self._incoming:
                self._pending.append(self._incoming.popleft())
            ready, keep = [], []
            for item in self._pending:
                (ready if item[0].is_complete else keep).append(item)
            self._pending = keep
        for _event, callback in ready:
            try:
                callback()
            except Exception:  # a failing release must not stop the others
                _log.exception("warp_buffer: a deferred CUDA release failed")
        return len(ready)

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until every pending callback ran (True) or ``timeout`` passed (False)."""
        deadline = time.monotonic() + timeout
        while True:
            self.poll()
            if not len(self):
                return True
            if time.monotonic() > deadline:
                return False
            time.sleep(self._poll_s)

    def __len__(self) -> int:
        return len(self._pending) + len(self._incoming)

    def _run(self) -> None:
        while True:
            self.poll()
            if len(self):
                time.sleep(self._poll_s)
            else:  # idle: a deferral writes the eventfd (counts add up: no wake-up is lost)
                os.eventfd_read(self._wake)


_release_queue = ReleaseQueue()


def _after_fork_in_child() -> None:
    # The parent's release thread is not the child's: the child's first deferral starts its own.
    _release_queue._starts = itertools.count()
    _release_queue._wake = -1


os.register_at_fork(after_in_child=_after_fork_in_child)


def flush_releases(timeout: float = 5.0) -> bool:
    """Wait for every release deferred by :func:`release_after` (a clean shutdown calls this
    before closing what the callbacks release); False if some did not complete in time."""
    return _release_queue.flush(timeout)


def release_after(stream: Any, callback: Callable[[], None],
                  queue: ReleaseQueue | None = None, event: Any = None) -> None:
    """Run ``callback`` once the work enqueued on ``stream`` so far completed: records
    ``event`` (a new one if None) on ``stream`` and defers ``callback`` to ``queue`` (the
    module's). With ``stream`` None (cpu), runs it now."""
    if stream is None:
        callback()
        return
    event = stream.record_event(event)
    (queue if queue is not None else _release_queue).defer(event, callback)


# ------------------------------------------------------------------------------ streams
_stream_cache: collections.OrderedDict[tuple[int, int], wp.Stream] = collections.OrderedDict()
_stream_cache_lock = threading.Lock()
_STREAM_CACHE_MAX = 64


def stream_from_handle(cuda_stream: int, device: Any, keep: Any = None) -> wp.Stream:
    """A ``wp.Stream`` over the external CUDA stream handle ``cuda_stream`` (0: the legacy
    default stream) of ``device``, cached so a message does not register a stream each time.
    ``keep`` (the framework's stream object) stays referenced while the wrapper is cached, so
    its handle cannot be reused by another stream meanwhile."""
    device = _cuda_device(device)
    key = (device.ordinal, int(cuda_stream))
    with _stream_cache_lock:
        stream = _stream_cache.get(key)
        if stream is not None:
            _stream_cache.move_to_end(key)
            return stream
        stream = wp.Stream(device, cuda_stream=int(cuda_stream))
        stream._warp_buffer_keep = keep
        _stream_cache[key] = stream
        while len(_stream_cache) > _STREAM_CACHE_MAX:
            _stream_cache.popitem(last=False)
        return stream


def torch_current_stream(device: Any) -> wp.Stream | None:
    """Torch's current stream on CUDA ``device`` as a ``wp.Stream``, or None when torch is not
    imported or has not initialised CUDA (then torch has written nothing on that device)."""
    torch = sys.modules.get("torch")
    if torch is None:
        return None
    try:
        if not torch.cuda.is_initialized():
            return None
        device = _cuda_device(device)
        current = torch.cuda.current_stream(device.ordinal)
    except Exception:
        return None
    return stream_from_handle(current.cuda_stream, device, keep=current)


#: DLPack's ``stream`` values for CUDA (the array API standard): 1 the legacy default stream,
#: 2 the per-thread default stream; -1 "no synchronisation"; other values are stream handles.
_DLPACK_LEGACY, _DLPACK_PER_THREAD, _CU_STREAM_PER_THREAD = 1, 2, 0x2


def stream_from_dlpack(stream: int | None, device: Any) -> wp.Stream | None:
    """The consumer stream a ``__dlpack__(stream=...)`` call names, as a ``wp.Stream`` (None for
    -1: the consumer asked for no ordering). None means the legacy default stream."""
    if stream == -1:
        return None
    if stream is None or stream == _DLPACK_LEGACY:
        return stream_from_handle(0, device)
    if stream == _DLPACK_PER_THREAD:
        return stream_from_handle(_CU_STREAM_PER_THREAD, device)
    if isinstance(stream, bool) or not isinstance(stream, int) or stream < 0:
        raise ValueError(f"not a DLPack CUDA stream: {stream!r}")
    return stream_from_handle(stream, device)


def write_stream(device: Any, stream: Any = None) -> wp.Stream:
    """The stream on which a write to ``device`` is complete once its work is.

    ``stream`` given: that one. Otherwise Warp's current stream, joined on the device with
    torch's current stream when torch uses another one (``wait_stream``: no host wait), so an
    event recorded on the result covers writes made by Warp and by torch alike.
    """
    if stream is not None:
        return stream
    device = _cuda_device(device)
    warp_stream = device.stream
    torch_stream = torch_current_stream(device)
    if torch_stream is not None and int(torch_stream.cuda_stream or 0) != int(
            warp_stream.cuda_stream or 0):
        warp_stream.wait_stream(torch_stream)
    return warp_stream


# ------------------------------------------------------------------------------ staging
def pinned_host_array(nbytes: int) -> wp.array:
    """``nbytes`` of pinned (page-locked) host memory: device-to-host copies into it are
    asynchronous and run at the link's speed."""
    return wp.empty(nbytes, dtype=wp.uint8, device="cpu", pinned=True)


def stage_to_host(src: wp.array, dst: wp.array, stream: Any = None,
                  event: Any = None) -> Any:
    """Enqueue the copy of CUDA ``src`` into host ``dst`` on ``stream`` (default: Warp's current
    stream of ``src``'s device) and return the event that completes with it. Nothing waits:
    the caller hands the event to whoever must know (``ReleaseQueue.defer`` to send the
    descriptor once the bytes are there, or ``event.synchronize`` where a blocking wait is
    wanted). ``dst`` must be pinned (:func:`pinned_host_array`, :func:`register_host_memory`)
    for the copy to be asynchronous; with pageable memory CUDA completes it before returning.
    """
    if not src.device.is_cuda or not dst.device.is_cpu:
        raise ValueError(f"stage_to_host copies CUDA to cpu, not {src.device} to {dst.device}")
    nbytes = src.shape[0] * wp.types.type_size_in_bytes(src.dtype)
    if dst.shape[0] * wp.types.type_size_in_bytes(dst.dtype) != nbytes:
        raise ValueError("stage_to_host: source and destination sizes differ")
    stream = stream if stream is not None else src.device.stream
    wp.copy(dst, src, stream=stream)
    return stream.record_event(event)


# ------------------------------------------------------------------------------ CUDA driver
_CU_MEM_ALLOCATION_TYPE_PINNED = 0x1
_CU_MEM_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR = 0x1
_CU_MEM_LOCATION_TYPE_DEVICE = 0x1
_CU_MEM_ACCESS_FLAGS_PROT_READ = 0x1
_CU_MEM_ACCESS_FLAGS_PROT_READWRITE = 0x3
_CU_MEM_ALLOC_GRANULARITY_MINIMUM = 0x0
_CU_DEVICE_ATTRIBUTE_VIRTUAL_MEMORY_MANAGEMENT_SUPPORTED = 102
_CU_DEVICE_ATTRIBUTE_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR_SUPPORTED = 103
_CU_MEMHOSTREGISTER_PORTABLE = 0x1
_CUDA_ERROR_OUT_OF_MEMORY = 2


class _MemLocation(ctypes.Structure):
    _fields_ = [("type", ctypes.c_int), ("id", ctypes.c_int)]


class _AllocFlags(ctypes.Structure):
    _fields_ = [("compressionType", ctypes.c_ubyte), ("gpuDirectRDMACapable", ctypes.c_ubyte),
                ("usage", ctypes.c_ushort), ("reserved", ctypes.c_ubyte * 4)]


class _MemAllocationProp(ctypes.Structure):
    """``CUmemAllocationProp`` (cuda.h, CUDA 11.0 to 13.0: 32 bytes)."""

    _fields_ = [("type", ctypes.c_int), ("requestedHandleTypes", ctypes.c_int),
                ("location", _MemLocation), ("win32HandleMetaData", ctypes.c_void_p),
                ("allocFlags", _AllocFlags)]


class _MemAccessDesc(ctypes.Structure):
    """``CUmemAccessDesc`` (12 bytes)."""

    _fields_ = [("location", _MemLocation), ("flags", ctypes.c_int)]


_u64 = ctypes.c_ulonglong
_size = ctypes.c_size_t
_DRIVER_SIGNATURES: dict[str, list[Any]] = {
    "cuGetErrorString": [ctypes.c_int, ctypes.POINTER(ctypes.c_char_p)],
    "cuDeviceGetAttribute": [ctypes.POINTER(ctypes.c_int), ctypes.c_int, ctypes.c_int],
    "cuMemGetAllocationGranularity": [ctypes.POINTER(_size),
                                      ctypes.POINTER(_MemAllocationProp), ctypes.c_int],
    "cuMemCreate": [ctypes.POINTER(_u64), _size, ctypes.POINTER(_MemAllocationProp), _u64],
    "cuMemRelease": [_u64],
    "cuMemExportToShareableHandle": [ctypes.c_void_p, _u64, ctypes.c_int, _u64],
    "cuMemImportFromShareableHandle": [ctypes.POINTER(_u64), ctypes.c_void_p, ctypes.c_int],
    "cuMemAddressReserve": [ctypes.POINTER(_u64), _size, _size, _u64, _u64],
    "cuMemAddressFree": [_u64, _size],
    "cuMemMap": [_u64, _size, _size, _u64, _u64],
    "cuMemUnmap": [_u64, _size],
    "cuMemSetAccess": [_u64, _size, ctypes.POINTER(_MemAccessDesc), _size],
    "cuMemHostRegister_v2": [ctypes.c_void_p, _size, ctypes.c_uint],
    "cuMemHostUnregister": [ctypes.c_void_p],
}
_driver_lib: Any = None
_driver_lock = threading.Lock()


def _driver() -> Any:
    """``libcuda.so.1`` with the signatures above; :class:`CudaDriverError` without a driver."""
    global _driver_lib
    with _driver_lock:
        if _driver_lib is None:
            try:
                lib = ctypes.CDLL("libcuda.so.1")
            except OSError as exc:
                raise CudaDriverError(f"no CUDA driver (libcuda.so.1): {exc}") from None
            for name, argtypes in _DRIVER_SIGNATURES.items():
                function = getattr(lib, name)
                function.argtypes = argtypes
                function.restype = ctypes.c_int
            _driver_lib = lib
        return _driver_lib


def _check(result: int, what: str, error: type[Exception] = CudaDriverError) -> None:
    if result == 0:
        return
    message = ctypes.c_char_p()
    try:
        _driver().cuGetErrorString(result, ctypes.byref(message))
    except CudaDriverError:  # pragma: no cover - a result implies a driver
        pass
    text = message.value.decode(errors="replace") if message.value else "unknown error"
    raise error(f"{what} failed: CUDA error {result} ({text})")


def _attribute(device: Any, attribute: int) -> int:
    value = ctypes.c_int(0)
    _check(_driver().cuDeviceGetAttribute(ctypes.byref(value), attribute, device.ordinal),
           "cuDeviceGetAttribute")
    return value.value


def vmm_supported(device: Any) -> bool:
    """Can ``device`` make VMM memory exportable as a POSIX fd (needs a CUDA driver)?"""
    try:
        device = wp.get_device(device)
        if not device.is_cuda:
            return False
        vmm = _attribute(device, _CU_DEVICE_ATTRIBUTE_VIRTUAL_MEMORY_MANAGEMENT_SUPPORTED)
        fd = _attribute(device, _CU_DEVICE_ATTRIBUTE_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR_SUPPORTED)
        return bool(vmm and fd)
    except (CudaDriverError, RuntimeError, ValueError):
        return False


def _allocation_prop(device: Any) -> _MemAllocationProp:
    prop = _MemAllocationProp()
    prop.type = _CU_MEM_ALLOCATION_TYPE_PINNED
    prop.requestedHandleTypes = _CU_MEM_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR
    prop.location.type = _CU_MEM_LOCATION_TYPE_DEVICE
    prop.location.id = device.ordinal
    return prop


def vmm_granularity(device: Any) -> int:
    """The allocation granularity of VMM memory on ``device`` (typically 2 MiB): sizes are
    rounded up to it, so VMM suits arenas, not 4 KiB blocks."""
    device = _cuda_device(device)
    granularity = _size(0)
    prop = _allocation_prop(device)
    with device.context_guard:
        _check(_driver().cuMemGetAllocationGranularity(
            ctypes.byref(granularity), ctypes.byref(prop), _CU_MEM_ALLOC_GRANULARITY_MINIMUM),
            "cuMemGetAllocationGranularity")
    return int(granularity.value)


class _Keep:
    """Deleter of a view: holds its owner until the view is collected."""

    __slots__ = ("owner",)

    def __init__(self, owner: Any) -> None:
        self.owner = owner

    def __call__(self, ptr: int, size: int) -> None:
        self.owner = None


class VmmMemory:
    """Device memory made with ``cuMemCreate`` and mapped into this process.

    ``VmmMemory.create(device, nbytes)`` allocates and maps it read-write; :meth:`export_fd`
    gives a POSIX fd (``cuMemExportToShareableHandle``) to pass with ``SCM_RIGHTS``;
    ``VmmMemory.import_fd(fd, nbytes, device)`` maps a peer's export, read-only by default
    (``cuMemSetAccess`` with ``PROT_READ``: a kernel that writes through it faults instead of
    changing the publisher's bytes). The physical memory lives while any process holds a
    handle or mapping: an import outlives its exporter. :meth:`array` is a ``wp.array`` view
    that keeps this object alive; :meth:`close` (or collection) unmaps and releases.
    """

    def __init__(self, device: Any, handle: int, nbytes: int, read_only: bool) -> None:
        self.device = device
        self.nbytes = nbytes
        self.read_only = read_only
        self._handle = handle
        self.ptr = 0
        self._lock = threading.Lock()
        self._map(read_only)

    def _map(self, read_only: bool) -> None:
        lib = _driver()
        ptr = _u64(0)
        with self.device.context_guard:  # the VA reservation needs a current context
            _check(lib.cuMemAddressReserve(ctypes.byref(ptr), self.nbytes, 0, 0, 0),
                   "cuMemAddressReserve")
            try:
                _check(lib.cuMemMap(ptr, self.nbytes, 0, self._handle, 0), "cuMemMap")
                try:
                    access = _MemAccessDesc()
                    access.location.type = _CU_MEM_LOCATION_TYPE_DEVICE
                    access.location.id = self.device.ordinal
                    access.flags = (_CU_MEM_ACCESS_FLAGS_PROT_READ if read_only
                                    else _CU_MEM_ACCESS_FLAGS_PROT_READWRITE)
                    _check(lib.cuMemSetAccess(ptr, self.nbytes, ctypes.byref(access), 1),
                           "cuMemSetAccess")
                except BaseException:
                    lib.cuMemUnmap(ptr, self.nbytes)
                    raise
            except BaseException:
                lib.cuMemAddressFree(ptr, self.nbytes)
                lib.cuMemRelease(_u64(self._handle))
                self._handle = 0
                raise
        self.ptr = int(ptr.value)

    @classmethod
    def create(cls, device: Any, nbytes: int) -> VmmMemory:
        """``nbytes`` (rounded up to the granularity) of exportable device memory."""
        device = _cuda_device(device)
        if not vmm_supported(device):
            raise ExportUnavailableError(f"{device.alias} has no VMM with POSIX fd export")
        granularity = vmm_granularity(device)
        nbytes = -(-int(nbytes) // granularity) * granularity
        handle = _u64(0)
        prop = _allocation_prop(device)
        with device.context_guard:
            result = _driver().cuMemCreate(ctypes.byref(handle), nbytes, ctypes.byref(prop), 0)
        # Out of memory is DeviceMemoryError (the pool trims and retries); anything else means
        # the driver refuses VMM here (CudaDriverError: the pool falls back to legacy IPC).
        _check(result, "cuMemCreate",
               DeviceMemoryError if result == _CUDA_ERROR_OUT_OF_MEMORY else CudaDriverError)
        return cls(device, int(handle.value), nbytes, read_only=False)

    @classmethod
    def import_fd(cls, fd: int, nbytes: int, device: Any, read_only: bool = True) -> VmmMemory:
        """Map a peer's VMM export from its fd (the fd stays the caller's to close).

        Raises :class:`StaleBufferError` when the import fails (not a VMM export, another
        device, a size beyond the allocation).
        """
        device = _cuda_device(device)
        handle = _u64(0)
        with device.context_guard:
            _check(_driver().cuMemImportFromShareableHandle(
                ctypes.byref(handle), ctypes.c_void_p(int(fd)),
                _CU_MEM_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR),
                "cuMemImportFromShareableHandle", StaleBufferError)
        try:
            return cls(device, int(handle.value), int(nbytes), read_only=read_only)
        except CudaDriverError as exc:
            raise StaleBufferError(f"cannot map an imported VMM allocation: {exc}") from None

    def export_fd(self) -> int:
        """A new POSIX fd for this allocation (the caller closes it once sent)."""
        fd = ctypes.c_int(-1)
        with self._lock:
            if not self._handle:
                raise StaleBufferError("this VMM allocation was closed")
            with self.device.context_guard:  # called from the hand-off server's thread too
                _check(_driver().cuMemExportToShareableHandle(
                    ctypes.byref(fd), _u64(self._handle),
                    _CU_MEM_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR, 0), "cuMemExportToShareableHandle")
        return fd.value

    def array(self, offset: int = 0, nbytes: int | None = None) -> wp.array:
        """A 1-D uint8 ``wp.array`` over ``[offset, offset + nbytes)``; it keeps this alive."""
        nbytes = self.nbytes - offset if nbytes is None else nbytes
        if offset < 0 or nbytes <= 0 or offset + nbytes > self.nbytes:
            raise ValueError(f"[{offset}, {offset}+{nbytes}) is outside {self.nbytes} bytes")
        if not self.ptr:
            raise StaleBufferError("this VMM allocation was closed")
        return wp.array(ptr=self.ptr + offset, dtype=wp.uint8, shape=(nbytes,), device=self.device,
                        deleter=_Keep(self))

    def close(self) -> None:
        with self._lock:
            ptr, handle, self.ptr, self._handle = self.ptr, self._handle, 0, 0
        self._release(ptr, handle)

    def _release(self, ptr: int, handle: int) -> None:
        if sys.is_finalizing() or _driver_lib is None:
            return
        lib = _driver_lib
        with self.device.context_guard:
            if ptr:
                lib.cuMemUnmap(_u64(ptr), self.nbytes)
                lib.cuMemAddressFree(_u64(ptr), self.nbytes)
            if handle:
                lib.cuMemRelease(_u64(handle))

    def __del__(self) -> None:
        # Unreachable: nobody else can use it, so no lock (a finalizer takes none).
        ptr, handle, self.ptr, self._handle = self.ptr, self._handle, 0, 0
        try:
            self._release(ptr, handle)
        except Exception:  # pragma: no cover - interpreter shutdown
            pass


class HostRegistration:
    """Host memory pinned with ``cuMemHostRegister`` (so device-to-host copies into it are
    asynchronous); unpinned by :meth:`close` or collection. The memory stays the caller's."""

    def __init__(self, addr: int, nbytes: int) -> None:
        self.addr = addr
        self.nbytes = nbytes
        self._open = False
        _check(_driver().cuMemHostRegister_v2(ctypes.c_void_p(addr), nbytes,
                                              _CU_MEMHOSTREGISTER_PORTABLE),
               "cuMemHostRegister")
        self._open = True

    def close(self) -> None:
        if self._open and not sys.is_finalizing() and _driver_lib is not None:
            self._open = False  # (registered through the driver: it is loaded, no lock needed)
            _driver_lib.cuMemHostUnregister(ctypes.c_void_p(self.addr))

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # pragma: no cover
            pass


def register_host_memory(addr: int, nbytes: int) -> HostRegistration:
    """Pin ``nbytes`` of existing host memory at ``addr`` (e.g. a shared-memory arena that
    peers map) for asynchronous staging copies. Needs a CUDA context current or Warp's primary
    one initialised; raises :class:`CudaDriverError` without a driver."""
    wp.init()
    if wp.get_cuda_device_count() == 0:
        raise CudaDriverError("no CUDA device: host memory cannot be pinned")
    with wp.get_cuda_device(0).context_guard:
        return HostRegistration(addr, nbytes)


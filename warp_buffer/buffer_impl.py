"""``WarpBufferImpl``: a ``rosidl_buffer`` storage impl whose bytes are a Warp array.

The storage is a 1-D ``wp.array`` of uint8 on a Warp device, over a block leased from the
device's pool (:mod:`warp_buffer.pool`) or over memory imported from another process
(:mod:`warp_buffer.ipc`). The lease (or the import's hold) is owned by the impl and is the
``deleter`` of its array, so the memory is recycled, or the hold dropped, exactly when the impl
and the last array over it, views and DLPack consumers included, are gone;
:meth:`WarpBufferImpl.release` drops an import's hold at once. On cpu the ``wp.array`` is made
lazily (on first use), so allocating and importing cost no Warp call, and host copies
(``to_cpu``, ``clone``, ``to_buffer``) are plain NumPy copies at memory speed.

Write ordering lives here too. A buffer takes one write handle, ever; its write ends when the
handle is released, or the buffer is sealed (published) or read while the handle is still open.
On CUDA the end of the write is an event recorded on the writer's stream; on the cpu device Warp
kernels are synchronous, so the write is complete when the handle is released and nothing needs
recording.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import warp as wp

from rosidl_buffer.buffer_impl import BufferImplBase, CpuBufferImpl

from . import cuda, kernels
from .errors import DeviceUnavailableError, EmptyBufferError, HandleReleasedError, WriteHandleError
from .pool import get_pool, ipc_disabled

__all__ = ["WARP_BACKEND", "WarpBufferImpl", "WriteState", "resolve_device"]

WARP_BACKEND = "warp"
_new_impl = object.__new__


def resolve_device(device: Any = None) -> Any:
    """The ``wp.Device`` for ``device`` (a name, a ``wp.Device``, or None for Warp's default)."""
    try:
        return wp.get_device(device)
    except (ValueError, RuntimeError, TypeError) as exc:
        raise DeviceUnavailableError(
            f"Warp device {device!r} is not available here: {exc} "
            f"(available: {[d.alias for d in wp.get_devices()]})"
        ) from None


def wrap_bytes(ptr: int, nbytes: int, device: Any, owner: Any) -> wp.array:
    """A 1-D uint8 ``wp.array`` over ``nbytes`` at ``ptr``; ``owner(ptr, size)`` runs when the
    array (and every view of it) is collected, and keeps ``owner`` alive until then."""
    return wp.array(ptr=ptr, dtype=wp.uint8, shape=(nbytes,), device=device, deleter=owner)


class _HostKeep:
    """Deleter of a ``wp.array`` over private host memory (a clone's ``np.empty``): keeps the
    NumPy array alive until the ``wp.array`` and its views are gone."""

    __slots__ = ("base",)

    def __init__(self, base: np.ndarray) -> None:
        self.base = base

    def __call__(self, ptr: int = 0, size: int = 0) -> None:
        self.base = None


class _LazyLock:
    """The impl's ``_lock``, made on first use (an impl that is never exported, written through a
    handle or re-read, a cpu clone, never needs one). ``dict.setdefault`` is atomic, so two
    threads racing for the first use get the same lock."""

    def __get__(self, impl: Any, owner: Any = None) -> Any:
        if impl is None:
            return self
        return impl.__dict__.setdefault("_lock", threading.RLock())


class WriteState:
    """The state of one buffer's (only) write, shared by the impl and its write handle."""

    __slots__ = ("stream", "sealed")

    def __init__(self, stream: Any) -> None:
        # The CUDA stream the user named for the writes, None for "the current one" (resolved
        # when the write completes: Warp's current stream joined with torch's, see
        # cuda.write_stream); always None on cpu.
        self.stream = stream
        self.sealed: str | None = None  # why writes ended early: "published" or "read"


class WarpBufferImpl(BufferImplBase):
    """Warp-backed storage of a :class:`rosidl_buffer.Buffer` (backend type ``"warp"``).

    Build one with :func:`warp_buffer.allocate_buffer`; importing an export also yields one.
    ``array`` is the raw storage, without synchronisation: use the handles of :mod:`warp_buffer`
    (``from_output_buffer`` / ``from_input_buffer``) to write and read it in order.
    """

    # State every impl starts with, as class attributes: an import builds no more than it needs
    # (an instance attribute shadows one when it changes).
    _event: Any = None  # CUDA event recorded when the last write completed
    _writer: WriteState | None = None  # the open write, if any
    _write_opened = False
    _published = False
    _read = False
    _released = False
    _staging: Any = None  # host staging copy for CUDA exports
    cuda_uses: Any = None  # an import's readers' last-use events (cuda.BlockUses), CUDA only
    # Storage a private cpu clone does not have (set per instance by __init__ otherwise).
    _arr: wp.array | None = None
    _owner: Any = None
    _ptr = 0  # 0: a private clone's, read from its NumPy array when first needed
    _block: Any = None
    _import: Any = None
    _hold: Any = None
    _lock = _LazyLock()  # an instance attribute once made
    _reexport: WarpBufferImpl | None = None  # local copy of an import, to re-publish

    def __init__(self, array: wp.array | None, device: Any, *, block: Any = None,
                 imported: Any = None, hold: Any = None, ptr: int = 0, size: int = 0,
                 host: np.ndarray | None = None, owner: Any = None) -> None:
        self._arr = array
        self._owner = owner if owner is not None else hold  # deleter of the lazy array
        self._device = device
        self._ptr = array.ptr if array is not None else ptr
        self._size = array.shape[0] if array is not None else size
        self._block = block  # the leased pool block, None for imports
        self._import = imported  # the descriptor this buffer was imported from
        self._hold = hold  # an import's hold on the publisher's block
        self._host = host  # NumPy view of host storage, for plain host copies

    @classmethod
    def allocate(cls, nbytes: int, device: Any = None) -> WarpBufferImpl:
        """A new impl of ``nbytes`` (uninitialised) from the pool of ``device``."""
        if nbytes <= 0:
            raise EmptyBufferError(f"a warp buffer holds at least one byte, not {nbytes}")
        device = resolve_device(device)
        lease = get_pool(device).acquire(nbytes)  # validates the size first
        block = lease.block
        host = block.host
        if host is None:  # CUDA: the array now (its users are Warp calls anyway)
            return cls(wrap_bytes(block.data_ptr, nbytes, device, lease), device, block=block)
        # cpu: the wp.array is made on first use; the lease returns the block when both this
        # impl and that array are gone.
        return cls(None, device, block=block, ptr=block.data_ptr, size=nbytes,
                   host=host[:nbytes], owner=lease)

    @classmethod
    def imported(cls, ptr: int, size: int, device: Any, hold: Any, descriptor: Any,
                 host: np.ndarray | None) -> WarpBufferImpl:
        """An impl over imported memory; its ``wp.array`` is made on first use."""
        return cls(None, device, imported=descriptor, hold=hold, ptr=ptr, size=size, host=host)

    def _adopt_block(self) -> bool:
        """Move private host storage (a clone's) into a pool block, so it can be exported
        without a further copy to each peer: one copy, on the first export only. Call with the
        lock held, once the write ended (the bytes no longer change). Arrays already made over
        the private memory keep it alive and still read the same bytes. False when the pool
        gives private memory too (IPC disabled, no arena room)."""
        if self._block is not None or self._import is not None or not self._device.is_cpu:
            return self._block is not None and self._block.shared
        lease = get_pool(self._device).acquire(self._size)
        block = lease.block
        if not block.shared:
            return False  # the lease goes back with this frame
        host = block.host[:self._size]
        np.copyto(host, self._host)
        self._block, self._owner, self._host = block, lease, host
        self._ptr, self._arr = block.data_ptr, None
        return True

    @property
    def _array(self) -> wp.array:
        if self._released:
            raise HandleReleasedError("this buffer was released; its memory is no longer "
                                      "accessible through it")
        array = self._arr
        if array is None:
            with self._lock:
                if self._arr is None:
                    owner, ptr = self._owner, self._ptr
                    if owner is None and self._block is None and self._import is None:
                        owner = _HostKeep(self._host)  # a private clone's memory
                        ptr = self._ptr = self._host.ctypes.data
                    self._arr = wrap_bytes(ptr, self._size, self._device, owner)
                array = self._arr
        return array

    # -- BufferImplBase ------------------------------------------------------------------------
    def get_backend_type(self) -> str:
        return WARP_BACKEND

    def size(self) -> int:
        return self._size

    def _check_live(self) -> None:
        if self._released:
            raise HandleReleasedError("this buffer was released; its memory is no longer "
                                      "accessible through it")

    def to_cpu(self) -> CpuBufferImpl:
        """A CPU copy: a plain host copy on the cpu device (memory speed), a device-to-host copy
        after the writer's pending work on CUDA."""
        host = self._host
        if host is not None and not self._released:
            return CpuBufferImpl.wrap(host.copy())
        self._check_live()
        n = self._size
        out = np.empty(n, dtype=np.uint8)
        dst = wp.array(ptr=out.ctypes.data, dtype=wp.uint8, shape=(n,), device="cpu")
        stream = cuda.write_stream(self._device)
        self._wait_for_writer(stream)
        wp.copy(dst, self._array, stream=stream)
        done = stream.record_event()
        self._record_use(stream)
        wp.synchronize_event(done)  # the host needs the bytes: wait for this copy only
        return CpuBufferImpl.wrap(out)

    def clone(self) -> WarpBufferImpl:
        """A deep copy on the same device (a host copy on cpu, the copy kernel on CUDA); the copy
        is a fresh buffer (one write handle allowed, not published).

        On cpu the copy is private host memory (``ndarray.copy``: no pool call, so a clone runs
        at the memory's speed at every size); it moves into the pool's shared memory on its
        first export (one more copy then, none per peer)."""
        host = self._host
        if host is not None and not self._released:
            impl = _new_impl(WarpBufferImpl)  # no pool call, no lock: class defaults
            impl._device = self._device
            impl._size = self._size
            impl._host = host.copy()
            return impl
        return self._clone_pooled()

    def _clone_pooled(self) -> WarpBufferImpl:
        """A deep copy in a pool block (exportable as it is)."""
        self._check_live()
        other = WarpBufferImpl.allocate(self._size, self._device)
        if self._host is not None and other._host is not None:
            np.copyto(other._host, self._host)
            return other
        stream = None if self._device.is_cpu else cuda.write_stream(self._device)
        self._wait_for_writer(stream)
        kernels.copy_bytes(other._array, self._array, stream)
        self._record_use(stream)  # our block is not reused before the copy read it
        other._complete_write(stream)
        return other

    def seal(self) -> None:
        """End the write now (the transport calls it on every publish route): an open write
        handle is closed and its completion recorded; no write afterwards."""
        if self._sealed_host():
            return  # sealed already (every route seals; the first one did the work)
        self._mark_published()

    def _sealed_host(self) -> bool:
        """Host memory already published with no writer: sealing again would change nothing
        (read without the lock: no write handle opens once published)."""
        return self._published and self._writer is None and self._host is not None

    def release(self) -> None:
        """Drop an import's hold on the publisher's block now (idempotent); the imported buffer
        is unusable afterwards (:class:`HandleReleasedError`). A local buffer holds nothing to
        give back early (its memory returns to the pool when it and its views are collected,
        and an intra-process message shares it with its publisher): a no-op."""
        hold = self._hold
        if hold is None:
            return
        self._released = True  # a plain store: later accesses check it
        hold.release()  # CUDA imports: stream-ordered (ipc._CudaHold)

    # -- public properties ---------------------------------------------------------------------
    @property
    def array(self) -> wp.array:
        """The storage: a 1-D ``wp.array`` of uint8, ``size()`` long (no synchronisation)."""
        return self._array

    @property
    def device(self) -> str:
        """The Warp device of the storage, e.g. ``"cpu"`` or ``"cuda:0"``."""
        return self._device.alias

    @property
    def is_imported(self) -> bool:
        """True for a buffer imported from another process's export (read-only)."""
        return self._import is not None

    @property
    def is_published(self) -> bool:
        return self._published

    @property
    def is_read(self) -> bool:
        return self._read

    @property
    def is_released(self) -> bool:
        return self._released

    @property
    def is_exportable(self) -> bool:
        """Can this buffer be shared with a same-host process without a CPU copy?"""
        if self._import is not None:
            return True  # through a local copy
        if self._device.is_cpu:
            if self._block is None:  # a private clone: moves into the arena on export
                return not ipc_disabled()
            return bool(self._block.shared)
        return True  # CUDA: an IPC handle or a host staging block

    def __repr__(self) -> str:
        origin = "imported" if self._import is not None else "local"
        state = ", released" if self._released else ""
        return f"WarpBufferImpl(size={self.size()}, device={self.device!r}, {origin}{state})"

    # -- write / read ordering (used by the handles and the IPC layer) --------------------------
    def _open_writer(self, stream: Any) -> WriteState:
        with self._lock:
            self._check_live()
            if self._import is not None:
                raise WriteHandleError(
                    "this buffer was imported from another process and is read-only; "
                    "clone() it for a writable copy"
                )
            if self._published:
                raise WriteHandleError("this buffer was published; it can no longer be written")
            if self._read:
                raise WriteHandleError("this buffer was read; it can no longer be written")
            if self._write_opened:
                raise WriteHandleError("a buffer accepts one write handle, ever")
            self._write_opened = True
            self._writer = WriteState(stream)
            return self._writer

    def _close_writer(self, state: WriteState) -> None:
        with self._lock:
            if self._writer is state:
                self._writer = None
                self._complete_write(state.stream)

    def _seal(self, reason: str) -> None:
        """End an open write now (publish or read): record its completion; later accesses
        through the write handle raise."""
        with self._lock:
            writer, self._writer = self._writer, None
            if writer is not None:
                writer.sealed = reason
                self._complete_write(writer.stream)

    def _mark_published(self) -> None:
        with self._lock:
            self._seal("published")
            self._published = True

    def _mark_read(self) -> None:
        if self._import is not None:  # read-only from birth: no writer to seal, no lock needed
            self._check_live()
            self._read = True
            return
        with self._lock:
            self._check_live()
            self._seal("read")
            self._read = True

    def _complete_write(self, stream: Any) -> None:
        """Record that every write enqueued so far has completed (CUDA: an event on the stream
        the write ran on: ``stream``, or for None Warp's current stream joined with torch's;
        cpu kernels are synchronous, so there is nothing to record). The block's one event is
        re-recorded per write."""
        if self._device.is_cpu:
            return
        stream = cuda.write_stream(self._device, stream)
        event = self._block.event if self._block is not None else wp.Event(self._device)
        stream.record_event(event)
        self._event = event

    def _wait_for_writer(self, stream: Any) -> None:
        """Order work on ``stream`` (CUDA) after the writer's; nothing to wait for on cpu."""
        if self._device.is_cpu:
            return
        with self._lock:
            writer = self._writer
            if writer is not None:
                writes = cuda.write_stream(self._device, writer.stream)
                if writes.cuda_stream != stream.cuda_stream:
                    stream.wait_stream(writes)
            elif self._event is not None:
                stream.wait_event(self._event)

    def _record_use(self, stream: Any) -> None:
        """Work on ``stream`` read this buffer (a read handle's release, a clone's or staging
        copy): a local block is not reused, and an import's hold not dropped, before that work
        completed. Nothing to record on cpu (synchronous)."""
        if stream is None or self._device.is_cpu:
            return
        cuda.record_use(self._block if self._block is not None else self, stream)

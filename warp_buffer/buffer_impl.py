"""``WarpBufferImpl``: a ``rosidl_buffer`` storage impl whose bytes are a Warp array.

The storage is a 1-D ``wp.array`` of uint8 on a Warp device, over local memory or over memory
imported from another process (:mod:`warp_buffer.ipc`).

- Local memory (a block of the device's pool, :mod:`warp_buffer.pool`, or a cpu clone's private
  memory) has one owner, this impl, and a :class:`~warp_buffer.lease.Lease` that holds its
  state: the one write handle, the seal at publish, the readers' tokens, the return of the block
  to the pool once the lease is gone (impl, arrays and tokens alike).
- An import holds a token of the publisher's block (:class:`warp_buffer.attach.Hold`: a read
  lock in the publisher's arena): the impl's own token, which :meth:`WarpBufferImpl.release`
  drops; arrays and views made of the import hold it too, so what they read stays valid until
  they are gone.

On cpu the ``wp.array`` is made lazily (on first use), so allocating and importing cost no Warp
call, and host copies (``to_cpu``, ``clone``, ``to_buffer``) are plain NumPy copies at memory
speed. Write ordering: a buffer takes one write handle, ever; its write ends when the handle is
released, or the buffer is sealed (published) or read while the handle is still open. On CUDA
the end of the write is an event recorded on the writer's stream; on the cpu device Warp kernels
are synchronous, so the write is complete when the handle is released and nothing is recorded.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from rosidl_buffer.buffer_impl import BufferImplBase, CpuBufferImpl, array_at

from . import cuda, kernels
from .errors import DeviceUnavailableError, EmptyBufferError, HandleReleasedError, WriteHandleError
from .lease import PUBLISHED, READ, Lease, WriteState
from .pool import get_pool, ipc_disabled

__all__ = ["WARP_BACKEND", "WarpBufferImpl", "WriteState", "resolve_device", "wrap_bytes"]

WARP_BACKEND = "warp"
_new_impl = object.__new__


def resolve_device(device: Any = None) -> Any:
    """The ``wp.Device`` for ``device`` (a name, a ``wp.Device``, or None for Warp's default).

    Raises:
        DeviceUnavailableError: no such device here (a CUDA name where CUDA is not usable is
            refused before Warp is asked: Warp's native code would print to stderr first).
    """
    try:
        if isinstance(device, str) and device.startswith("cuda") and not wp.is_cuda_available():
            raise RuntimeError("CUDA is not available (no GPU or no driver)")
        return wp.get_device(device)
    except (ValueError, RuntimeError, TypeError) as exc:
        raise DeviceUnavailableError(
            f"Warp device {device!r} is not available here: {exc} "
            f"(available: {[d.alias for d in wp.get_devices()]})"
        ) from None


def wrap_bytes(ptr: int, nbytes: int, device: Any, owner: Any) -> wp.array:
    """A 1-D uint8 ``wp.array`` over ``nbytes`` at ``ptr`` that keeps ``owner`` alive (its
    ``deleter``: called with ``(ptr, size)`` when the array and every view of it are gone)."""
    return wp.array(ptr=ptr, dtype=wp.uint8, shape=(nbytes,), device=device, deleter=owner)


class _HostKeep:
    """Deleter of a ``wp.array`` over private host memory (a clone's ``np.empty``): keeps the
    NumPy array alive until the ``wp.array`` and its views are gone."""

    __slots__ = ("base",)

    def __init__(self, base: np.ndarray) -> None:
        self.base = base

    def __call__(self, ptr: int = 0, size: int = 0) -> None:
        self.base = None


_RELEASED = "this buffer was released; its memory is no longer accessible through it"


class WarpBufferImpl(BufferImplBase):
    """Warp-backed storage of a :class:`rosidl_buffer.Buffer` (backend type ``"warp"``).

    Build one with :func:`warp_buffer.allocate_buffer`; importing an export also yields one.
    ``array`` is the raw storage, without synchronisation: use the handles of :mod:`warp_buffer`
    (``from_output_buffer`` / ``from_input_buffer``) to write and read it in order.
    """

    # State every impl starts with, as class attributes: an import builds no more than it needs
    # (an instance attribute shadows one when it changes).
    #
    # Public attributes: plain attributes, not properties (the handles of ``warp_buffer.api``, the
    # IPC layer ``warp_buffer.ipc`` and the loans of ``warp_buffer.loan`` read them once or more
    # per message, and a property costs a Python frame). Only this class and its subclasses set
    # them, except where a line says otherwise.
    #: The lease of local memory (its write, its seal, its readers' tokens); None for an import
    #: (whose token is its hold on the publisher's block). Read by the handles (a loan's read
    #: handle, a write handle collected while open) and by ``ipc.export_buffer`` (seal, export).
    lease: Lease | None = None
    #: The leased pool block (the arena's for cpu, device memory for CUDA); None for an import
    #: and for a private clone until its first export moves it into one (:meth:`adopt_block`).
    #: Read by the IPC layer (what to describe), the handles (where a read's last use is
    #: recorded) and the loans (which pages to protect).
    block: Any = None
    #: Address of the first byte; 0 for a private clone until its array is first made (then the
    #: NumPy array's address is used). Read by host views (``api``, ``loan``) without a Warp call.
    data_ptr = 0
    #: Number of bytes (what :meth:`size` returns; the element is uint8, so also
    #: ``BufferImplBase.nbytes``, which this plain attribute overrides): read per export by the
    #: IPC layer without a call.
    nbytes = 0
    #: NumPy view of host storage (a 1-D uint8 array), for plain host copies and host views
    #: without a ``wp.array``; None for device memory. Read by the handles (``host_array``,
    #: ``to_buffer``), the IPC layer (is this a host export) and the loans (which replace it by
    #: their protected window).
    host: np.ndarray | None = None
    #: Host staging copy of a CUDA buffer (a cpu impl in the arena), made by the IPC layer on the
    #: first export to a peer without that GPU and kept here, so later exports reuse it.
    staging: WarpBufferImpl | None = None
    #: Local copy of an import, made by the IPC layer on its first re-export (published).
    reexport: WarpBufferImpl | None = None
    cuda_uses: Any = None  # an import's readers' last-use events (cuda.BlockUses), CUDA only
    #: The storage's ``wp.Device`` (:attr:`device` is its name), set by every constructor: the
    #: handles and the IPC layer read it to pick and check streams and to tell cpu from CUDA.
    wp_device: Any
    _import_event: Any = None  # an import's CUDA event (the publisher's write completion)
    _read = False  # an import was read (local memory: its lease knows)
    _import_published = False  # an import was published again (from a local copy)
    _released = False
    _arr: wp.array | None = None
    _owner: Any = None  # what the lazy array keeps alive: the lease, an import's hold, a clone's
    _import: Any = None
    _hold: Any = None  # an import's token (its hold on the publisher's block)

    def __init__(self, array: wp.array | None, device: Any, *, block: Any = None,
                 imported: Any = None, hold: Any = None, ptr: int = 0, size: int = 0,
                 host: np.ndarray | None = None, owner: Any = None) -> None:
        if array is not None:
            self._arr = array
        self.wp_device = device
        self.data_ptr = array.ptr if array is not None else ptr
        self.nbytes = array.shape[0] if array is not None else size
        self.block = block  # the leased pool block, None for imports
        self._import = imported  # the descriptor this buffer was imported from
        self._hold = hold
        self.host = host  # NumPy view of host storage, for plain host copies
        if imported is None:
            lease = owner if type(owner) is Lease else Lease(None, block, device)
            self.lease = lease
            self._owner = owner if owner is not None else lease
        else:
            self._owner = owner if owner is not None else hold

    @classmethod
    def allocate(cls, nbytes: int, device: Any = None, rearmable: bool = False
                 ) -> WarpBufferImpl:
        """A new impl of ``nbytes`` (uninitialised) from the pool of ``device``; ``rearmable``:
        its lease can be written again after a publish (a loan)."""
        if nbytes <= 0:
            raise EmptyBufferError(f"a warp buffer holds at least one byte, not {nbytes}")
        device = resolve_device(device)
        lease = get_pool(device).acquire(nbytes, rearmable)  # validates the size first
        block = lease.block
        host = block.host
        if host is None:  # CUDA: the array now (its users are Warp calls anyway)
            return cls(wrap_bytes(block.data_ptr, nbytes, device, lease), device, block=block,
                       owner=lease)
        # cpu: the wp.array is made on first use; the block goes back when this impl, that
        # array and every reader's token are gone (the lease is collected).
        return cls(None, device, block=block, ptr=block.data_ptr, size=nbytes,
                   host=host[:nbytes], owner=lease)

    @classmethod
    def imported(cls, ptr: int, size: int, device: Any, hold: Any, descriptor: Any,
                 host: np.ndarray | None) -> WarpBufferImpl:
        """An impl over imported memory holding ``hold``; its ``wp.array`` is made on first
        use. ``host`` (host memory) must keep ``hold`` in its base chain (see
        :func:`rosidl_buffer.buffer_impl.array_at`): views of it are the import's readers."""
        impl = _new_impl(cls)
        impl.wp_device = device
        impl.data_ptr, impl.nbytes = ptr, size
        impl._import, impl._hold, impl._owner, impl.host = descriptor, hold, hold, host
        return impl

    def adopt_block(self) -> bool:
        """Move private host storage (a clone's) into a pool block, so it can be exported
        without a further copy to each peer: one copy, on the first export only (the IPC layer
        calls it, under its copy lock). Call once the write ended (the bytes no longer change).
        Arrays already made over the private memory keep it alive and still read the same
        bytes. False when the pool gives private memory too (IPC disabled, no arena room)."""
        lease = self.lease
        if self.block is not None or lease is None or not self.wp_device.is_cpu:
            return self.block is not None and self.block.shared
        acquired = get_pool(self.wp_device).acquire(self.nbytes)
        block = acquired.block
        if not block.shared:
            return False  # the lease goes back with this frame
        host = block.host[:self.nbytes]
        np.copyto(host, self.host)
        # One lease for this owner: the new block joins it (the acquired one gives up its own).
        lease.adopt(block, acquired.pool)
        acquired.pool = None
        self.block, self._owner, self.host = block, lease, host
        self.data_ptr, self._arr = block.data_ptr, None
        return True

    @property
    def wp_array(self) -> wp.array:
        """The storage's own ``wp.array`` (1-D uint8, made on first use), which holds no
        reader's token: the handles (a write handle, a read handle of a plain buffer) and the
        IPC layer's staging copy use it; :attr:`array` is what users get (a loan's holds a
        token). Raises :class:`HandleReleasedError` once released."""
        array = self._arr
        if array is None:
            if self._released:
                raise HandleReleasedError(_RELEASED)
            owner, ptr = self._owner, self.data_ptr
            if self.block is None and self._import is None:
                if owner is self.lease:  # a private clone's memory: the array keeps it
                    owner = self._owner = _HostKeep(self.host)
                ptr = self.data_ptr = self.host.ctypes.data
            array = wrap_bytes(ptr, self.nbytes, self.wp_device, owner)
            if self._arr is None:  # (two threads may both build one: either is valid)
                self._arr = array
        elif self._released:
            raise HandleReleasedError(_RELEASED)
        return array

    # -- BufferImplBase ------------------------------------------------------------------------
    def get_backend_type(self) -> str:
        return WARP_BACKEND

    def size(self) -> int:
        return self.nbytes

    def seal_for_publish(self) -> tuple[str, int]:
        self.seal()  # (a loan's is its lease's own, bound in C)
        return WARP_BACKEND, self.nbytes

    def _check_live(self) -> None:
        if self._released:
            raise HandleReleasedError(_RELEASED)

    def to_cpu(self) -> CpuBufferImpl:
        """A CPU copy: a plain host copy on the cpu device (memory speed), a device-to-host copy
        after the writer's pending work on CUDA."""
        host = self.host
        if host is not None and not self._released:
            return CpuBufferImpl.wrap(host.copy())
        self._check_live()
        n = self.nbytes
        out = np.empty(n, dtype=np.uint8)
        dst = wp.array(ptr=out.ctypes.data, dtype=wp.uint8, shape=(n,), device="cpu")
        stream = cuda.write_stream(self.wp_device)
        self.wait_for_writer(stream)
        wp.copy(dst, self.wp_array, stream=stream)
        done = stream.record_event()
        self.record_use(stream)
        wp.synchronize_event(done)  # the host needs the bytes: wait for this copy only
        return CpuBufferImpl.wrap(out)

    def clone(self) -> WarpBufferImpl:
        """A deep copy on the same device (a host copy on cpu, the copy kernel on CUDA); the copy
        is a fresh buffer (one write handle allowed, not published).

        On cpu the copy is private host memory (``ndarray.copy``: no pool call, so a clone runs
        at the memory's speed at every size); it moves into the pool's shared memory on its
        first export (one more copy then, none per peer)."""
        host = self.host
        if host is not None and not self._released:
            impl = _new_impl(WarpBufferImpl)  # no pool call: class defaults, a private lease
            impl.wp_device = device = self.wp_device
            impl.nbytes = self.nbytes
            impl.host = host.copy()
            impl.lease = impl._owner = Lease(None, None, device)
            return impl
        return self.clone_pooled()

    def clone_pooled(self) -> WarpBufferImpl:
        """A deep copy in a pool block (exportable as it is): what :meth:`clone` makes of device
        memory, and the IPC layer's local copy of an import it re-exports."""
        self._check_live()
        other = WarpBufferImpl.allocate(self.nbytes, self.wp_device)
        if self.host is not None and other.host is not None:
            np.copyto(other.host, self.host)
            return other
        stream = None if self.wp_device.is_cpu else cuda.write_stream(self.wp_device)
        self.wait_for_writer(stream)
        kernels.copy_bytes(other.wp_array, self.wp_array, stream)
        self.record_use(stream)  # our block is not reused before the copy read it
        other.complete_write(stream)
        return other

    def seal(self) -> None:
        """End the write now: the lease's one transition to PUBLISHED (the transport calls it
        once per publish): an open write handle is closed and its completion recorded; no write
        afterwards. An import is read-only already: nothing to do."""
        lease = self.lease
        if lease is not None:
            lease.seal()

    def release(self) -> None:
        """Drop this buffer's own token (idempotent): an import's hold on the publisher's block
        ends once no array or view made of it holds the token any more; the buffer is unusable
        afterwards (:class:`HandleReleasedError`). A local buffer holds no token of its own to
        give back early (its memory returns to the pool when it, its arrays and its readers'
        tokens are gone): a no-op. ``Buffer.release`` then leaves the Buffer an
        :meth:`as_released` impl either way."""
        if self._import is None:
            return
        self._released = True  # a plain store: later accesses check it
        # Our references go; what views of the import keep stays theirs.
        self._hold = self._owner = self._arr = self.host = None

    def as_released(self) -> WarpBufferImpl:
        """A released impl of this device and size holding nothing (what a released share
        keeps): a WarpBufferImpl, so the tensor adapters reach it as one and get
        :class:`HandleReleasedError` from its accesses."""
        impl = _new_impl(WarpBufferImpl)
        impl.wp_device, impl.nbytes, impl._released = self.wp_device, self.nbytes, True
        return impl

    def reader_host(self) -> np.ndarray | None:
        """The bytes as a 1-D uint8 NumPy array over host memory (no copy) that holds a
        reader's token, for a consumer that only reads; None for device memory. Ends the write
        (a reader took the buffer): the fast path of a host reader, one call.

        Its flags say writable (legacy DLPack cannot carry read-only): an import's memory is
        mapped read-only, a published buffer's is not to be written."""
        host = self.host
        if host is None:
            if self._released:
                raise HandleReleasedError(_RELEASED)
            return None
        lease = self.lease
        if lease is None:  # an import: its host view holds the import's token already
            self._read = True
            return host
        if lease.state < READ or lease.writer is not None:
            lease.mark_read()
        # The token keeps the lease, and so the block, for as long as the view lives.
        return array_at(self.data_ptr or host.ctypes.data, self.nbytes, lease.hold())

    def reader_token(self) -> Any:
        """A reader's token (keep it while anything made over the bytes lives): the lease's
        (:meth:`warp_buffer.lease.Lease.hold`), or an import's own hold."""
        lease = self.lease
        return self._hold if lease is None else lease.hold()

    def owner_view(self) -> Any:
        """The owner's own view of the bytes, for a loan's cached writable views (the owner
        writes without a handle): host memory as a 1-D uint8 NumPy array that keeps this impl
        (and so its lease and block) alive, device memory as this impl's ``wp.array``. Not a
        reader's token: it does not keep a published loan from its next loan."""
        host = self.host
        if host is not None:
            return array_at(self.data_ptr or host.ctypes.data, self.nbytes, self)
        return self.wp_array

    # -- public properties ---------------------------------------------------------------------
    @property
    def array(self) -> wp.array:
        """The storage: a 1-D ``wp.array`` of uint8, ``size()`` long (no synchronisation)."""
        return self.wp_array

    @property
    def device(self) -> str:
        """The Warp device of the storage, e.g. ``"cpu"`` or ``"cuda:0"``."""
        return self.wp_device.alias

    @property
    def is_imported(self) -> bool:
        """True for a buffer imported from another process's export (read-only)."""
        return self._import is not None

    @property
    def is_published(self) -> bool:
        """True once a publish sealed the buffer (its lease is PUBLISHED); for an import, once
        it was published again (:meth:`mark_published`)."""
        lease = self.lease
        return lease.state == PUBLISHED if lease is not None else self._import_published

    @property
    def is_read(self) -> bool:
        """True once a reader took the buffer or it was published: no write can follow (its
        lease is READ or later; for an import, once it was read)."""
        lease = self.lease
        return lease.state >= READ if lease is not None else self._read

    @property
    def is_released(self) -> bool:
        """True once :meth:`release` ended an import's hold, and for a released share's impl
        (:meth:`as_released`); its data access then raises :class:`HandleReleasedError`."""
        return self._released

    @property
    def is_exportable(self) -> bool:
        """Can this buffer be shared with a same-host process without a CPU copy?"""
        block = self.block
        if block is not None:
            return bool(block.shared)  # (a CUDA block: an IPC handle or a host staging block)
        if self._import is not None:
            return True  # through a local copy
        return not ipc_disabled()  # a private clone: moves into the arena on export

    def __repr__(self) -> str:
        origin = "imported" if self._import is not None else "local"
        state = ", released" if self._released else ""
        return f"WarpBufferImpl(size={self.size()}, device={self.device!r}, {origin}{state})"

    # -- write / read ordering (used by the handles of warp_buffer.api and by warp_buffer.ipc) --
    @property
    def write_event(self) -> Any:
        """The CUDA event recorded when the write completed (an import's: the publisher's).
        The IPC layer reads it before a CUDA export (None: no write recorded yet) and sets an
        import's to the publisher's interprocess event."""
        lease = self.lease
        return self._import_event if lease is None else lease.event

    @write_event.setter
    def write_event(self, event: Any) -> None:
        lease = self.lease
        if lease is None:
            self._import_event = event
        else:
            lease.event = event

    def open_writer(self, stream: Any) -> WriteState:
        """Open the one write of this buffer (a :class:`~warp_buffer.api.WriteHandle` calls it
        when it is made); its completion is recorded on ``stream`` (None: the current streams)
        when it ends. Raises :class:`WriteHandleError` for an import or a second write."""
        self._check_live()
        lease = self.lease
        if lease is None:
            raise WriteHandleError("this buffer was imported from another process and is "
                                   "read-only; clone() it for a writable copy")
        return lease.open_write(stream)

    def close_writer(self, state: WriteState) -> None:
        """End the write ``state`` (:meth:`open_writer`'s) and record its completion: a write
        handle's release."""
        self.lease.close_write(state)  # type: ignore[union-attr]

    def mark_published(self) -> None:
        """Sealed by a publish: the lease's transition; an import is only marked (a re-export
        publishes a local copy). The IPC layer calls it on the import it re-exports and on the
        copies it makes (re-export, staging)."""
        lease = self.lease
        if lease is None:
            self._import_published = True
        else:
            lease.seal()

    def mark_read(self) -> None:
        """A reader took the buffer (``from_input_buffer``): its write ends (an open write
        handle is sealed), no write afterwards. Raises :class:`HandleReleasedError` once
        released."""
        self._check_live()
        lease = self.lease
        if lease is None:  # read-only from birth: no writer to seal
            self._read = True
        else:
            lease.mark_read()

    def complete_write(self, stream: Any) -> None:
        """Record that every write enqueued so far on ``stream`` completed (CUDA; None: Warp's
        current stream joined with torch's; cpu work is synchronous). The block's one event is
        re-recorded per write. Called after a copy into the buffer (``to_buffer``, a clone) and
        by the IPC layer before a CUDA export with no write recorded."""
        if not self.wp_device.is_cpu:
            self.lease.complete_write(stream)  # type: ignore[union-attr]

    def wait_for_writer(self, stream: Any) -> None:
        """Order work on ``stream`` (CUDA) after the writer's; nothing to wait for on cpu.
        Called by a read handle when it is made and before a copy out (``to_cpu``, a clone, the
        IPC layer's staging copy)."""
        if self.wp_device.is_cpu:
            return
        lease = self.lease
        if lease is not None:
            lease.order_after_write(stream)
        elif self._import_event is not None:
            stream.wait_event(self._import_event)

    def record_use(self, stream: Any) -> None:
        """Work on ``stream`` read this buffer (a read handle's release, a clone's or staging
        copy): a local block is not reused, and an import's hold not dropped, before that work
        completed. Nothing to record on cpu (synchronous)."""
        if stream is None or self.wp_device.is_cpu:
            return
        cuda.record_use(self.block if self.block is not None else self, stream)

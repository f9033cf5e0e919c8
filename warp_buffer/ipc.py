"""Same-host IPC: export a warp buffer as a descriptor, import a descriptor in another process.

Zero payload copies between processes of one user on one host:

- ``KIND_HOST``: a cpu buffer lives in a block of this process's arena (:mod:`warp_buffer.arena`);
  the importer reads it through its own mapping of that arena, fetched once per session
  (:mod:`warp_buffer.attach`), as a read-only ``wp.array`` on ``cpu``.
- ``KIND_CUDA_IPC``: a CUDA buffer whose peer has the same GPU (same device UUID, judged once per
  peer at discovery; MIG instances have their own) is opened from the allocation's CUDA IPC
  handle, once per (publisher session, block) (:class:`warp_buffer.cuda.ImportCache`, checked:
  a failed open raises :class:`StaleBufferError`), and ordered by an interprocess CUDA event. The
  importer drops its hold only once its readers' streams finished with the bytes
  (:func:`warp_buffer.cuda.release_after`), so the publisher never recycles memory still read.
- ``KIND_CUDA_VMM``: as ``KIND_CUDA_IPC``, for a block of VMM memory (the device exports it as a
  POSIX fd): the importer fetches the block's fd over the session's hand-off socket (once per
  block, :func:`warp_buffer.handoff.fetch_cuda_block`) and maps it read-only; the mapping keeps
  the memory alive after the publisher exits. The write's event still travels as a CUDA IPC
  event handle.
- ``KIND_CUDA_STAGING``: a CUDA buffer for a peer without that GPU (or without CUDA IPC, or in
  memory CUDA IPC cannot export: a user-set allocator, a mempool) is copied once into a host
  block (pinned with ``cuMemHostRegister``, so the copy is asynchronous), which the peer reads as
  in ``KIND_HOST`` (it arrives on ``cpu``).

The descriptor (:mod:`warp_buffer.descriptor`) is the record: it carries numbers only. An export
is the lease's transition to "published to a peer" (:meth:`warp_buffer.lease.Lease.export`: the
block's generation, and the delivery the peer owes). An import is one call of the session's
native core: it validates the descriptor against the session's geometry, takes its hold (a read
lock on the block's lock range: the import's token, :class:`warp_buffer.attach.Hold`), then checks
the block's generation: a recycled block raises :class:`StaleBufferError`, and is never delivered
as an empty or wrong buffer. Every failure is a typed :class:`~warp_buffer.errors.ExportError`.
"""

from __future__ import annotations

import logging
import os
import threading
import weakref
from typing import Any

import numpy as np
import warp as wp

from rosidl_buffer import Buffer
from rosidl_buffer.endpoint import local_host_id as _real_host_id

from . import attach as _attach
from . import cuda as _cuda
from . import descriptor as _desc
from . import handoff
from .arena import NO_PEER, PeerSlot, current_arena, existing_arena
from .buffer_impl import WarpBufferImpl, wrap_bytes
from .descriptor import _core
from .lease import PUBLISHED
from .errors import (
    DescriptorError,
    ExportBoundsError,
    ExportError,
    ExportUnavailableError,
    StaleBufferError,
)
from .pool import ipc_disabled, pool_stats, shutdown, trim_pools

__all__ = [
    "export_buffer",
    "import_buffer",
    "forget_session",
    "peer_slot",
    "forget_peer",
    "local_host_id",
    "local_user_id",
    "ipc_disabled",
    "pool_stats",
    "trim_pools",
    "shutdown",
]

_log = logging.getLogger(__name__)
_frombuffer, _UINT8 = np.frombuffer, np.dtype(np.uint8)
_describe_native = _core.describe
#: This process's pid without a system call (the core keeps it across forks)
_this_pid = _core.pid
_server_lock = threading.Lock()
# Local copies made once per buffer (a clone moved into a block, an import's re-export copy, a
# CUDA buffer's staging copy): made under this lock, so two exports never make two.
_copy_lock = threading.Lock()


def local_host_id() -> str:
    """This host's id as the warp backend sees it (``WARP_BUFFER_TEST_HOST_ID`` overrides it,
    for tests only: peers then look foreign)."""
    return os.environ.get("WARP_BUFFER_TEST_HOST_ID") or _real_host_id()


def local_user_id() -> int:
    """This user's id as the warp backend sees it (``WARP_BUFFER_TEST_USER_ID`` overrides it,
    for tests only). The kernel's credential checks always use the real uid."""
    override = os.environ.get("WARP_BUFFER_TEST_USER_ID", "").strip()
    if override:
        try:
            return int(override)
        except ValueError:
            pass
    return os.getuid()


def peer_slot(key: Any, pid: int, window: int = 0) -> PeerSlot | None:
    """The delivery slot of a peer subscription (``key``: its gid) in this process's arena;
    ``window``: how many of its latest descriptors it can still import (0: no limit)."""
    return current_arena().peer_slot(key, pid, window)


def forget_peer(key: Any) -> None:
    """The peer subscription ``key`` is gone: what was sent to it pins nothing any more."""
    arena = existing_arena()
    if arena is not None:
        arena.forget_peer(key)


# ------------------------------------------------------------------------------------ export
def _impl_of(buffer: Buffer | WarpBufferImpl) -> WarpBufferImpl:
    impl = buffer.get_impl() if isinstance(buffer, Buffer) else buffer
    if not isinstance(impl, WarpBufferImpl):
        raise ExportUnavailableError(
            f"only warp buffers can be exported, not {impl.get_backend_type()!r} ones"
        )
    return impl


def export_buffer(buffer: Buffer | WarpBufferImpl, kind: int | None = None, *,
                  peer: PeerSlot | None = None,
                  peer_device_uuids: frozenset[str] | set[str] = frozenset()) -> Any:
    """Export ``buffer`` for one same-host peer and return the descriptor to send it.

    The buffer is sealed if it was not yet (an open write handle is closed; no write after
    this: the transport seals it once per publish before). ``peer`` is the receiving
    subscription's delivery slot (:func:`peer_slot`): the block is then not recycled before that
    peer imported this descriptor or a later one, or is gone. Without it the block is only
    protected once imported. ``kind`` None picks the cheapest mechanism: host on cpu; on CUDA,
    CUDA IPC when the device supports it, its UUID is in ``peer_device_uuids`` and its memory
    can be exported (else staging: never an error). An imported buffer is re-exported from a
    local copy made once. Raises :class:`ExportUnavailableError` when the buffer cannot be
    exported.
    """
    impl = buffer.get_impl() if type(buffer) is Buffer else buffer
    lease = getattr(impl, "lease", None)
    block = None if lease is None else lease.block
    if lease is None or block is not None and block.arena is not None \
            and block.arena.pid != _this_pid():
        impl = _local_copy(_impl_of(impl))  # an import, or memory inherited at a fork
    else:
        if lease.state != PUBLISHED or lease.writer is not None:
            lease.seal()
        if kind is None and block is not None and block.shared and impl.host is not None:
            return _describe(_desc.KIND_HOST, impl, block, peer)  # (the common case, inline)
    return _export_local(impl, kind, peer_device_uuids, peer)


def _local_copy(impl: WarpBufferImpl) -> WarpBufferImpl:
    """The local copy ``impl`` is re-exported from (made once, published)."""
    impl.mark_published()
    with _copy_lock:
        if impl.reexport is None:
            copy = impl.clone_pooled()  # exportable as it is (a plain clone may not be)
            copy.mark_published()
            impl.reexport = copy
        return impl.reexport


def _export_local(impl: WarpBufferImpl, kind: int | None, peer_uuids: frozenset[str] | set[str],
                  peer: PeerSlot | None) -> Any:
    block = impl.block
    if block is not None and impl.host is not None:  # cpu, a block of the arena (or private)
        if kind is not None and kind != _desc.KIND_HOST:
            raise ExportUnavailableError(f"a cpu buffer cannot be exported as kind {kind!r}")
        if not block.shared:
            raise ExportUnavailableError("this buffer lives in private memory (IPC is disabled, "
                                         "or the arena had no room)")
        return _describe(_desc.KIND_HOST, impl, block, peer)
    device = impl.wp_device
    if device.is_cpu:  # a private clone moves into the arena now (once)
        if kind not in (None, _desc.KIND_HOST):
            raise ExportUnavailableError(f"a cpu buffer cannot be exported as kind {kind!r}")
        with _copy_lock:
            adopted = impl.adopt_block()
        if not adopted:
            raise ExportUnavailableError("this buffer lives in private memory (IPC is disabled, "
                                         "or the arena had no room)")
        return _describe(_desc.KIND_HOST, impl, impl.block, peer)
    device_word = _desc.uuid_word(device.uuid)
    if kind is None:
        if block.ipc_supported and device.uuid in peer_uuids:
            try:
                return _describe_cuda(impl, block, peer, device_word)
            except ExportUnavailableError as exc:
                # Memory CUDA IPC cannot export (a user-set allocator, a mempool): stage it.
                # publish() must not fail for it.
                _log.debug("CUDA IPC export unavailable (%s): staging instead", exc)
        kind = _desc.KIND_CUDA_STAGING
    elif kind in _desc.CUDA_ZERO_COPY:
        if kind != block.cuda_kind:
            raise ExportUnavailableError(f"this {device.alias} block is exported as kind "
                                         f"{block.cuda_kind}, not {kind}")
        return _describe_cuda(impl, block, peer, device_word)
    if kind != _desc.KIND_CUDA_STAGING:
        raise ExportUnavailableError(f"a CUDA buffer cannot be exported as kind {kind!r}")
    staging = impl.staging
    if staging is None:
        with _copy_lock:
            staging = impl.staging
            if staging is None:
                staging = impl.staging = _stage(impl)
    return _describe(kind, staging, staging.block, peer, device_word)


def _describe_cuda(impl: WarpBufferImpl, block: Any, peer: PeerSlot | None,
                   device_word: int) -> Any:
    """A same-GPU zero-copy descriptor (the block's kind: legacy CUDA IPC or VMM)."""
    if not block.ipc_supported:
        raise ExportUnavailableError(f"{impl.wp_device.alias} does not support CUDA IPC")
    mem_words = block.mem_words()  # ExportUnavailableError: memory it cannot export
    if impl.write_event is None:
        impl.complete_write(None)  # orders after whatever is pending on the current streams
    handles = mem_words + _desc.handle_words(block.ipc_event_handle())
    return _describe(block.cuda_kind, impl, block, peer, device_word, handles)


def _stage(impl: WarpBufferImpl) -> WarpBufferImpl:
    """Copy CUDA ``impl`` into a host block of the arena (pinned, so the copy is asynchronous)
    and wait for that copy only: the transport sends the descriptor synchronously after this, so
    the bytes must be there; nothing else on the device or stream is waited for."""
    staging = WarpBufferImpl.allocate(impl.size(), "cpu")
    host_block = staging.block
    if not host_block.shared:
        raise ExportUnavailableError("no arena room for a staging block")
    _pin(host_block)
    stream = _cuda.write_stream(impl.wp_device)
    impl.wait_for_writer(stream)
    done = _cuda.stage_to_host(impl.wp_array, staging.wp_array, stream)
    impl.record_use(stream)  # the source block is not reused before the copy read it
    wp.synchronize_event(done)
    staging.mark_published()
    return staging


def _pin(block: Any) -> None:
    """Pin a host staging block once (``cuMemHostRegister``; unpinned when the block is
    destroyed, before its pages are punched out). Unpinned memory still works, synchronously."""
    if getattr(block, "cuda_pin", None) is not None:
        return
    try:
        block.cuda_pin = _cuda.register_host_memory(block.data_ptr, block.capacity)
    except ExportError as exc:
        _log.debug("staging into pageable memory (%s)", exc)
        block.cuda_pin = False


def _describe(kind: int, impl: WarpBufferImpl, block: Any, peer: PeerSlot | None,
              device_word: int = 0, handles: tuple[int, ...] | None = None) -> Any:
    arena = block.arena
    if arena is None:  # a CUDA block gets its lock range with its first export
        try:
            block.ensure_arena_range()
        except OSError as exc:
            raise ExportUnavailableError(f"cannot export this block: {exc}") from None
        arena = block.arena
    if arena.pid != _this_pid():  # inherited at a fork: never describe or serve another's
        raise ExportUnavailableError(f"this block is in the memory of process {arena.pid}, "
                                     "which this process was forked from")
    if arena.server is None:
        with _server_lock:
            try:
                handoff.start_server(arena)
            except OSError as exc:
                raise ExportUnavailableError(f"cannot serve the arena to peers: {exc}") from None
    # The lease's export to the peer (its generation, the delivery it now waits for) and the
    # descriptor made of it: one C call.
    if _desc.loaded_type is None:
        _desc.descriptor_type()
    try:
        return _describe_native(impl.lease, peer, kind, impl.nbytes, arena.pid, arena.session,
                                device_word, handles)
    except OSError as exc:
        raise ExportUnavailableError(f"cannot export this block: {exc}") from None


# ------------------------------------------------------------------------------------ import
def import_buffer(descriptor: Any) -> WarpBufferImpl:
    """Read the export ``descriptor`` names in place and return a read-only
    :class:`WarpBufferImpl` over it (zero copies). Its hold on the block (its token) lasts until
    :meth:`WarpBufferImpl.release` and the collection of everything made of it (arrays, views),
    or until this process dies.

    Raises :class:`StaleBufferError` (recycled, or the publisher gone before this process
    attached to its memory), :class:`ForeignExportError` (another user serves the session, an
    unsealed arena), :class:`ExportBoundsError` (oversize), :class:`DescriptorError` (malformed)
    or :class:`ExportUnavailableError` (no such GPU here).
    """
    if type(descriptor) is not (_desc.loaded_type or _desc.descriptor_type()):
        raise DescriptorError(f"expected a {_desc.DESCRIPTOR_TYPE}, got "
                              f"{type(descriptor).__name__}")
    values = _desc.fields_of(descriptor)
    kind, owner_pid, session = values[1], values[3], values[4]
    arena = _attach.attached((owner_pid, session))
    if arena is None:
        _desc.check_names(values)  # nothing is fetched for a descriptor that names no export
        arena = _attach.attach(owner_pid, session)
    # Every field checked against the session, the block held, the delivery acknowledged, the
    # generation compared: one C call (warp_buffer._core.Session.import_block).
    hold = arena.import_block(values)
    if kind in _desc.CUDA_ZERO_COPY:
        try:
            return _import_cuda(descriptor, kind, values[6], values[7], values[10], values[11:],
                                hold)
        except BaseException:
            hold.release()
            raise
    # The host view holds the token (and through it the session's mapping): every view of the
    # import made from it keeps the block held and mapped.
    return WarpBufferImpl.imported(hold.address, values[7], _cpu or _cpu_device(), hold,
                                   descriptor, _frombuffer(hold, _UINT8))


_cpu: Any = None


def _cpu_device() -> Any:
    global _cpu
    if _cpu is None:
        _cpu = wp.get_device("cpu")
    return _cpu


# -- CUDA (the one place an import opens a CUDA handle) ------------------------------------
_devices_by_word: dict[int, Any] | None = None


def _cuda_device(device_word: int) -> Any:
    """The local CUDA device whose UUID digest is ``device_word`` (UUIDs, not PCI bus ids: MIG
    instances share one)."""
    global _devices_by_word
    if _devices_by_word is None:
        _devices_by_word = {_desc.uuid_word(d.uuid): d for d in wp.get_cuda_devices() if d.uuid}
    device = _devices_by_word.get(device_word)
    if device is None:
        raise ExportUnavailableError(f"no local CUDA device with uuid digest {device_word:#x} "
                                     "for a CUDA IPC export")
    if not device.is_ipc_supported:
        raise ExportUnavailableError(f"{device.alias} does not support CUDA IPC")
    return device


#: Opened CUDA IPC / VMM memory and events, once per (publisher session, block) here.
_cuda_imports = _cuda.ImportCache()


def forget_session(owner_pid: int, session: int) -> int:
    """Publisher session ``(owner_pid, session)`` is gone: drop its cached CUDA imports now
    (returns how many). The cache's references go only once the work queued so far on each
    device's current streams completed (:func:`warp_buffer.cuda.release_after`); a mapping an
    imported buffer still uses stays until that buffer's own stream-ordered release."""
    taken = _cuda_imports.take((owner_pid, session))
    by_device: dict[Any, list[Any]] = {}
    for value in taken:
        by_device.setdefault(getattr(value, "device", None), []).append(value)
    for device, values in by_device.items():
        stream = _cuda.write_stream(device) if device is not None else None
        _cuda.release_after(stream, values.clear)  # None: nothing queued, let go now
    return len(taken)


def _forget_session_key(key: tuple[int, int]) -> None:
    forget_session(*key)


# S5: a gone session is forgotten when its mapping is let go (attach.forget_idle) and as soon
# as its hand-off socket reports the publisher gone (both run handoff.session_gone); the
# backend adds on_endpoint_gone.
handoff.session_gone_hooks.append(_forget_session_key)


def _open_vmm(owner_pid: int, session: int, offset: int, mem_words: list[int], capacity: int,
              device: Any) -> Any:
    """Import VMM block ``offset`` of the session read-only (called holding the block, so
    the publisher cannot recycle it meanwhile); a ``wp.array`` of ``capacity`` bytes that keeps
    the import mapped. The received fd is closed at once (the import holds the memory)."""
    serial, nbytes = mem_words[0], mem_words[1]
    fd, got = handoff.fetch_cuda_block(owner_pid, session, offset, serial)
    try:
        if got != nbytes or got < capacity:
            raise ExportBoundsError(f"VMM block {offset:#x} of process {owner_pid} is {got} "
                                    f"bytes; the descriptor says {nbytes} (capacity {capacity})")
        memory = _cuda.VmmMemory.import_fd(fd, got, device, read_only=True)
    finally:
        os.close(fd)
    return memory.array(0, capacity)


def _import_cuda(descriptor: Any, kind: int, capacity: int, size: int, device_word: int,
                 handles: list[int], hold: _attach.Hold) -> WarpBufferImpl:
    device = _cuda_device(device_word)
    owner_pid, session_tag, block = descriptor.owner_pid, descriptor.session, descriptor.offset
    session = (owner_pid, session_tag)
    mem = _desc.handle_bytes(handles[:8])
    # Checked opens (StaleBufferError when the exporter is gone or the handle forged), one per
    # (session, block) while the block's handle (VMM: its allocation serial) is unchanged.
    opener = None
    if kind == _desc.KIND_CUDA_VMM:
        def opener() -> Any:
            return _open_vmm(owner_pid, session_tag, block, handles[:8], capacity, device)
    base = _cuda_imports.memory(session, block, mem, capacity, device, opener)
    event = _cuda_imports.event(session, block, _desc.handle_bytes(handles[8:]), device)
    impl = WarpBufferImpl.__new__(WarpBufferImpl)
    keep = _CudaHold(impl, hold, base, event)
    WarpBufferImpl.__init__(impl, wrap_bytes(base.ptr, size, device, keep), device,
                            imported=descriptor, hold=keep)
    impl.write_event = event
    return impl


class _CudaHold:
    """An imported CUDA buffer's token: keeps the opened allocation and event, and releases the
    arena hold (the lock the publisher's reclaim probes) only once the work queued on the
    current streams, and every read recorded on the buffer, completed (stream-ordered release:
    :func:`warp_buffer.cuda.release_after`, which takes no lock). Held by the import, the
    imported array (its deleter) and every view; it ends when the last of them is gone, or
    :meth:`release`."""

    __slots__ = ("hold", "keep", "impl", "__weakref__")

    def __init__(self, impl: WarpBufferImpl, hold: _attach.Hold, *keep: Any) -> None:
        self.hold = hold
        self.keep = keep
        self.impl = weakref.ref(impl)

    def release(self, *_args: Any) -> None:
        hold, self.hold = self.hold, None
        if hold is None or not hold.live:
            return
        keep, self.keep = self.keep, ()
        device = keep[0].device if keep else None
        if device is None:
            hold.release()
            return
        stream = _cuda.write_stream(device)
        impl = self.impl()
        uses = impl.cuda_uses if impl is not None else None
        if uses is not None:
            uses.order_after(stream)

        def drop(keep: tuple[Any, ...] = keep) -> None:
            hold.release()  # the mapping and event (keep) go with this closure

        _cuda.release_after(stream, drop)

    def __call__(self, ptr: int = 0, size: int = 0) -> None:
        """As the ``deleter`` of the imported array: it only keeps the token alive."""

    def __del__(self) -> None:
        try:
            self.release()
        except Exception:  # pragma: no cover - interpreter shutdown
            pass

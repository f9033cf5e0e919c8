"""Same-host IPC: export a warp buffer as a descriptor, import a descriptor in another process.

Zero payload copies between processes of one user on one host:

- ``KIND_HOST``: a cpu buffer lives in a block of this process's arena (:mod:`warp_buffer.arena`);
  the importer reads it through its own mapping of that arena, fetched once per session
  (:mod:`warp_buffer.attach`), as a read-only ``wp.array`` on ``cpu``.
- ``KIND_CUDA_IPC``: a CUDA buffer whose peer has the same GPU (same PCI bus id) is opened from
  the allocation's CUDA IPC handle and ordered by an interprocess CUDA event.
- ``KIND_CUDA_STAGING``: a CUDA buffer for a peer without that GPU (or without CUDA IPC) is copied
  once into a host block, which the peer reads as in ``KIND_HOST`` (it arrives on ``cpu``).

The descriptor (:mod:`warp_buffer.descriptor`) is the record: it carries numbers only. An import
validates it against the session's geometry, takes its hold (a read lock on the block's first
byte), then checks the block's generation: a recycled block raises :class:`StaleBufferError`, and
is never delivered as an empty or wrong buffer. Every failure is a typed
:class:`~warp_buffer.errors.ExportError`.
"""

from __future__ import annotations

import os
import threading
import weakref
from typing import Any

import warp as wp

from rosidl_buffer import Buffer
from rosidl_buffer.endpoint import local_host_id as _real_host_id

from . import attach as _attach
from . import descriptor as _desc
from . import handoff
from .arena import MAX_PEERS, NO_PEER, PeerSlot, current_arena, existing_arena
from .buffer_impl import WarpBufferImpl, wrap_bytes
from .errors import (
    DescriptorError,
    ExportBoundsError,
    ExportUnavailableError,
    StaleBufferError,
)
from .pool import ipc_disabled, pool_stats, shutdown, trim_pools

__all__ = [
    "export_buffer",
    "import_buffer",
    "peer_slot",
    "forget_peer",
    "local_host_id",
    "local_user_id",
    "ipc_disabled",
    "pool_stats",
    "trim_pools",
    "shutdown",
]

_PID_MAX = 1 << 22  # Linux's pid_max ceiling
_server_lock = threading.Lock()


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


def peer_slot(key: Any, pid: int) -> PeerSlot | None:
    """The delivery slot of a peer subscription (``key``: its gid) in this process's arena."""
    return current_arena().peer_slot(key, pid)


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
                  peer_pci_bus_ids: frozenset[str] | set[str] = frozenset()) -> Any:
    """Export ``buffer`` for one same-host peer and return the descriptor to send it.

    Seals the buffer (an open write handle is closed; no write after this). ``peer`` is the
    receiving subscription's delivery slot (:func:`peer_slot`): the block is then not recycled
    before that peer imported this descriptor or a later one, or is gone. Without it the block is
    only protected once imported. ``kind`` None picks the cheapest mechanism: host on cpu; on
    CUDA, CUDA IPC when the device supports it and its PCI bus id is in ``peer_pci_bus_ids``,
    else staging. An imported buffer is re-exported from a local copy made once. Raises
    :class:`ExportUnavailableError` when the buffer cannot be exported.
    """
    impl = _impl_of(buffer)
    with impl._lock:
        impl._mark_published()
        if impl._import is not None:
            if impl._reexport is None:
                copy = impl.clone()
                copy._mark_published()
                impl._reexport = copy
            impl = impl._reexport
        return _export_local(impl, kind, frozenset(peer_pci_bus_ids), peer)


def _export_local(impl: WarpBufferImpl, kind: int | None, peer_pcis: frozenset[str],
                  peer: PeerSlot | None) -> Any:
    device = impl._device
    block = impl._block
    if device.is_cpu:
        if kind not in (None, _desc.KIND_HOST):
            raise ExportUnavailableError(f"a cpu buffer cannot be exported as kind {kind!r}")
        if block is None or not block.shared:
            raise ExportUnavailableError("this buffer lives in private memory (IPC is disabled, "
                                         "or the arena had no room)")
        return _describe(_desc.KIND_HOST, impl, block, peer)
    if kind is None:
        kind = (_desc.KIND_CUDA_IPC if block.ipc_supported and device.pci_bus_id in peer_pcis
                else _desc.KIND_CUDA_STAGING)
    if kind == _desc.KIND_CUDA_IPC:
        if not block.ipc_supported:
            raise ExportUnavailableError(f"{device.alias} does not support CUDA IPC")
        if impl._event is None:
            impl._complete_write(None)  # orders after whatever is pending on the current stream
        handles = (_desc.handle_words(block.ipc_mem_handle())
                   + _desc.handle_words(block.ipc_event_handle()))
        return _describe(kind, impl, block, peer, _desc.pci_to_int(device.pci_bus_id), handles)
    if kind != _desc.KIND_CUDA_STAGING:
        raise ExportUnavailableError(f"a CUDA buffer cannot be exported as kind {kind!r}")
    staging = impl._staging
    if staging is None:
        staging = WarpBufferImpl.allocate(impl.size(), "cpu")
        if not staging._block.shared:
            raise ExportUnavailableError("no arena room for a staging block")
        stream = wp.get_stream(device)
        impl._wait_for_writer(stream)
        wp.copy(staging._array, impl._array, stream=stream)
        wp.synchronize_stream(stream)
        staging._mark_published()
        impl._staging = staging
    return _describe(kind, staging, staging._block, peer, _desc.pci_to_int(device.pci_bus_id))


def _describe(kind: int, impl: WarpBufferImpl, block: Any, peer: PeerSlot | None,
              pci: int = 0, handles: tuple[int, ...] = _desc.NO_HANDLES) -> Any:
    try:
        generation = block.begin_export()
    except OSError as exc:
        raise ExportUnavailableError(f"cannot export this block: {exc}") from None
    arena = block.arena
    if arena.server is None:
        with _server_lock:
            try:
                handoff.start_server(arena)
            except OSError as exc:
                raise ExportUnavailableError(f"cannot serve the arena to peers: {exc}") from None
    if peer is None:
        slot, sequence = NO_PEER, 0
    else:
        slot, sequence = peer.index, peer.next_sequence()
        block.pending[slot] = sequence
    return _desc.make((_desc.VERSION, kind, slot, arena.pid, arena.session, block.offset,
                       block.capacity, impl.size(), generation, sequence, pci) + handles)


# ------------------------------------------------------------------------------------ import
def import_buffer(descriptor: Any) -> WarpBufferImpl:
    """Read the export ``descriptor`` names in place and return a read-only
    :class:`WarpBufferImpl` over it (zero copies). Its hold on the block lasts until
    :meth:`WarpBufferImpl.release`, or until the impl and every array over it are collected, or
    this process dies.

    Raises :class:`StaleBufferError` (recycled, or the publisher gone before this process
    attached to its memory), :class:`ForeignExportError` (another user serves the session, an
    unsealed arena), :class:`ExportBoundsError` (oversize), :class:`DescriptorError` (malformed)
    or :class:`ExportUnavailableError` (no such GPU here).
    """
    if type(descriptor) is not _desc.descriptor_type():
        raise DescriptorError(f"expected a {_desc.DESCRIPTOR_TYPE}, got "
                              f"{type(descriptor).__name__}")
    (version, kind, slot, owner_pid, session, offset, capacity, size, generation, sequence,
     pci, *handles) = _desc.values_of(descriptor)
    if version != _desc.VERSION:
        raise DescriptorError(f"descriptor version {version} (this reader knows {_desc.VERSION})")
    if kind not in _desc.KINDS:
        raise DescriptorError(f"unknown descriptor kind {kind}")
    if not 0 < owner_pid < _PID_MAX or not 0 < session < 1 << 64 or generation <= 0:
        raise DescriptorError(f"descriptor names no export (pid {owner_pid}, session "
                              f"{session:#x}, generation {generation})")
    if slot != NO_PEER and not 0 <= slot < MAX_PEERS:
        raise DescriptorError(f"peer slot {slot}")
    arena = _attach.attach(owner_pid, session)
    cuda = kind == _desc.KIND_CUDA_IPC
    block_bytes = 4096 if cuda else capacity
    problem = arena.geometry.check_block(offset, block_bytes)
    if problem is not None:
        raise ExportBoundsError(f"descriptor of process {owner_pid}: {problem}")
    if not 0 < size <= capacity:
        raise ExportBoundsError(f"size {size} outside 1..{capacity}")
    arena.hold(offset, -1 if slot == NO_PEER else slot, sequence)
    hold = _attach.Hold(arena, offset)
    try:
        if arena.gens[arena.geometry.gen_index(offset)] != generation:
            raise StaleBufferError(f"block {offset:#x} of process {owner_pid} was recycled "
                                   "(a later publish reuses it)")
        if cuda:
            return _import_cuda(descriptor, capacity, size, pci, handles, hold)
        return WarpBufferImpl.imported(arena.address(offset), size, _cpu_device(), hold,
                                       descriptor, arena.host_array(offset, size))
    except BaseException:
        hold.release()
        raise


_cpu: Any = None


def _cpu_device() -> Any:
    global _cpu
    if _cpu is None:
        _cpu = wp.get_device("cpu")
    return _cpu


# -- CUDA (the one place an import opens a CUDA handle) ------------------------------------
def _cuda_device(pci: int) -> Any:
    wanted = _desc.pci_from_int(pci)
    for device in wp.get_cuda_devices():
        if device.pci_bus_id == wanted:
            if not device.is_ipc_supported:
                raise ExportUnavailableError(f"{device.alias} does not support CUDA IPC")
            return device
    raise ExportUnavailableError(f"no local GPU with PCI bus id {wanted!r} for a CUDA IPC export")


_cuda_maps: dict[tuple[int, int, int], weakref.ref[wp.array]] = {}
_cuda_maps_lock = threading.Lock()


def _import_cuda(descriptor: Any, capacity: int, size: int, pci: int, handles: list[int],
                 hold: _attach.Hold) -> WarpBufferImpl:
    device = _cuda_device(pci)
    key = (descriptor.owner_pid, descriptor.session, descriptor.offset)
    mem_handle = _desc.handle_bytes(handles[:8])
    with _cuda_maps_lock:  # a handle may not be opened twice in one context: once per block
        ref = _cuda_maps.get(key)
        base = ref() if ref is not None else None
        if base is None:
            try:
                base = wp.from_ipc_handle(mem_handle, wp.uint8, (capacity,), device=device)
            except RuntimeError as exc:
                raise StaleBufferError(f"cannot open the CUDA IPC handle of block "
                                       f"{descriptor.offset:#x}: {exc}") from None
            _cuda_maps[key] = weakref.ref(base, lambda _ref, key=key: _cuda_maps.pop(key, None))
    event = wp.event_from_ipc_handle(_desc.handle_bytes(handles[8:]), device=device)
    keep = _CudaHold(hold, base, event)
    array = wrap_bytes(base.ptr, size, device, keep)
    impl = WarpBufferImpl(array, device, imported=descriptor, hold=hold)
    impl._event = event
    return impl


class _CudaHold:
    """Deleter of an imported CUDA array: keeps the opened allocation and event, then releases
    the hold (the one place a CUDA import is released)."""

    __slots__ = ("hold", "keep")

    def __init__(self, hold: _attach.Hold, *keep: Any) -> None:
        self.hold = hold
        self.keep = keep

    def __call__(self, ptr: int = 0, size: int = 0) -> None:
        self.keep = ()
        self.hold.release()


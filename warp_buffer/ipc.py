"""Same-host IPC: export a warp buffer as a small record, import it in another process.

Zero payload copies between processes of one user on one host:

- ``HOST_SHM``: a cpu buffer already lives in a ``/dev/shm`` block (:mod:`warp_buffer.pool`);
  the importer maps the same file and wraps it as a ``wp.array`` on ``cpu``. Its mapping is
  copy-on-write (``MAP_PRIVATE``): reading shares the publisher's pages, a stray write by the
  reader changes only its own copy of that page, never the publisher's or other readers' bytes.
- ``CUDA_IPC``: a CUDA buffer whose peer has the same GPU (same PCI bus id) is opened from the
  allocation's CUDA IPC handle (``wp.from_ipc_handle``) and ordered by an interprocess CUDA event.
- ``CUDA_STAGING``: a CUDA buffer for a peer without that GPU (or without CUDA IPC) is copied once
  into a host block, which the peer maps as in ``HOST_SHM`` (it arrives on the ``cpu`` device).

An :class:`ExportRecord` carries numbers only (block id, 64-bit uid, owner pid and session, sizes,
host and user ids, device, CUDA handles); the importer rebuilds the file name from its own prefix,
validates every field, checks the file (owner, mode, size) before mapping anything, takes its
hold (``flock(LOCK_SH)``, dropped by the kernel if it dies), and checks the uid and the writer's
generation stamp in the block header. Every failure is a typed :class:`~warp_buffer.errors.
ExportError`; a recycled, missing or truncated export raises :class:`StaleBufferError`, and is
never delivered as an empty or wrong buffer.

Leak checks use :func:`shm_prefix`, :func:`list_exports` and :func:`sweep_orphans`; a clean
shutdown (:func:`shutdown`, also run at exit) removes every file of the process.
"""

from __future__ import annotations

import ctypes
import enum
import os
import threading
import time
import weakref
from dataclasses import asdict, dataclass
from typing import Any

import warp as wp

from rosidl_buffer import Buffer
from rosidl_buffer.endpoint import local_host_id as _real_host_id

from . import shm
from .buffer_impl import WarpBufferImpl, wrap_bytes
from .errors import (
    DescriptorError,
    ExportError,
    ExportBoundsError,
    ExportUnavailableError,
    ForeignExportError,
    StaleBufferError,
    SyncTimeoutError,
)
from .pool import MAX_BLOCK, MIN_BLOCK, _env_float, ipc_disabled, pool_stats, shutdown, trim_pools
from .shm import ExportFile, list_exports, shm_prefix, sweep_orphans

__all__ = [
    "RECORD_VERSION",
    "HOST_ID_MAX",
    "DEVICE_MAX",
    "ExportKind",
    "ExportRecord",
    "ExportFile",
    "export_buffer",
    "import_export",
    "local_host_id",
    "local_user_id",
    "ipc_disabled",
    "shm_prefix",
    "list_exports",
    "sweep_orphans",
    "pool_stats",
    "trim_pools",
    "shutdown",
]

RECORD_VERSION = 1
HOST_ID_MAX = 255  # bytes (UTF-8)
DEVICE_MAX = 32
CUDA_HANDLE_SIZE = 64
_PID_MAX = (1 << 22)  # Linux's pid_max ceiling


class ExportKind(enum.IntEnum):
    HOST_SHM = 0
    CUDA_IPC = 1
    CUDA_STAGING = 2


def local_host_id() -> str:
    """This host's id as the warp backend sees it (``WARP_BUFFER_TEST_HOST_ID`` overrides it,
    for tests only: peers then look foreign)."""
    return os.environ.get("WARP_BUFFER_TEST_HOST_ID") or _real_host_id()


def local_user_id() -> int:
    """This user's id as the warp backend sees it (``WARP_BUFFER_TEST_USER_ID`` overrides it,
    for tests only). File ownership checks always use the real uid."""
    override = os.environ.get("WARP_BUFFER_TEST_USER_ID", "").strip()
    if override:
        try:
            return int(override)
        except ValueError:
            pass
    return os.getuid()


@dataclass(frozen=True)
class ExportRecord:
    """Everything a same-host peer needs to re-attach to an export, and nothing it could use to
    open an arbitrary file: the path is rebuilt from ``owner_pid``, ``session`` and ``block_id``
    under the importer's own prefix."""

    kind: ExportKind
    size: int  # bytes of the buffer
    offset: int  # start of the buffer in the block's data
    capacity: int  # data bytes of the block (checked against the file)
    block_id: int
    uid: int  # per-publish id, checked against the block header
    generation: int  # the writer's completion stamp (host data)
    ack_slot: int  # header byte the importer sets (shm.NO_ACK_SLOT: none)
    owner_pid: int
    session: int
    user_id: int
    host_id: str
    device: str  # producing device ("cpu", "cuda:0")
    device_pci_bus_id: str = ""
    cuda_ipc_mem_handle: bytes = b""
    cuda_ipc_event_handle: bytes = b""
    version: int = RECORD_VERSION

    @property
    def path(self) -> str:
        return shm.block_path(self.owner_pid, self.session, self.block_id)

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form (bytes as hex), e.g. to hand a record to a child process."""
        out = asdict(self)
        out["kind"] = int(self.kind)
        out["cuda_ipc_mem_handle"] = self.cuda_ipc_mem_handle.hex()
        out["cuda_ipc_event_handle"] = self.cuda_ipc_event_handle.hex()
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ExportRecord:
        fields = dict(data)
        try:
            fields["kind"] = ExportKind(int(fields["kind"]))
            fields["cuda_ipc_mem_handle"] = bytes.fromhex(fields.get("cuda_ipc_mem_handle", ""))
            fields["cuda_ipc_event_handle"] = bytes.fromhex(fields.get("cuda_ipc_event_handle", ""))
            return cls(**fields)
        except (KeyError, TypeError, ValueError) as exc:
            raise DescriptorError(f"not an export record: {exc}") from None

    def validate(self) -> None:
        """Check every field on its own (no file is touched). Raises :class:`DescriptorError`
        for malformed fields and :class:`ExportBoundsError` for impossible sizes."""
        # Runs for every imported message: the messages are built only on failure (lambdas),
        # eager f-strings for all ~25 checks cost tens of us per import.
        def need(ok: bool, what: Any, error: type[Exception] = DescriptorError) -> None:
            if not ok:
                raise error(f"invalid export record: {what() if callable(what) else what}")

        for name in _RECORD_INTS:
            value = getattr(self, name)
            if type(value) is not int:  # fast path; bool and int subclasses checked below
                need(isinstance(value, int) and not isinstance(value, bool),
                     lambda: f"{name} is not an int")
        need(self.version == RECORD_VERSION, lambda: f"version {self.version} (this reader "
             f"knows {RECORD_VERSION})")
        need(self.kind in _EXPORT_KINDS, lambda: f"unknown kind {self.kind!r}")
        need(0 < self.owner_pid < _PID_MAX, lambda: f"owner pid {self.owner_pid}")
        need(0 < self.session < 1 << 64, lambda: f"session {self.session}")
        need(0 < self.block_id < 1 << 32, lambda: f"block id {self.block_id}")
        need(0 < self.uid < 1 << 64, lambda: f"uid {self.uid}")
        need(0 <= self.generation < 1 << 64, lambda: f"generation {self.generation}")
        need(0 <= self.user_id < 1 << 32, lambda: f"user id {self.user_id}")
        need(self.ack_slot < shm.ACK_SLOTS or self.ack_slot == shm.NO_ACK_SLOT,
             lambda: f"ack slot {self.ack_slot}")
        need(self.ack_slot >= 0, lambda: f"ack slot {self.ack_slot}")
        need(isinstance(self.host_id, str) and 0 < len(self.host_id.encode()) <= HOST_ID_MAX,
             "host id")
        need(isinstance(self.device, str) and 0 < len(self.device) <= DEVICE_MAX, "device")
        need(isinstance(self.device_pci_bus_id, str) and len(self.device_pci_bus_id) <= DEVICE_MAX,
             "device PCI bus id")
        bounds = ExportBoundsError
        need(MIN_BLOCK <= self.capacity <= MAX_BLOCK and self.capacity & (self.capacity - 1) == 0,
             lambda: f"capacity {self.capacity} is not a block size", bounds)
        need(0 < self.size <= self.capacity,
             lambda: f"size {self.size} outside 1..{self.capacity}", bounds)
        need(0 <= self.offset <= self.capacity - self.size,
             lambda: f"offset {self.offset} + size {self.size} beyond capacity {self.capacity}",
             bounds)
        if self.kind is ExportKind.CUDA_IPC:
            need(len(self.cuda_ipc_mem_handle) == CUDA_HANDLE_SIZE, "CUDA IPC memory handle")
            need(len(self.cuda_ipc_event_handle) == CUDA_HANDLE_SIZE, "CUDA IPC event handle")
            need(bool(self.device_pci_bus_id), "CUDA export without a PCI bus id")


_RECORD_INTS = ("size", "offset", "capacity", "block_id", "uid", "generation", "ack_slot",
                "owner_pid", "session", "user_id", "version")
_EXPORT_KINDS = tuple(ExportKind)


# ------------------------------------------------------------------------------------ export
def _impl_of(buffer: Buffer | WarpBufferImpl) -> WarpBufferImpl:
    impl = buffer.get_impl() if isinstance(buffer, Buffer) else buffer
    if not isinstance(impl, WarpBufferImpl):
        raise ExportUnavailableError(
            f"only warp buffers can be exported, not {impl.get_backend_type()!r} ones"
        )
    return impl


def export_buffer(buffer: Buffer | WarpBufferImpl, kind: ExportKind | None = None, *,
                  peer_pci_bus_ids: frozenset[str] | set[str] = frozenset()) -> ExportRecord:
    """Export ``buffer`` for one same-host peer and return the record to send it.

    Marks the buffer published (an open write handle is sealed; no write after this). Each call
    issues a fresh acknowledgement slot for one peer. ``kind`` None picks the cheapest mechanism:
    ``HOST_SHM`` on cpu; on CUDA, ``CUDA_IPC`` when the device supports it and its PCI bus id is
    in ``peer_pci_bus_ids``, else ``CUDA_STAGING``. An imported buffer is re-exported from a
    local copy made once. Raises :class:`ExportUnavailableError` when the buffer cannot be
    exported (private memory, a mechanism the device lacks).
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
        return _export_local(impl, kind, frozenset(peer_pci_bus_ids))


def _export_local(impl: WarpBufferImpl, kind: ExportKind | None,
                  peer_pcis: frozenset[str]) -> ExportRecord:
    device = impl._device
    block = impl._block
    if device.is_cpu:
        if kind not in (None, ExportKind.HOST_SHM):
            raise ExportUnavailableError(f"a cpu buffer cannot be exported as {kind!r}")
        if block is None or not block.shared:
            raise ExportUnavailableError("this buffer lives in private memory (no shared memory "
                                         "was available, or IPC is disabled)")
        return _record(ExportKind.HOST_SHM, impl, block, impl._generation, device.alias)
    if kind is None:
        kind = (ExportKind.CUDA_IPC if block.ipc_supported and device.pci_bus_id in peer_pcis
                else ExportKind.CUDA_STAGING)
    if kind is ExportKind.CUDA_IPC:
        if not block.ipc_supported:
            raise ExportUnavailableError(f"{device.alias} does not support CUDA IPC")
        if impl._event is None:
            impl._complete_write(None)  # orders after whatever is pending on the current stream
        return _record(kind, impl, block, 0, device.alias, device.pci_bus_id or "",
                       block.ipc_mem_handle(), block.ipc_event_handle())
    if kind is not ExportKind.CUDA_STAGING:
        raise ExportUnavailableError(f"a CUDA buffer cannot be exported as {kind!r}")
    staging = impl._staging
    if staging is None:
        staging = WarpBufferImpl.allocate(impl.size(), "cpu")
        if not staging._block.shared:
            raise ExportUnavailableError("no shared memory for a staging block")
        stream = wp.get_stream(device)
        impl._wait_for_writer(stream)
        wp.copy(staging._array, impl._array, stream=stream)
        wp.synchronize_stream(stream)
        staging._complete_write(None)
        staging._mark_published()
        impl._staging = staging
    return _record(ExportKind.CUDA_STAGING, staging, staging._block, staging._generation,
                   device.alias, device.pci_bus_id or "")


def _record(kind: ExportKind, impl: WarpBufferImpl, block: Any, generation: int, device: str,
            pci: str = "", mem_handle: bytes = b"", event_handle: bytes = b"") -> ExportRecord:
    uid = block.begin_export()
    header = block.header
    return ExportRecord(
        kind=kind, size=impl.size(), offset=0, capacity=block.capacity, block_id=block.block_id,
        uid=uid, generation=generation, ack_slot=block.issue_slot(),
        owner_pid=int(header.owner_pid), session=int(header.session), user_id=local_user_id(),
        host_id=local_host_id(), device=device, device_pci_bus_id=pci,
        cuda_ipc_mem_handle=mem_handle, cuda_ipc_event_handle=event_handle,
    )


# ------------------------------------------------------------------------------------ import
class _ImportHold:
    """Deleter of an imported array: unmaps the data and closes the file, which drops the
    reader's ``LOCK_SH`` (the kernel drops it too if the process dies)."""

    __slots__ = ("fd", "mapping", "keep")

    def __init__(self, fd: int, mapping: tuple[int, int] | None, keep: Any = None) -> None:
        self.fd = fd
        self.mapping = mapping
        self.keep = keep  # CUDA: the opened IPC allocation and event

    def __call__(self, ptr: int = 0, size: int = 0) -> None:
        mapping, self.mapping = self.mapping, None
        if mapping is not None:
            shm.unmap(*mapping)
        fd, self.fd = self.fd, -1
        if fd >= 0:
            os.close(fd)
        self.keep = None


def import_export(record: ExportRecord) -> WarpBufferImpl:
    """Map the export ``record`` describes and return a read-only :class:`WarpBufferImpl` over
    it (zero copies). Its hold on the block lasts until the impl and every array over it are
    collected, or this process dies.

    Raises :class:`ForeignExportError` (another host or user, a file not ours),
    :class:`StaleBufferError` (recycled, missing, truncated), :class:`ExportBoundsError`
    (oversize), :class:`DescriptorError` (malformed) or :class:`SyncTimeoutError`.
    """
    if not isinstance(record, ExportRecord):
        raise DescriptorError(f"expected an ExportRecord, got {type(record).__name__}")
    record.validate()
    host, user = local_host_id(), local_user_id()
    if record.host_id != host:
        raise ForeignExportError(f"export of host {record.host_id!r}; this is {host!r}")
    if record.user_id != user:
        raise ForeignExportError(f"export of user {record.user_id}; this is user {user}")
    cuda = record.kind is ExportKind.CUDA_IPC
    device = _cuda_device(record.device_pci_bus_id) if cuda else wp.get_device("cpu")
    fd, st = shm.open_block_file(record.owner_pid, record.session, record.block_id)
    try:
        # perf: the header is read with one pread and the ack written with one pwrite on the
        # already-open, already-locked fd, instead of an mmap + munmap of the header page per
        # import (same checks, same bytes; the shared page cache keeps them coherent with the
        # owner's mapping).
        header = _read_header(fd, record)
        _check_header(header, st.st_size, record, cuda,
                      reread=lambda: _read_header(fd, record))
        if record.ack_slot != shm.NO_ACK_SLOT:
            os.pwrite(fd, b"\x01", _ACKS_OFFSET + record.ack_slot)
        if cuda:
            base = _open_cuda_allocation(record, device)
            event = wp.event_from_ipc_handle(record.cuda_ipc_event_handle, device=device)
            hold = _ImportHold(fd, None, (base, event))
            array = wrap_bytes(base.ptr + record.offset, record.size, device, hold)
        else:
            try:
                addr = shm.map_fd(fd, record.capacity, shm.HEADER_SIZE, writable=True,
                                  private=True)
            except OSError as exc:  # e.g. ENOMEM for a forged huge block: a typed error
                raise ExportError(f"cannot map export {record.block_id} of process "
                                  f"{record.owner_pid} ({record.capacity} bytes): {exc}") from None
            hold = _ImportHold(fd, (addr, record.capacity))
            array = wrap_bytes(addr + record.offset, record.size, device, hold)
            event = None
    except BaseException:
        os.close(fd)
        raise
    impl = WarpBufferImpl(array, device, imported=record)
    impl._generation = record.generation
    impl._event = event
    return impl


_HEADER_BYTES = ctypes.sizeof(shm.BlockHeader)
_ACKS_OFFSET = shm.BlockHeader.acks.offset


def _read_header(fd: int, record: ExportRecord) -> shm.BlockHeader:
    """A private copy of the block header of ``fd`` (one pread)."""
    raw = os.pread(fd, _HEADER_BYTES, 0)
    if len(raw) < _HEADER_BYTES:
        raise StaleBufferError(f"export {record.block_id} of process {record.owner_pid} is "
                               f"truncated ({len(raw)} header bytes)")
    return shm.BlockHeader.from_buffer_copy(raw)


def _check_header(header: shm.BlockHeader, file_size: int, record: ExportRecord,
                  cuda: bool, reread: Any = None) -> None:
    """Validate ``header`` against ``record``; ``reread`` (a fresh copy of the header) is polled
    while waiting for the writer's generation stamp (``header`` itself when None: a mapping)."""
    where = f"export {record.block_id} of process {record.owner_pid}"
    if (header.magic != shm.MAGIC or header.version != shm.HEADER_VERSION
            or header.header_size != shm.HEADER_SIZE):
        raise StaleBufferError(f"{where} does not hold a warp_buffer block header")
    if (header.session != record.session or header.owner_pid != record.owner_pid
            or header.block_id != record.block_id):
        raise StaleBufferError(f"{where}: the block header names another block")
    expected_kind = shm.KIND_HEADER_ONLY if cuda else shm.KIND_HOST_DATA
    if header.kind != expected_kind:
        raise DescriptorError(f"{where}: a {record.kind.name} record for a block of kind "
                              f"{header.kind}")
    expected_size = shm.HEADER_SIZE + (0 if cuda else header.capacity)
    if file_size != expected_size:
        raise StaleBufferError(f"{where} is truncated or damaged: {file_size} bytes, "
                               f"its header says {expected_size}")
    if header.capacity != record.capacity:
        raise ExportBoundsError(f"{where}: the record claims a {record.capacity}-byte block; "
                                f"the block has {header.capacity} bytes")
    if header.uid != record.uid:
        raise StaleBufferError(f"{where} was recycled: uid {header.uid:#x}, the record has "
                               f"{record.uid:#x}")
    if not cuda and header.generation != record.generation:
        # The writer's stamp lands after its work; on the cpu device it is already there.
        deadline = time.monotonic() + _env_float("WARP_BUFFER_SYNC_TIMEOUT_S", 2.0)
        while header.generation != record.generation:
            if reread is not None:
                header = reread()
                if header.generation == record.generation:
                    break
            if time.monotonic() > deadline:
                raise SyncTimeoutError(f"{where}: the writer's stamp {record.generation} did "
                                       f"not arrive (header has {header.generation})")
            time.sleep(0.0005)


def _cuda_device(pci_bus_id: str) -> Any:
    for device in wp.get_cuda_devices():
        if device.pci_bus_id == pci_bus_id:
            if not device.is_ipc_supported:
                raise ExportUnavailableError(f"{device.alias} does not support CUDA IPC")
            return device
    raise ExportUnavailableError(f"no local GPU with PCI bus id {pci_bus_id!r} for a CUDA IPC "
                                 "export")


_cuda_maps: dict[tuple[int, int, int], weakref.ref[wp.array]] = {}
_cuda_maps_lock = threading.Lock()


def _open_cuda_allocation(record: ExportRecord, device: Any) -> wp.array:
    """The publisher's allocation opened from its CUDA IPC handle, once per block per process
    (a handle may not be opened twice in one context); closed when no import uses it."""
    key = (record.owner_pid, record.session, record.block_id)
    with _cuda_maps_lock:
        ref = _cuda_maps.get(key)
        base = ref() if ref is not None else None
        if base is None:
            try:
                base = wp.from_ipc_handle(record.cuda_ipc_mem_handle, wp.uint8,
                                          (record.capacity,), device=device)
            except RuntimeError as exc:
                raise StaleBufferError(f"cannot open the CUDA IPC handle of export "
                                       f"{record.block_id}: {exc}") from None
            _cuda_maps[key] = weakref.ref(base, lambda _ref, key=key: _cuda_maps.pop(key, None))
        return base
